"""Generate -> any humanoid rig: the plain decisions between the panel, the batch script and ``keyedit`` (no bpy).

What lives here (all plain Python, tested by ``tests/test_retarget_wiring.py``):

* :class:`RetargetSettings`: the user's options (Reduce Keys + tolerance, Rotation, Foot Lock, Push to NLA) and
  how they become ``keyedit.BakeOptions`` and per-bone rotation modes;
* :func:`uses_keyedit`: the canonical armature keeps its exact path (rotations + bone offsets, every joint on
  the generated position) unless the user asks for key reduction, Euler rotations or foot locking;
* the per-armature bone map as panel rows (``canonical joint -> bone``, required joints marked) and back
  (:func:`map_to_rows`, :func:`rows_to_map`), and as the JSON kept beside the rows (parent overrides, pose
  properties, source);
* :func:`map_problem`: one sentence naming the required joints without a bone (or bones not in the rig), used by
  the Generate button's poll and by ``apply``; :class:`DetectionCache` so the poll never re-runs detection for
  a rig whose bones did not change;
* :func:`take_contacts`: a take's HumanML3D foot contacts (its own, or recomputed from its joints).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

import numpy as np

from mld_core.rig import bone_maps as bm
from mld_core.rig import keyframes as ke

# (identifier, label, description) for the panel's Rotation menu; "KEEP" keeps each bone's current mode.
ROTATION_CHOICES = (
    ("QUATERNION", "Quaternion", "Key rotation_quaternion (no gimbal lock; the default)"),
    ("XYZ", "Euler XYZ", "Key rotation_euler, order XYZ"),
    ("XZY", "Euler XZY", "Key rotation_euler, order XZY"),
    ("YXZ", "Euler YXZ", "Key rotation_euler, order YXZ"),
    ("YZX", "Euler YZX", "Key rotation_euler, order YZX"),
    ("ZXY", "Euler ZXY", "Key rotation_euler, order ZXY"),
    ("ZYX", "Euler ZYX", "Key rotation_euler, order ZYX"),
    ("KEEP", "Keep Rig's", "Keep each bone's current rotation mode (Axis Angle bones get quaternions)"),
)
ROTATION_IDS = tuple(c[0] for c in ROTATION_CHOICES)
DEFAULT_TOLERANCE_DEG = 0.5
MAP_FORMAT = "mld-bone-map/1"


@dataclass(frozen=True)
class RetargetSettings:
    """How a take is keyed. Defaults: a key on every frame, quaternions, no foot lock, the Action assigned."""

    reduce: bool = False
    tolerance_deg: float = DEFAULT_TOLERANCE_DEG
    rotation_mode: str = "QUATERNION"
    foot_lock: bool = False
    nla: bool = False

    def __post_init__(self) -> None:
        if self.rotation_mode not in ROTATION_IDS:
            raise ValueError(f"rotation mode must be one of {', '.join(ROTATION_IDS)}; got {self.rotation_mode!r}")
        if not (0.0 < float(self.tolerance_deg) <= 45.0):
            raise ValueError(f"key reduction tolerance must be between 0 and 45 degrees; got {self.tolerance_deg:g}")

    @classmethod
    def from_settings(cls, settings) -> "RetargetSettings":
        """From the panel's scene settings (``scene.mld_motion``) or anything with the same attributes."""
        return cls(
            reduce=bool(getattr(settings, "reduce_keys", False)),
            tolerance_deg=float(getattr(settings, "reduce_tolerance", DEFAULT_TOLERANCE_DEG)),
            rotation_mode=str(getattr(settings, "rotation_mode", "QUATERNION")),
            foot_lock=bool(getattr(settings, "foot_lock", False)),
            nla=bool(getattr(settings, "push_nla", False)),
        )

    def bake_options(self, fps: float, frame_start: float) -> ke.BakeOptions:
        """keyedit's options for a scene at ``fps`` starting at ``frame_start`` ("KEEP" bakes quaternions unless
        :meth:`rotation_modes` names another mode for a bone)."""
        mode = "QUATERNION" if self.rotation_mode == "KEEP" else self.rotation_mode
        return ke.BakeOptions(
            fps=float(fps),
            frame_start=float(frame_start),
            rotation_mode=mode,
            reduce=bool(self.reduce),
            rot_tolerance_deg=float(self.tolerance_deg),
            foot_lock=bool(self.foot_lock),
        )

    def rotation_modes(self, current: Mapping[str, str], bones: Iterable[str]) -> dict[str, str] | None:
        """Per-bone rotation modes for keyedit: with "KEEP", each of ``bones`` keeps its ``current`` mode
        (quaternion or an Euler order; Axis Angle becomes quaternion); otherwise None (one mode for all)."""
        if self.rotation_mode != "KEEP":
            return None
        out = {}
        for bone in bones:
            mode = current.get(bone, "QUATERNION")
            out[bone] = mode if mode in ke.EULER_ORDERS else "QUATERNION"
        return out

    def to_dict(self) -> dict:
        return {
            "reduce": self.reduce,
            "tolerance_deg": self.tolerance_deg,
            "rotation_mode": self.rotation_mode,
            "foot_lock": self.foot_lock,
            "nla": self.nla,
        }


def uses_keyedit(canonical: bool, settings: RetargetSettings, current_modes: Mapping[str, str] | None = None) -> bool:
    """True when a take goes through retargeting + keyedit; False for the canonical armature's exact path
    (quaternion keys on every frame), which is kept unless the user asks for reduction, Euler or foot locking."""
    if not canonical:
        return True
    if settings.reduce or settings.foot_lock:
        return True
    if settings.rotation_mode == "KEEP":
        return any(m in ke.EULER_ORDERS for m in (current_modes or {}).values())
    return settings.rotation_mode != "QUATERNION"


