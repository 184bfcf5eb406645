"""Takes for game engines (numpy only): the export settings and their checks, the engine's bone names, the files an
export writes, and the pose each exported take plays, as keys (root motion applied, a loop's seam closed).

The Blender side (``blender_addon/scene/export_takes.py``) samples each Action on the armature into armature-space
matrices (T, B, 4, 4), calls :func:`export_pose` and :func:`pose_keys`, keys a renamed copy of the armature and runs
Blender's own FBX / glTF / BVH exporters on it. Docs: docs/game_engines.md.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from mld_core.inputs import InputError
from mld_core.rig import root_motion as rm
from mld_core.rig.bone_maps import PRESET_DIR, load_presets
from mld_core.rig.retarget import RigRest, _topological_order

FORMATS = ("fbx", "glb", "bvh")
ONE_FILE_FORMATS = ("fbx", "glb")  # formats that hold several takes as separate animations
EXTENSIONS = {"fbx": ".fbx", "glb": ".glb", "bvh": ".bvh"}
NAMING_DIR = PRESET_DIR / "engine"
NAMINGS = ("canonical", "mixamo", "ue5", "unity")


# --------------------------------------------------------------------------------------------------------------
# Engine bone names.


@dataclass(frozen=True)
class EngineNaming:
    """An engine's bone names: ``bones`` canonical joint -> name, ``root`` the root bone's name."""

    name: str
    label: str
    description: str
    root: str
    bones: dict


def load_namings(directory: str | Path | None = None) -> dict[str, EngineNaming]:
    """Every naming in ``presets/engine/``; one with ``"bones_from": PRESET`` takes each joint's first name from that
    bone-map preset (the names a rig of that kind is detected by)."""
    directory = Path(directory) if directory is not None else NAMING_DIR
    presets = None
    out = {}
    for path in sorted(directory.glob("*.json")):
        data = json.loads(path.read_text(encoding="utf-8"))
        bones = dict(data.get("bones", {}))
        if "bones_from" in data:
            presets = presets or load_presets()
            bones = {joint: names[0] for joint, names in presets[data["bones_from"]].bones.items()}
        out[data["name"]] = EngineNaming(data["name"], data.get("label", data["name"]), data.get("description", ""),
                                         data["root"], bones)
    return {name: out[name] for name in NAMINGS if name in out} | out


def bone_renames(naming: str, bone_map: Mapping[str, str], bone_names: Sequence[str], *, root: bool = False
                 ) -> tuple[dict[str, str], str | None]:
    """({bone: exported name} for the bones that play a joint, the root bone's name or None) under ``naming``.

    bone_map: canonical joint -> bone of the rig; bone_names: every bone of the rig (the others keep their names).
    Raises InputError when two bones would end up with one name."""
    table = load_namings()[naming]
    renames = {bone: table.bones[joint] for joint, bone in bone_map.items() if joint in table.bones}
    root_name = table.root if root else None
    final: dict[str, str] = {}
    for bone in list(bone_names) + ([None] if root_name else []):
        new = root_name if bone is None else renames.get(bone, bone)
        if new in final:
            first, this = (repr(b) if b is not None else "the root bone" for b in (final[new], bone))
            raise InputError(f"--bone-names {naming}: {first} and {this} would both be called {new!r}; "
                             "rename one of them in the rig")
        final[new] = bone
    return renames, root_name


# --------------------------------------------------------------------------------------------------------------
# Settings.


def _one_of(value, allowed: Sequence[str], what: str) -> str:
    text = str(value).strip().lower()
    if text not in allowed:
        raise InputError(f"{what}: unknown value {value!r}; use {', '.join(allowed[:-1])} or {allowed[-1]}")
    return text


@dataclass(frozen=True)
class ExportSettings:
    """What an export writes: ``formats`` (of :data:`FORMATS`), ``root_motion`` (of ``root_motion.MODES``),
    ``yaw`` (the turning goes with the travel), ``bone_names`` (of :data:`NAMINGS`), ``one_file`` (one file per
    format holding every take, where the format can: FBX, GLB; BVH stays one file per take)."""

    formats: tuple = ("fbx",)
    root_motion: str = "object"
    yaw: bool = False
    bone_names: str = "canonical"
    one_file: bool = False

    def __post_init__(self) -> None:
        if not self.formats:
            raise InputError("--export: name at least one format (fbx, glb or bvh)")
        for fmt in self.formats:
            _one_of(fmt, FORMATS, "--export")
        _one_of(self.root_motion, rm.MODES, "--root-motion")
        _one_of(self.bone_names, NAMINGS, "--bone-names")

    @classmethod
    def parse(cls, formats: Iterable[str], root_motion: str = "object", yaw: bool = False,
              bone_names: str = "canonical", one_file: bool = False) -> "ExportSettings":
        """From the batch's flags: ``formats`` like ``["fbx", "glb,bvh"]`` (repeated or comma-separated)."""
        wanted: list[str] = []
        for item in formats:
            for part in str(item).split(","):
                if not part.strip():
                    continue
                fmt = _one_of(part, FORMATS, "--export")
                if fmt in wanted:
                    raise InputError(f"--export: {fmt} is named twice; each format is written once")
                wanted.append(fmt)
        return cls(tuple(wanted), _one_of(root_motion, rm.MODES, "--root-motion"), bool(yaw),
                   _one_of(bone_names, NAMINGS, "--bone-names"), bool(one_file))

    @property
    def motion(self) -> rm.RootMotion:
        return rm.RootMotion(self.root_motion, self.yaw)

    def to_dict(self) -> dict:
        return {"formats": list(self.formats), "root_motion": self.root_motion, "yaw": self.yaw,
                "bone_names": self.bone_names, "one_file": self.one_file}


# --------------------------------------------------------------------------------------------------------------
# Files.


@dataclass(frozen=True)
class ExportFile:
    """One file an export writes: its format, path and the takes (Action names) it holds, in order; ``shared``:
    the one file of its format holding every take."""

    format: str
    path: Path
    takes: tuple
    shared: bool = False

    @property
    def label(self) -> str:
        """How messages name it: ``--export fbx (walks_s0)`` or ``--export glb (every take)``."""
        return f"--export {self.format} ({'every take' if self.shared else self.takes[0]})"


def file_stem(take: str) -> str:
    """A file name for a take: its name with anything but letters, digits, '.', '-' and '_' made '_'."""
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", take).strip(". ")
    return stem or "take"


def export_files(folder: str | Path, stem: str, takes: Sequence[str], settings: ExportSettings) -> list[ExportFile]:
    """The files ``settings`` write into ``folder`` for ``takes``: ``<take>.<ext>`` each, or with ``one_file``
    ``<stem>.<ext>`` holding every take (FBX, GLB)."""
    folder = Path(folder)
    files = []
    for fmt in settings.formats:
        ext = EXTENSIONS[fmt]
        if settings.one_file and fmt in ONE_FILE_FORMATS:
            files.append(ExportFile(fmt, folder / f"{stem}{ext}", tuple(takes), shared=True))
        else:
            files += [ExportFile(fmt, folder / f"{file_stem(t)}{ext}", (t,)) for t in takes]
    return files


def check_export_files(files: Sequence[ExportFile], others: Mapping[str, Path], sources: Mapping[str, Path],
                       overwrite: bool = False) -> None:
    """Every export file checked with the other outputs (``others``: the .blend, the manifest ...) and the inputs
    (``sources``): none equal to another, none a folder or under a file, none existing without ``overwrite``
    (``mld_core.inputs.check_outputs``), and the folder writable."""
    from mld_core import inputs

    outputs = dict(others)
    for f in files:
        outputs[f.label] = f.path
    inputs.check_outputs(outputs, dict(sources), overwrite=overwrite)
    for folder in sorted({f.path.parent for f in files}):
        inputs.check_writable_folder(folder, "--export-dir")


# --------------------------------------------------------------------------------------------------------------
# The exported armature and pose.


@dataclass
class ExportRig:
    """The armature as exported: ``names`` (renamed; the root bone first when there is one), ``source`` (each
    bone's index in the original rig, -1 for the root), ``parents`` and ``rest`` (B, 4, 4) rest matrices (the
    root's: identity, at the armature's origin)."""

    names: list
    source: np.ndarray
    parents: np.ndarray
    rest: np.ndarray
    root: bool
    order: list = field(default_factory=list)

    def __post_init__(self) -> None:
        self.order = _topological_order(np.asarray(self.parents))


def export_rig(rig: RigRest, renames: Mapping[str, str], root_name: str | None) -> ExportRig:
    """``rig`` with ``renames`` applied and, with ``root_name``, a root bone at the origin above its top bones."""
    names = [renames.get(n, n) for n in rig.names]
    source = np.arange(len(names))
    parents = np.asarray(rig.parents, np.int64).copy()
    rest = np.asarray(rig.matrices, np.float64).copy()
    if root_name is None:
        return ExportRig(names, source, parents, rest, False)
    parents = np.concatenate([[-1], np.where(parents < 0, 0, parents + 1)])
    return ExportRig([root_name] + names, np.concatenate([[-1], source]), parents,
                     np.concatenate([np.eye(4)[None], rest]), True)


def local_matrices(pose: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(T, B, 4, 4) each bone's pose relative to its parent's pose (a top bone's: its armature-space pose)."""
    local = np.array(pose, np.float64, copy=True)
    has = parents >= 0
    local[:, has] = np.linalg.inv(pose[:, parents[has]]) @ pose[:, has]
    return local


def chain(local: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """The inverse of :func:`local_matrices`: armature-space poses from parent-relative ones."""
    order = _topological_order(np.asarray(parents))
    pose = np.array(local, np.float64, copy=True)
    for b in order:
        if parents[b] >= 0:
            pose[:, b] = pose[:, parents[b]] @ local[:, b]
    return pose


@dataclass
class ExportedTake:
    """``bases`` (T, B, 4, 4): each exported bone's ``matrix_basis`` (location, rotation, scale relative to its
    rest) on every frame; ``pose`` (T, B, 4, 4) the exported bones' armature-space poses; ``report`` for the
    manifest (centimetres and degrees)."""

    bases: np.ndarray
    pose: np.ndarray
    report: dict


def export_pose(rig: RigRest, out: ExportRig, pose: np.ndarray, hips: int, up: np.ndarray, fps: float,
                motion: rm.RootMotion, *, loop: bool = False, metres_per_unit: float = 1.0) -> ExportedTake:
    """What the exported armature ``out`` plays for a take that puts ``rig`` in ``pose`` (T, B, 4, 4, armature
    space, every frame of the take at ``fps``): the take's travel handled as ``motion`` says (from the ``hips``
    bone's path; ``up``: the world's up in armature space), and for a ``loop`` its last frame made equal to its first
    (relative to the root; the gap spread over the take) so an engine can play it round."""
    pose = np.asarray(pose, np.float64)
    parents = np.asarray(rig.parents)
    top = np.flatnonzero(parents < 0)
    cm = 100.0 * metres_per_unit
    report = {"frames": int(len(pose)), "fps": float(fps), "hips_travel_cm": round(
        rm.ground_travel(pose[:, hips, :3, 3], up) * cm, 2)}
    if loop:  # judged from the root the engine sees: turning with the take only when the turn is exported with it
        turning = motion.yaw or motion.mode == "object"
        pose, report["seam"] = _closed_loop(pose, hips, up, fps, motion.smooth_s, cm, turning)
    frames = rm.root_frames(pose[:, hips], up, fps, yaw=motion.yaw, loop=loop, smooth_s=motion.smooth_s)
    split = rm.split_root(pose[:, top], frames, motion.mode)
    local = local_matrices(pose, parents)  # (T, B, 4, 4) parent-relative
    local[:, top] = split.top
    if out.root:
        local = np.concatenate([split.root[:, None], local], axis=1)
    exported = chain(local, out.parents)
    bases = np.linalg.inv(_rest_relative(out))[None] @ local
    hips_out = int(np.flatnonzero(out.source == hips)[0])
    report["exported_hips_travel_cm"] = round(rm.ground_travel(exported[:, hips_out, :3, 3], up) * cm, 2)
    if out.root:
        report["root_travel_cm"] = round(rm.ground_travel(split.root[:, :3, 3], up) * cm, 2)
    if motion.yaw and motion.mode != "object":
        heading = rm.level_heading(frames[:, :3, :3], up)  # the turning the root carries (root-bone) or drops
        report["turn_deg"] = round(float(np.degrees(heading[-1] - heading[0])), 2)
    return ExportedTake(bases, exported, report)


def _rest_relative(out: ExportRig) -> np.ndarray:
    """(B, 4, 4) each bone's rest relative to its parent's rest (a top bone's: its rest): pose = parent pose @ this
    @ basis."""
    rel = np.array(out.rest, copy=True)
    has = out.parents >= 0
    rel[has] = np.linalg.inv(out.rest[out.parents[has]]) @ out.rest[has]
    return rel


def _closed_loop(pose, hips, up, fps, smooth_s, cm, turning: bool) -> tuple[np.ndarray, dict]:
    """The pose with its last frame equal to its first relative to the root (``turning``: a root that turns with
    the take; otherwise a loop's turn is spread over it, so its ends face alike), each joint moved by at most its
    own gap; and the seam's report."""
    frames = rm.root_frames(pose[:, hips], up, fps, yaw=turning, loop=True, smooth_s=smooth_s)
    seen = rm.in_root_frame(frames, pose)
    gap_before = rm.seam_gap(seen[..., :3, 3], seen[..., :3, :3])
    closed = frames[:, None] @ rm.close_loop(seen)
    seen = rm.in_root_frame(frames, closed)
    gap_after = rm.seam_gap(seen[..., :3, 3], seen[..., :3, :3])
    heading = rm.level_heading(pose[:, hips, :3, :3], up)
    travel = rm.ground_travel(frames[:, :3, 3], up)
    return closed, {"gap_cm": round(gap_before[0] * cm, 3), "gap_deg": round(gap_before[1], 3),
                    "closed_gap_cm": round(gap_after[0] * cm, 4), "closed_gap_deg": round(gap_after[1], 4),
                    "cycle_travel_cm": round(travel * cm, 2),
                    "cycle_turn_deg": round(float(np.degrees(heading[-1] - heading[0])), 2)}


def pose_keys(names: Sequence[str], bases: np.ndarray, frame_start: float, fps: float):
    """Keys (``keyframes.BakedKeys``) playing ``bases`` (T, B, 4, 4) on the bones ``names``: a LINEAR key on every
    frame for location and quaternion rotation of every bone (scale where a bone scales)."""
    from mld_core.rig.keyframes import BakedKeys, CurveKeys

    frames = float(frame_start) + np.arange(len(bases), dtype=np.float64)
    scale = np.linalg.norm(bases[..., :3, :3], axis=-2)  # (T, B, 3) column lengths
    quats = rm.quaternions(bases[..., :3, :3] / scale[..., None, :])  # (T, B, 4)
    curves = []
    for b, bone in enumerate(names):
        path = f'pose.bones["{bone}"]'
        curves += [CurveKeys(f"{path}.location", i, bone, frames, bases[:, b, i, 3]) for i in range(3)]
        curves += [CurveKeys(f"{path}.rotation_quaternion", i, bone, frames, quats[:, b, i]) for i in range(4)]
        if np.abs(scale[:, b] - 1.0).max() > 1e-6:
            curves += [CurveKeys(f"{path}.scale", i, bone, frames, scale[:, b, i]) for i in range(3)]
    return BakedKeys(curves, fps=float(fps), frame_start=float(frame_start), num_frames=len(bases),
                     interpolation="LINEAR", handle_type=None, auto_smoothing=None,
                     rotation_modes={bone: "QUATERNION" for bone in names}, stats={"reduction_ratio": 1.0})
