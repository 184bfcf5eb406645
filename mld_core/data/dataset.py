"""Loading any HumanML3D-format folder (HumanML3D, KIT-ML, or one written by ``data prepare``).

A folder holds::

    new_joint_vecs/ID.npy   (T, D) float features (D = 263 for HumanML3D, 251 for KIT-ML)
    texts/ID.txt            one caption per line: ``caption#word/POS ...#start#end`` (seconds; 0 0 = all)
    train.txt val.txt test.txt (all.txt)   one id per line
    Mean.npy Std.npy        (D,) normalisation statistics
    actions.json            optional: {"classes": [...], "clips": {id: label}, "styles": {id: style}}

``load_split`` returns plain :class:`Clip` records (unnormalised float32 features); :class:`MotionDataset`
turns them into training items (normalised, randomly cropped, one randomly chosen caption, whose time
span, when it has one, selects that part of the clip as in HumanML3D's loader); :func:`collate` pads a
batch and returns the lengths.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

__all__ = [
    "DatasetError",
    "Caption",
    "Clip",
    "parse_caption_line",
    "read_captions",
    "load_split",
    "load_mean_std",
    "read_actions",
    "guess_fps",
    "MotionDataset",
    "collate",
    "balanced_weights",
]

SPLITS = ("train", "val", "test", "all")


class DatasetError(ValueError):
    """A folder that is not (or not completely) in HumanML3D format."""


@dataclass(frozen=True)
class Caption:
    text: str
    start_s: float = 0.0
    end_s: float = 0.0
    tokens: tuple[str, ...] = ()

    @property
    def whole_clip(self) -> bool:
        """True when the caption describes the whole clip (HumanML3D writes 0.0#0.0; also any empty span)."""
        return not self.end_s > self.start_s

    def frames(self, fps: float, length: int) -> tuple[int, int]:
        """The [start, end) frame range this caption describes, clipped to a clip of ``length`` frames."""
        if self.whole_clip:
            return 0, length
        start = min(max(int(self.start_s * fps), 0), length)
        end = min(max(int(self.end_s * fps), start), length)
        return start, end


@dataclass
class Clip:
    id: str
    features: np.ndarray  # (T, D) float32, unnormalised
    captions: list[Caption]
    action: str | None = None
    style: str | None = None
    fps: float = 20.0

    @property
    def num_frames(self) -> int:
        return int(self.features.shape[0])


def parse_caption_line(line: str) -> Caption | None:
    """``caption#tokens#start#end`` -> Caption (None for an empty line). Missing fields mean the whole clip;
    NaN or unreadable times (present in a few HumanML3D files) also mean the whole clip."""
    line = line.strip()
    if not line:
        return None
    parts = line.split("#")
    text = parts[0].strip()
    if not text:
        return None
    tokens = tuple(parts[1].split()) if len(parts) > 1 else ()

    def number(k: int) -> float:
        try:
            v = float(parts[k]) if len(parts) > k and parts[k].strip() else 0.0
        except ValueError:
            return 0.0
        return v if math.isfinite(v) and v >= 0 else 0.0

    start, end = number(2), number(3)
    if not end > start:
        start, end = 0.0, 0.0
    return Caption(text, start, end, tokens)


def read_captions(path: Path) -> list[Caption]:
    with open(path, encoding="utf-8", errors="replace") as f:
        caps = [parse_caption_line(line) for line in f]
    return [c for c in caps if c is not None]


def guess_fps(dim: int) -> float:
    """HumanML3D (263-d) is 20 fps, KIT-ML (251-d) 12.5 fps."""
    return 12.5 if dim == 251 else 20.0


def read_actions(root) -> dict | None:
    """actions.json as {"classes": [...], "clips": {id: label}, "styles": {id: style}}; None when absent."""
    path = Path(root) / "actions.json"
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise DatasetError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("clips", {}), dict):
        raise DatasetError(f"{path} must hold an object with 'classes' and 'clips'")
    clips = {str(k): str(v) for k, v in data.get("clips", {}).items()}
    classes = [str(c) for c in data.get("classes", sorted(set(clips.values())))]
    styles = {str(k): str(v) for k, v in data.get("styles", {}).items()}
    return {"classes": classes, "clips": clips, "styles": styles}