# --------------------------------------------------------------------------------------------------------------
# The bone map as panel rows (one per canonical joint) + JSON extras.


@dataclass(frozen=True)
class MapRow:
    joint: str
    bone: str  # '' when unmapped
    required: bool


def joint_names() -> tuple[str, ...]:
    from mld_core.motion.skeleton import JOINT_NAMES

    return tuple(JOINT_NAMES)


def map_to_rows(bone_map: bm.BoneMap | None) -> list[MapRow]:
    """One row per canonical joint, in skeleton order; unmapped joints get ''."""
    joints = bone_map.joints if bone_map is not None else {}
    return [MapRow(j, joints.get(j, ""), j in bm.REQUIRED_JOINTS) for j in joint_names()]


def map_extras(bone_map: bm.BoneMap) -> str:
    """What the rows do not hold (source, parent overrides, pose properties) as a JSON string."""
    return json.dumps(
        {
            "format": MAP_FORMAT,
            "source": bone_map.source,
            "parent_overrides": dict(bone_map.parent_overrides),
            "pose_properties": {b: dict(p) for b, p in bone_map.pose_properties.items()},
        },
        sort_keys=True,
    )


def rows_to_map(rows: Iterable, extras: str = "") -> bm.BoneMap:
    """A BoneMap from rows (anything with ``.joint`` and ``.bone``, or (joint, bone) pairs) and the extras JSON.
    Overrides and pose properties of bones no longer in the map are dropped."""
    joints = {}
    for row in rows:
        joint, bone = (row.joint, row.bone) if hasattr(row, "joint") else (row[0], row[1])
        if bone:
            joints[str(joint)] = str(bone)
    data = {}
    if extras:
        try:
            data = json.loads(extras)
        except json.JSONDecodeError:
            data = {}
        if not isinstance(data, dict):
            data = {}
    used = set(joints.values())
    overrides = {c: p for c, p in dict(data.get("parent_overrides", {})).items() if c in used}
    props = {b: dict(p) for b, p in dict(data.get("pose_properties", {})).items()}
    return bm.BoneMap(joints, source=str(data.get("source", "user")), parent_overrides=overrides, pose_properties=props)


def map_problem(bone_map: bm.BoneMap, bone_names: Iterable[str], rig_name: str = "") -> str:
    """'' when ``bone_map`` can key the rig, else one sentence naming what is missing (for polls and errors)."""
    try:
        bone_map.validate(bone_names)
    except bm.BoneMapError as exc:
        who = f"{rig_name!r}: " if rig_name else ""
        text = str(exc).replace(" Nothing was keyed.", "")
        return f"{who}{text}. Pick the bones in the Retarget panel (or press Detect)"
    return ""


def missing_message(error: bm.BoneMapError, rig_name: str) -> str:
    """The message a failed apply shows: what is missing, and that nothing was keyed."""
    text = str(error)
    if "Nothing was keyed" not in text:
        text += " Nothing was keyed."
    return f"{rig_name!r}: {text}"


class DetectionCache:
    """Bone-map detection per rig, recomputed only when the rig's bone names or hierarchy change."""

    def __init__(self, size: int = 16):
        self.size = size
        self._store: dict[tuple, bm.Detection] = {}
        self.runs = 0  # detections actually computed (for tests)

    def get(self, names: Sequence[str], parents: Sequence | None = None) -> bm.Detection:
        key = (tuple(names), tuple(parents) if parents is not None else None)
        hit = self._store.get(key)
        if hit is not None:
            return hit
        detection = bm.detect_bone_map(list(names), list(parents) if parents is not None else None)
        self.runs += 1
        if len(self._store) >= self.size:
            self._store.pop(next(iter(self._store)))
        self._store[key] = detection
        return detection


detections = DetectionCache()


def canonical_map(bone_names: Sequence[str]) -> bm.BoneMap:
    """The canonical preset resolved against a rig's names (the canonical armature going through keyedit)."""
    preset = bm.load_presets()["canonical"]
    return bm.apply_preset(preset, list(bone_names))[0]


# --------------------------------------------------------------------------------------------------------------
# Takes.


def take_contacts(take) -> np.ndarray | None:
    """(T, 4) HumanML3D foot contacts of a take (left ankle, left toe, right ankle, right toe; > 0.5 = contact):
    ``take.contacts`` when the take carries them (the generated features' last four channels), else recomputed
    from its joints with HumanML3D's own rule (``joints_to_features``). None for takes shorter than 2 frames."""
    given = getattr(take, "contacts", None)
    joints = np.asarray(take.joints, dtype=np.float64)
    if given is not None:
        c = np.asarray(given, dtype=np.float64)
        if c.ndim == 2 and c.shape[1] == 4 and len(c) >= 1:
            return _pad(c, len(joints))
    if len(joints) < 2:
        return None
    from mld_core.motion import features as F

    feats = F.joints_to_features(joints, fps=getattr(take, "fps", 20) or 20)  # (T-1, 263)
    return _pad(np.asarray(feats[:, F.FOOT_CONTACT], dtype=np.float64), len(joints))


def _pad(c: np.ndarray, n: int) -> np.ndarray:
    if len(c) >= n:
        return c[:n]
    return np.concatenate([c, np.repeat(c[-1:], n - len(c), axis=0)], 0)  # features have T-1 rows
