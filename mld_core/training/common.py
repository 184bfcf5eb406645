"""Pieces both training stages share: threads, seeds, resumable train state, content-balanced sampling, the
choice of which modules train, and whose terms a run's weights carry."""

from __future__ import annotations

import json
import math
import os
import random
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from mld_core import inputs
from mld_core.bundled import model_folder
from mld_core.checkpoint import CheckpointError, load_config
from mld_core.data import terms
from mld_core.fileio import atomic_write

STATE_FILE = "train_state.pt"


def setup_torch(seed: int, threads: int | None) -> None:
    torch.set_num_threads(threads or os.cpu_count() or 1)
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def run_training_data(data: str, models: list, out: Path, resume: bool) -> list[dict]:
    """The ``training_data`` of a run's model (mld_core.data.terms): its data folder's terms, the models it reads
    (its --init, VAE, teacher: ModelConfig or None) and, resumed, what its earlier sittings read."""
    lists = [terms.of_folder(Path(data)), *(terms.of_model(m) for m in models if m is not None)]
    if resume:
        lists.append(recorded_training_data(Path(out)))
    return terms.union(*lists)


def recorded_training_data(out: Path) -> list[dict]:
    """What a run folder's sittings read: its model's record, else (a run begun before the records) the data and
    models its first sitting's train_config.json names; unknown when neither can be read."""
    try:
        recorded = load_config(out).training_data
    except (CheckpointError, OSError, ValueError, TypeError, KeyError):
        recorded = None
    if recorded:
        return recorded
    try:
        first = json.loads((out / "train_config.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return [terms.unrecorded(f"run {out.name}")]
    lists = [terms.of_folder(Path(first["data"]))] if first.get("data") else [terms.unrecorded(f"run {out.name}")]
    for key in ("init", "vae", "teacher"):  # the models it read, by folder (a VAE run's "vae" is its architecture)
        if isinstance(first.get(key), str) and first[key]:
            lists.append(_model_data(first[key]))
    return terms.union(*lists)


def _model_data(name: str) -> list[dict]:
    """A model folder's (or bundled model's) ``training_data``; unknown when it cannot be read."""
    try:
        return terms.of_model(load_config(model_folder(name)))
    except (CheckpointError, OSError, ValueError, TypeError, KeyError):
        return [terms.unrecorded(f"model {name}")]


def save_train_state(run: Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer, step: int,
                     extra: dict | None = None) -> None:
    """Everything --resume needs, as CPU tensors and plain values (loadable with weights_only=True, on any device)."""
    state = {"model": on_cpu(getattr(model, "module", model).state_dict()), "optimizer": on_cpu(optimizer.state_dict()),
             "step": step, "torch_rng": torch.get_rng_state(), "extra": json.dumps(extra or {})}
    atomic_write(Path(run) / STATE_FILE, lambda tmp: torch.save(state, tmp))


def on_cpu(value):
    """A state dict (nested dicts and lists of tensors) with every tensor copied to the CPU."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, dict):
        return {k: on_cpu(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(on_cpu(v) for v in value)
    return value


def load_train_state(run: Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer) -> tuple[int, dict]:
    path = Path(run) / STATE_FILE
    if not path.is_file():
        raise FileNotFoundError(f"nothing to resume: {path} does not exist")
    state = torch.load(path, map_location="cpu", weights_only=True)
    getattr(model, "module", model).load_state_dict(state["model"])  # copied onto the model's device
    optimizer.load_state_dict(state["optimizer"])
    torch.set_rng_state(state["torch_rng"])
    return int(state["step"]), json.loads(state["extra"])


def balanced_weights(labels: list, power: float) -> np.ndarray:
    """Sampling weights ~ count(label)^-power (power 0: uniform over items, 1: uniform over labels)."""
    counts = Counter(labels)
    w = np.array([counts[label] ** -power for label in labels], dtype=np.float64)
    return w / w.sum()


def checked_label_boost(boost) -> dict | None:
    """``label_boost`` as {label: factor}, each factor a number from 0.01 to 1000."""
    if boost is None:
        return None
    if not isinstance(boost, dict) or not boost:
        raise inputs.InputError(f"label_boost must be a non-empty {{label: factor}} object, got {boost!r}")
    return {str(label): inputs.number_in_range(f, f"label_boost[{label!r}]", 0.01, 1000.0) for label, f in boost.items()}


def checked_folder_setting(value, what: str) -> str | None:
    """A --config setting naming a folder (``caches_from``, a Draft's ``init``): None, or a non-empty string."""
    if value is not None and (not isinstance(value, str) or not value.strip()):
        raise inputs.InputError(f"{what} must be a folder's path, got {value!r}")
    return value


def check_boosted_labels(labels, boost: dict | None) -> None:
    """A label in ``boost`` that no clip of ``labels`` has is an error (a misspelt label would otherwise boost
    nothing)."""
    known = set(labels)
    for label in boost or {}:
        if label not in known:
            raise inputs.InputError(f"label_boost: no train clip is labelled {label!r} "
                                    f"(labels: {', '.join(sorted(known))})")


def boosted_weights(labels: list, balance_power: float, boost: dict | None) -> np.ndarray:
    """Sampling weights: content-balanced (balanced_weights), then the clips of each label in ``boost`` times
    its factor (check_boosted_labels first)."""
    check_boosted_labels(labels, boost)
    weights = balanced_weights(labels, balance_power)
    for label, factor in (boost or {}).items():
        weights = np.where(np.array([l == label for l in labels]), weights * factor, weights)
    return weights / weights.sum()


def checked_budget(steps, minutes, names: tuple[str, str] = ("steps", "minutes")) -> tuple[int | None, float | None]:
    """A run's --steps and --minutes checked (a whole number >= 1, a finite number > 0, or None) and as numbers;
    ``names`` name them in the messages."""
    if steps is not None:
        steps = inputs.int_in_range(steps, names[0], 1, 10**9)
    if minutes is not None:
        minutes = inputs.finite_number(minutes, names[1])
        if minutes <= 0:
            raise inputs.InputError(f"{names[1]} must be above 0, got {minutes:g}")
    return steps, minutes


class Budget:
    """Stops a loop after max_steps or max_minutes, whichever comes first; the time limit lets a run make at least
    one step (a model folder is never written from a run that made none)."""

    def __init__(self, max_steps: int | None, max_minutes: float | None):
        self.max_steps, self.max_minutes = checked_budget(max_steps, max_minutes)
        self.start = time.monotonic()
        self.first_step: int | None = None  # the step this run started from (a resumed run's saved step)

    def done(self, step: int) -> bool:
        if self.max_steps is not None and step >= self.max_steps:
            return True
        if self.first_step is None:
            self.first_step = step
        return (step > self.first_step and self.max_minutes is not None
                and (time.monotonic() - self.start) / 60 >= self.max_minutes)

    @property
    def minutes(self) -> float:
        return (time.monotonic() - self.start) / 60

    def progress(self, step: int) -> float:
        """How much of the budget is spent, 0..1 (the larger of the step and the time fraction)."""
        fractions = [0.0]
        if self.max_steps:
            fractions.append(step / self.max_steps)
        if self.max_minutes:
            fractions.append(self.minutes / self.max_minutes)
        return min(1.0, max(fractions))


def lr_factor(progress: float, decay_start: float, floor: float = 0.1) -> float:
    """Constant, then a cosine decay to ``floor`` over the last (1 - decay_start) of the budget."""
    if progress <= decay_start or decay_start >= 1.0:
        return 1.0
    t = (progress - decay_start) / (1.0 - decay_start)
    return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * min(1.0, t)))


def warmup_factor(step: int, warmup_steps: int) -> float:
    """A linear ramp over a run's first ``warmup_steps`` steps (1 after them, and always when 0): a run that starts a
    fresh optimiser on trained weights (--init) takes no full-rate steps on Adam's first, noisy moments."""
    return 1.0 if step >= warmup_steps else (step + 1) / warmup_steps


def set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Every parameter group's rate: ``lr`` times the group's ``lr_scale`` (1 when it has none)."""
    for group in optimizer.param_groups:
        group["lr"] = lr * group.get("lr_scale", 1.0)


def checked_module_names(modules) -> list | None:
    """A ``train_modules`` setting as a list of names, or None for all; anything else is refused."""
    if modules is None:
        return None
    if not isinstance(modules, (list, tuple)) or not modules or not all(isinstance(m, str) and m for m in modules):
        raise ValueError("train_modules must be a non-empty list of module names, or null for all")
    return list(modules)


def trainable_parameters(model: torch.nn.Module, modules: list | None, what: str = "model") -> list:
    """The parameters of the named top-level modules (all when ``modules`` is None); the rest are frozen."""
    if modules is None:
        return list(model.parameters())
    known = sorted({name.split(".")[0] for name, _ in model.named_parameters()})
    unknown = [m for m in modules if m not in known]
    if unknown:
        raise ValueError(f"train_modules: no module {', '.join(unknown)} in this {what} (it has {', '.join(known)})")
    trained = []
    for name, p in model.named_parameters():
        p.requires_grad_(name.split(".")[0] in modules)
        if p.requires_grad:
            trained.append(p)
    return trained


def check_resumed_modules(out: Path, modules: list | None) -> None:
    """--resume continues an optimiser over one set of modules: another ``train_modules`` is refused."""
    saved = out / "train_config.json"
    if saved.is_file():
        before = json.loads(saved.read_text()).get("train_modules")
        if before != modules:
            raise ValueError(f"--resume: {out} trained train_modules {before}; resume it with the same setting")