def load_mean_std(root) -> tuple[np.ndarray, np.ndarray]:
    """(mean (D,), std (D,)) float32 from Mean.npy / Std.npy."""
    root = Path(root)
    try:
        mean = np.load(root / "Mean.npy").astype(np.float32)
        std = np.load(root / "Std.npy").astype(np.float32)
    except FileNotFoundError as exc:
        raise DatasetError(f"{root} has no Mean.npy / Std.npy ({exc.filename})") from None
    except ValueError as exc:
        raise DatasetError(f"cannot read Mean.npy / Std.npy in {root}: {exc}") from None
    if mean.ndim != 1 or mean.shape != std.shape:
        raise DatasetError(f"Mean.npy {mean.shape} and Std.npy {std.shape} must be matching vectors")
    if not (np.isfinite(mean).all() and np.isfinite(std).all()) or (std <= 0).any():
        raise DatasetError(f"Mean.npy / Std.npy in {root} hold non-finite or non-positive values")
    return mean, std


def split_ids(root, split: str) -> list[str]:
    path = Path(root) / f"{split}.txt"
    if not path.exists():
        raise DatasetError(f"{root} has no {split}.txt (expected one of {', '.join(SPLITS)})")
    return [line.strip() for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def load_split(root, split: str, min_frames: int = 1, max_frames: int | None = None,
               fps: float | None = None, captioned: bool = True) -> list[Clip]:
    """The clips of ``split`` (train/val/test/all) in a HumanML3D-format folder.

    Clips with fewer than ``min_frames`` feature rows, or (when ``max_frames`` is given) ``max_frames``
    or more (HumanML3D's loader uses min 40 and max 200 at 20 fps), are left out, as are ids whose
    feature or text file is missing or unreadable, whose features are not finite, or with no usable
    caption. Captions with a time span shorter than ``min_frames`` are dropped (as in HumanML3D).
    ``captioned=False`` keeps clips without a caption too (their ``captions`` empty): motion the VAE learns from.
    ``fps`` defaults to 20 for 263-d features and 12.5 for 251-d (KIT-ML).
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"dataset folder {root} does not exist")
    actions = read_actions(root)
    ids = split_ids(root, split)
    clips: list[Clip] = []
    dim = None
    problems: list[str] = []
    for cid in ids:
        try:
            feats = np.load(root / "new_joint_vecs" / f"{cid}.npy")
        except (OSError, ValueError) as exc:
            problems.append(f"{cid}: {type(exc).__name__}")
            continue
        if feats.ndim != 2 or not np.issubdtype(feats.dtype, np.floating):
            problems.append(f"{cid}: features of shape {feats.shape}")
            continue
        if dim is None:
            dim = feats.shape[1]
        elif feats.shape[1] != dim:
            raise DatasetError(f"{cid} has {feats.shape[1]}-d features, others {dim}-d")
        if not np.isfinite(feats).all():
            problems.append(f"{cid}: non-finite features")
            continue
        n = feats.shape[0]
        if n < min_frames or (max_frames is not None and n >= max_frames):
            continue
        rate = fps if fps is not None else guess_fps(feats.shape[1])
        try:
            caps = read_captions(root / "texts" / f"{cid}.txt")
        except OSError:
            if captioned:
                problems.append(f"{cid}: no texts/{cid}.txt")
                continue
            caps = []
        usable = []
        for c in caps:
            a, b = c.frames(rate, n)
            if c.whole_clip or (b - a >= min_frames and (max_frames is None or b - a < max_frames)):
                usable.append(c)
        if not usable and captioned:
            continue
        label = actions["clips"].get(cid) if actions else None
        style = actions["styles"].get(cid) if actions else None
        clips.append(Clip(cid, feats.astype(np.float32, copy=False), usable, label, style, rate))
    if problems:
        warnings.warn(f"{len(problems)} of {len(ids)} ids in {root}/{split}.txt were skipped, e.g. {problems[:3]}",
                      stacklevel=2)
    return clips


# --------------------------------------------------------------------------------------------------
# torch
# --------------------------------------------------------------------------------------------------


class MotionDataset(torch.utils.data.Dataset):
    """Training items from clips: one random caption, its span of the clip, a random crop, normalised.

    - ``max_frames``: longer spans are cropped to a random window of this many frames.
    - ``crop_frames=(lo, hi)``: instead, crop a random length uniformly in [lo, hi] (capped by the clip).
    - ``unit_length``: lengths are rounded down to a multiple of it (MLD/HumanML3D use 4).
    - ``seed``: items depend only on (seed, epoch, index) - set ``dataset.epoch`` each epoch; without a
      seed the torch RNG is used (seeded per DataLoader worker by torch).
    Each item: {"features": (T, D) float32 tensor, "length": T, "text": str, "action": str | None,
    "action_index": int (-1 without), "id": str, "start": first frame of the window in the clip}.
    """

    def __init__(self, clips: Sequence[Clip], mean: np.ndarray | None = None, std: np.ndarray | None = None,
                 *, max_frames: int | None = 196, crop_frames: tuple[int, int] | None = None,
                 unit_length: int = 1, classes: Sequence[str] | None = None, seed: int | None = None):
        if not clips:
            raise DatasetError("no clips to build a dataset from")
        self.clips = list(clips)
        dim = self.clips[0].features.shape[1]
        self.mean = np.zeros(dim, np.float32) if mean is None else np.asarray(mean, np.float32)
        self.std = np.ones(dim, np.float32) if std is None else np.asarray(std, np.float32)
        if self.mean.shape != (dim,) or self.std.shape != (dim,):
            raise DatasetError(f"mean/std of shape {self.mean.shape}/{self.std.shape} for {dim}-d features")
        if crop_frames is not None and not (1 <= crop_frames[0] <= crop_frames[1]):
            raise ValueError(f"crop_frames must be (lo, hi) with 1 <= lo <= hi, got {crop_frames}")
        if unit_length < 1:
            raise ValueError("unit_length must be >= 1")
        self.max_frames = max_frames
        self.crop_frames = crop_frames
        self.unit_length = unit_length
        labels = sorted({c.action for c in self.clips if c.action is not None})
        self.classes = list(classes) if classes is not None else labels
        self._class_index = {c: i for i, c in enumerate(self.classes)}
        self.seed = seed
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.clips)

    def _rng(self, index: int):
        if self.seed is None:
            return None
        return np.random.default_rng([self.seed, self.epoch, index])

    def _randint(self, rng, high: int) -> int:
        """Uniform integer in [0, high)."""
        if high <= 1:
            return 0
        if rng is None:
            return int(torch.randint(high, (1,)).item())
        return int(rng.integers(high))

    def __getitem__(self, index: int) -> dict:
        clip = self.clips[index]
        rng = self._rng(index)
        caption = clip.captions[self._randint(rng, len(clip.captions))]
        a, b = caption.frames(clip.fps, clip.num_frames)
        if b - a < 1:
            a, b = 0, clip.num_frames
        span = b - a
        if self.crop_frames is not None:
            lo, hi = self.crop_frames
            hi = min(hi, span)
            lo = min(lo, hi)
            if self.max_frames is not None:
                hi = min(hi, self.max_frames)
                lo = min(lo, hi)
            length = lo + self._randint(rng, hi - lo + 1)
        else:
            length = span if self.max_frames is None else min(span, self.max_frames)
        if self.unit_length > 1 and length >= self.unit_length:
            length = (length // self.unit_length) * self.unit_length
        start = a + self._randint(rng, span - length + 1)
        feats = (clip.features[start : start + length] - self.mean) / self.std  # (T, D)
        return {
            "features": torch.from_numpy(np.ascontiguousarray(feats, dtype=np.float32)),
            "length": int(length),
            "text": caption.text,
            "action": clip.action,
            "action_index": self._class_index.get(clip.action, -1) if clip.action is not None else -1,
            "id": clip.id,
            "start": int(start),
        }


def collate(batch: list[dict]) -> dict:
    """Pad a list of items to (B, T_max, D) with zeros; returns lengths (B,) and a valid-frame mask (B, T_max)."""
    if not batch:
        raise ValueError("empty batch")
    lengths = torch.tensor([b["length"] for b in batch], dtype=torch.long)  # (B,)
    dim = batch[0]["features"].shape[-1]
    t_max = int(lengths.max())
    feats = torch.zeros(len(batch), t_max, dim, dtype=batch[0]["features"].dtype)  # (B, T, D)
    for i, b in enumerate(batch):
        feats[i, : b["length"]] = b["features"]
    mask = torch.arange(t_max)[None, :] < lengths[:, None]  # (B, T)
    return {
        "features": feats,
        "lengths": lengths,
        "mask": mask,
        "texts": [b["text"] for b in batch],
        "actions": [b["action"] for b in batch],
        "action_index": torch.tensor([b["action_index"] for b in batch], dtype=torch.long),
        "ids": [b["id"] for b in batch],
    }


def balanced_weights(clips: Sequence[Clip], by: str = "action") -> torch.Tensor:
    """Per-clip sampling weights giving every label (``by`` = "action" or "style") the same total weight;
    for torch's WeightedRandomSampler. Clips without a label share one group."""
    keys = [getattr(c, by) for c in clips]
    counts: dict = {}
    for k in keys:
        counts[k] = counts.get(k, 0) + 1
    return torch.tensor([1.0 / counts[k] for k in keys], dtype=torch.double)
