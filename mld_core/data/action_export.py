"""Animated takes as training data: the 22 joints of each take -> a folder of BVH files + captions.csv, ready for
``python -m mld_core data prepare bvh FOLDER --captions FOLDER/captions.csv``.

The add-on samples an armature's Actions through its bone map (``blender_addon.scene.action_joints``) and hands
the joints here; this module knows nothing of Blender beyond its axes (Z up, the character facing -Y).
"""

from __future__ import annotations

import csv
import io
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mld_core.data.bandai import resample_joints
from mld_core.data.bvh_library import fill_missing_joints
from mld_core.fileio import OutputSet
from mld_core.inputs import InputError
from mld_core.motion.skeleton import JOINT_NAMES
from mld_core.rig.bone_maps import REQUIRED_JOINTS

CAPTION_PROPERTY = "mld_caption"  # an Action's custom property with its caption(s), one per line


@dataclass
class Take:
    name: str  # the Action's name
    joints: np.ndarray  # (T, 22, 3) Blender world positions (metres, Z up); NaN rows for unmapped joints
    fps: float
    captions: list[str] = field(default_factory=list)  # empty: from the name


def blender_to_model(joints: np.ndarray) -> np.ndarray:
    """Blender's axes (Z up, facing -Y) -> the model's (Y up, facing +Z): (x, y, z) -> (x, z, -y)."""
    return np.stack([joints[..., 0], joints[..., 2], -joints[..., 1]], axis=-1)


def caption_from_name(name: str) -> str:
    """'Walk_Tired.002' -> 'a person walk tired' (the words of an Action name)."""
    words = re.sub(r"(?<=[a-z])(?=[A-Z])", " ", re.sub(r"\.\d+$", "", name))
    words = re.sub(r"\s+", " ", re.sub(r"[^A-Za-z]+", " ", words)).strip().lower()
    return f"a person {words}" if words else ""


def file_name(name: str, taken: set) -> str:
    stem = re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_") or "action"
    out, n = stem, 1
    while out.lower() in taken:
        n += 1
        out = f"{stem}_{n}"
    taken.add(out.lower())
    return out


def take_bvh(joints_model: np.ndarray, fps: float):
    """(T, 22, 3) model-axis joints at ``fps`` -> a BVH writer for the canonical skeleton at 20 fps."""
    from mld_core.motion.bvh import write_canonical_bvh
    from mld_core.motion.features import joints_to_features
    from mld_core.motion.rotations import features_to_rotations

    joints = resample_joints(joints_model, fps, 20.0)
    quats, root = features_to_rotations(joints_to_features(joints))
    return lambda tmp: write_canonical_bvh(tmp, root, quats, 1.0 / 20.0)


def export_takes(takes: list[Take], folder, *, overwrite: bool = False) -> dict:
    """Write ``folder/NAME.bvh`` per usable take and ``folder/captions.csv``, all or none; returns
    {"written": [...], "skipped": {name: why}}. Existing files are never replaced unless ``overwrite``."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{folder} is a file, not a folder")
    rows, written, skipped, taken, staged = [], [], {}, set(), []
    for take in takes:
        why = _unusable(take)
        captions = [c for c in ([c.strip() for c in take.captions if c.strip()] or [caption_from_name(take.name)])
                    if c]
        if not why and not captions:
            why = f"no caption: name the Action in words or set its '{CAPTION_PROPERTY}' property"
        if why:
            skipped[take.name] = why
            continue
        name = file_name(take.name, taken) + ".bvh"
        staged.append((name, take))
        rows += [(name, c) for c in captions]
        written.append(name)
    if not written:
        raise InputError("no Action could be exported: " + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerows([("file", "caption"), *rows])
    try:
        with OutputSet(overwrite=overwrite) as outputs:
            for name, take in staged:
                joints = blender_to_model(np.asarray(take.joints, np.float64))
                fill_missing_joints(joints)
                outputs.stage(folder / name, take_bvh(joints, take.fps))
            outputs.stage(folder / "captions.csv", lambda tmp: Path(tmp).write_text(text.getvalue(), encoding="utf-8"))
    except FileExistsError as exc:
        where = str(exc).split(" exists")[0]
        raise InputError(f"{where} already exists: choose an empty folder (nothing was written)") from None
    return {"written": written, "skipped": skipped}


def _unusable(take: Take) -> str:
    j = np.asarray(take.joints, np.float64)
    if j.ndim != 3 or j.shape[1:] != (22, 3):
        return f"joints must be (T, 22, 3), got {j.shape}"
    if len(j) / take.fps < 2:
        return f"shorter than 2 s ({len(j)} frames at {take.fps:g} fps)"
    required = (*REQUIRED_JOINTS, "left_foot", "right_foot")  # the toes are not filled in
    missing = [n for n in required if not np.isfinite(j[:, JOINT_NAMES.index(n)]).all()]
    return f"the bone map has no {', '.join(missing)}" if missing else ""
