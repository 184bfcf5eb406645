"""Loading the model once and keeping it (bpy-free).

:class:`PipelineCache` loads ``mld_core.pipeline.MLDPipeline`` for a (model folder, device) pair the first
time it is asked and hands back the same object afterwards. It keeps the two used last (Auto moves between the
default and another bundled model); a third replaces the one used longest ago. It is thread-safe: the worker thread
loads, the main thread may ``clear()``.
"""

from __future__ import annotations

import inspect
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any


class ModelLoadError(RuntimeError):
    """The model folder cannot be loaded; the message says which folder and why."""


def resolve_device(device: str) -> str:
    """'auto' -> cuda / mps / cpu, whichever torch can use; other names are checked for availability."""
    import torch

    device = (device or "cpu").lower()
    if device == "auto":
        if torch.cuda.is_available():
            return "cuda"
        mps = getattr(torch.backends, "mps", None)
        if mps is not None and mps.is_available():
            return "mps"
        return "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise ModelLoadError("Device 'cuda' was chosen but this PyTorch has no CUDA GPU; choose CPU in Preferences")
    if device == "mps":
        mps = getattr(torch.backends, "mps", None)
        if mps is None or not mps.is_available():
            raise ModelLoadError("Device 'mps' was chosen but Metal is not available; choose CPU in Preferences")
    return device


def set_threads(threads: int) -> None:
    """Use ``threads`` CPU threads for torch (0 leaves torch's default)."""
    if threads and threads > 0:
        import torch

        if torch.get_num_threads() != threads:
            torch.set_num_threads(int(threads))


def _folder(model_dir: str) -> Path:
    """A model folder given by path (``~`` expanded) or by a bundled model's name (mld_core.bundled); the path as
    given when it is neither."""
    from mld_core.bundled import UnknownModel, model_folder

    path = Path(os.path.expanduser(str(model_dir)))
    if path.exists():
        return path
    try:
        return model_folder(str(model_dir))
    except UnknownModel:
        return path


def default_loader(model_dir: str | None, device: str) -> Any:
    """Load an MLDPipeline from ``model_dir`` (None: the bundled default; or a bundled model's name) onto
    ``device``."""
    if model_dir is not None:
        path = _folder(model_dir)
        if not path.exists():
            raise ModelLoadError(f"Model folder not found: {path}")
        if not path.is_dir():
            raise ModelLoadError(f"The model path is not a folder: {path}")
        model_dir = str(path)
    from mld_core.pipeline import MLDPipeline

    kwargs = {}
    try:
        if "device" in inspect.signature(MLDPipeline.from_pretrained).parameters:
            kwargs["device"] = device
    except (TypeError, ValueError):
        pass
    try:
        pipe = MLDPipeline.from_pretrained(model_dir, **kwargs)
    except FileNotFoundError as exc:
        where = model_dir or "the bundled default model"
        raise ModelLoadError(f"Cannot load the model from {where}: {exc}") from exc
    if not kwargs and device != "cpu" and hasattr(pipe, "to"):
        pipe = pipe.to(device) or pipe
    return pipe


class PipelineCache:
    """The pipelines of the last ``keep`` (model folder, device) pairs asked for, reused while they stay."""

    def __init__(self, loader: Callable[[str | None, str], Any] = default_loader, keep: int = 2):
        self._loader = loader
        self._keep = max(1, int(keep))
        self._lock = threading.Lock()
        self._pipes: OrderedDict = OrderedDict()  # key -> pipeline, the one used last at the end
        self._last: tuple[str | None, str] | None = None
        self.load_seconds: float = 0.0
        self.loads = 0

    @staticmethod
    def key(model_dir: str | None, device: str) -> tuple[str | None, str]:
        folder = str(_folder(model_dir).resolve()) if model_dir else None
        return folder, device

    def get(self, model_dir: str | None = None, device: str = "cpu", threads: int = 0) -> Any:
        """The pipeline for ``model_dir`` on ``device``, loading it if it is not kept."""
        set_threads(threads)
        if device == "auto":
            device = resolve_device(device)
        elif device != "cpu":
            device = resolve_device(device)
        key = self.key(model_dir, device)
        with self._lock:
            if key in self._pipes:
                self._pipes.move_to_end(key)
                self._last = key
                return self._pipes[key]
            while len(self._pipes) >= self._keep:  # drop the oldest before loading the new one
                self._pipes.popitem(last=False)
            start = time.perf_counter()
            pipe = self._loader(model_dir, device)
            self.load_seconds = time.perf_counter() - start
            self.loads += 1
            self._pipes[key], self._last = pipe, key
            return pipe

    @property
    def loaded(self) -> bool:
        return bool(self._pipes)

    def describe(self) -> str:
        """The pipeline used last: its model id, device and load time."""
        with self._lock:
            pipe = self._pipes.get(self._last) if self._last is not None else None
            if pipe is None:
                return "not loaded"
            folder, device = self._last
        model_id = getattr(pipe, "model_id", None) or (Path(folder).name if folder else "default")
        return f"{model_id} on {device} (loaded in {self.load_seconds:.1f} s)"

    def clear(self) -> None:
        with self._lock:
            self._pipes.clear()
            self._last = None
