"""One road from a take to the keys of one rig (numpy only): the user's keying options, and
:func:`take_keys`: joints (T, 22, 3) + rig rest + bone map + options -> one :class:`keyframes.BakedKeys`.

The canonical armature is a rig like any other (its bone map is the identity); only its *exact* option differs:
while the user asks for no key reduction, no Euler and no foot lock, every bone gets a rotation and a location
key on every frame so each joint lands exactly on the generated position (``canonical_pose``). Everything else
goes through the retarget solve and ``keyframes`` (resample, foot lock, reduction, rotation modes).
Also here: :func:`map_problem` (one sentence naming missing bones, for polls and errors), a detection cache, and
:func:`take_contacts`, and :func:`segment_strips` (where a sequence's segments lie in the scene's frames).

The add-on's road through here: a :class:`RigRecord` (read from the scene once) -> :func:`plan_keys` (the bone map,
the road, every take's keys, its Action's properties and NLA strips) -> the writer.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Mapping, Sequence

import numpy as np

from mld_core.rig import bone_maps as bm
from mld_core.rig import canonical_pose
from mld_core.rig import keyframes as ke
from mld_core.rig.retarget import RetargetOptions, RigRest

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

# (identifier, label, description) for the panel's Match menu and the batch's --match (lower case there).
MATCH_CHOICES = (
    ("EFFECTORS", "Hands and Feet", "Hands and feet land where the take puts them, scaled to the rig's limbs; "
     "limbs point within a few degrees of the take's (the default: feet never sink)"),
    ("DIRECTIONS", "Limb Directions", "Every limb points exactly as in the take; hands and feet land where the "
     "rig's own proportions take them, and feet may sink a few centimetres"),
)
MATCH_IDS = tuple(c[0].lower() for c in MATCH_CHOICES)


@dataclass(frozen=True)
class RetargetSettings:
    """How a take is keyed. Defaults: a key on every frame, quaternions, no foot lock, the Action assigned."""

    reduce: bool = False
    tolerance_deg: float = DEFAULT_TOLERANCE_DEG
    rotation_mode: str = "QUATERNION"
    foot_lock: bool = False
    nla: bool = False
    match: str = "effectors"  # retarget.RetargetOptions.match: "effectors" (hands and feet land) or "directions"

    def __post_init__(self) -> None:
        if self.match not in MATCH_IDS:
            raise ValueError(f"match must be one of {', '.join(MATCH_IDS)}; got {self.match!r}")
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
            match=str(getattr(settings, "match", "EFFECTORS")).lower(),
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
            "match": self.match,
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


# --------------------------------------------------------------------------------------------------------------
# The road.


@dataclass(frozen=True)
class Take:
    """What the road needs of a generated take: joints (T, 22, 3) metres Y up, the canonical skeleton's local
    rotations (T, 22, 4) w-first, foot contacts (T, 4) or None, and its frame rate."""

    joints: np.ndarray
    local_quats: np.ndarray
    contacts: np.ndarray | None
    fps: float


def exact_road(canonical: bool, bone_map_given: bool, settings: RetargetSettings,
               current_modes: Mapping[str, str] | None = None) -> bool:
    """Whether the canonical armature's exact option applies (see the module docstring)."""
    return canonical and not bone_map_given and not uses_keyedit(True, settings, current_modes)


def take_keys(take: Take, rig: RigRest, bone_map: bm.BoneMap, settings: RetargetSettings, *, fps: float,
              frame_start: float, exact: bool = False, current_modes: Mapping[str, str] | None = None,
              exact_locations: bool = True) -> ke.BakedKeys:
    """The keys that put ``rig`` on ``take`` at scene rate ``fps`` from ``frame_start``.

    ``exact``: the canonical armature's exact option (``rig`` must have the canonical bones); ``exact_locations``
    keys every bone's location there (else only the root's). Raises ``bone_maps.BoneMapError`` when the map
    does not fit the rig (nothing computed), ValueError for a foot lock on a one-frame take.
    """
    if exact:
        channels = canonical_pose.pose_channels(take.local_quats, take.joints, canonical_pose.canonical_rest(rig),
                                                src_fps=take.fps, dst_fps=fps, exact=exact_locations)
        return canonical_pose.channels_to_keys(channels, frame_start)
    if settings.foot_lock and take.contacts is None:
        raise ValueError("Foot Lock needs a take of at least 2 frames; nothing was keyed")
    per_bone = settings.rotation_modes(current_modes or {}, bone_map.joints.values())
    baked, _ = ke.take_to_keys(take.joints, rig, bone_map, retarget_options=RetargetOptions(match=settings.match),
                               bake_options=settings.bake_options(fps, frame_start),
                               contacts=take.contacts if settings.foot_lock else None, rotation_modes=per_bone,
                               fps=take.fps)
    return baked


@dataclass(frozen=True)
class RigRecord:
    """An armature and its scene as keying needs them, read from the file once on Blender's main thread
    (``scene/read_rig.read_record``), then planned from anywhere: the rest (names, parents, matrices), the bone map
    the Retarget panel stored on it (its rows and extras; none: no row names a bone), each pose bone's rotation
    mode, and the scene's frame rate (fps / fps_base) and first frame."""

    rig: RigRest
    map_rows: tuple = ()  # ((joint, bone), ...) as the panel stores them
    map_extras: str = ""
    rotation_modes: Mapping[str, str] = field(default_factory=dict)
    fps: float = 24.0
    frame_start: float = 1.0

    @property
    def canonical(self) -> bool:
        """True when the armature has every bone of the canonical skeleton."""
        from mld_core.motion.skeleton import JOINT_NAMES

        return all(name in self.rig for name in JOINT_NAMES)

    def stored_map(self) -> bm.BoneMap | None:
        """The map stored by the Retarget panel, or None."""
        if not any(bone for _, bone in self.map_rows):
            return None
        from mld_core.rig.bone_map_rows import rows_to_map

        return rows_to_map(self.map_rows, self.map_extras)

    def bone_map(self) -> bm.BoneMap:
        """The map the armature is keyed with: the stored one; else the canonical preset on the canonical
        armature; else the detected one (cached per set of bone names and parents)."""
        stored = self.stored_map()
        if stored is None and self.canonical:
            return canonical_map(self.rig.names)
        names = list(self.rig.names)
        parents = [names[p] if p >= 0 else None for p in self.rig.parents]
        return stored or detections.get(names, parents).bone_map


@dataclass(frozen=True)
class KeyPlan:
    """Everything keying decided for an armature (:func:`plan_of` a :class:`RigRecord`), so that the keys
    themselves can be computed anywhere (the add-on's worker thread, for Live Preview)."""

    rig: RigRest
    bone_map: bm.BoneMap
    settings: RetargetSettings
    fps: float
    frame_start: float
    exact: bool  # the canonical armature's exact road
    current_modes: Mapping[str, str] | None
    exact_locations: bool


def plan_of(record: RigRecord, settings: RetargetSettings, bone_map: bm.BoneMap | None = None,
            exact: bool = True) -> KeyPlan:
    """How ``record``'s armature is keyed under ``settings``: its bone map (``bone_map`` when given, else its own)
    and its road (the canonical armature's exact road, or the retarget solve)."""
    modes = dict(record.rotation_modes)
    on_exact_road = exact_road(record.canonical, bone_map is not None, settings, modes)
    bone_map = bone_map if bone_map is not None else record.bone_map()
    return KeyPlan(record.rig, bone_map, settings, record.fps, record.frame_start, on_exact_road, modes, exact)


@dataclass
class TakeKeys:
    """One take planned: its keys, the seconds they took, the road's custom properties for its Action (added to
    the take's own provenance when written) and its NLA strips (a prompt sequence pushed to NLA; else None)."""

    take: object
    keys: ke.BakedKeys
    seconds: float
    properties: dict
    strips: list | None = None


def road_properties(plan: KeyPlan, keys: ke.BakedKeys) -> dict:
    """How a take was keyed, as its Action's custom properties."""
    retargeted = not plan.exact
    props = dict(mld_scene_fps=float(plan.fps), mld_exact=int(bool(plan.exact_locations) and not retargeted),
                 mld_retargeted=int(retargeted))
    if retargeted:
        s = plan.settings
        props.update(mld_bone_map=plan.bone_map.source, mld_reduce=int(s.reduce),
                     mld_tolerance_deg=float(s.tolerance_deg), mld_rotation_mode=s.rotation_mode,
                     mld_foot_lock=int(s.foot_lock), mld_keys=int(keys.num_keys),
                     mld_reduction_ratio=float(keys.stats["reduction_ratio"]))
    return props


def plan_takes(takes: Sequence, plan: KeyPlan) -> list[TakeKeys]:
    """One :class:`TakeKeys` per generated take (the add-on's generation.Take: joints, local_quats, fps, foot
    contacts, segments) under ``plan``; raises what take_keys raises."""
    import time

    planned = []
    for take in takes:
        t0 = time.perf_counter()
        contacts = take_contacts(take) if plan.settings.foot_lock else None
        road_take = Take(take.joints, take.local_quats, contacts, take.fps)
        keys = take_keys(road_take, plan.rig, plan.bone_map, plan.settings, fps=plan.fps, frame_start=plan.frame_start,
                         exact=plan.exact, current_modes=plan.current_modes, exact_locations=plan.exact_locations)
        seconds = time.perf_counter() - t0
        segments = getattr(take, "segments", None)
        strips = segment_strips(segments, take.frames, take.fps, plan.fps, keys.frame_start) \
            if segments and plan.settings.nla else None
        planned.append(TakeKeys(take, keys, seconds, road_properties(plan, keys), strips))
    return planned


def plan_keys(takes: Sequence, record: RigRecord, settings: RetargetSettings, bone_map: bm.BoneMap | None = None,
              exact: bool = True) -> tuple[KeyPlan, list[TakeKeys]]:
    """Every take's keys for ``record``'s armature, computed before anything in the file changes: (the plan, one
    :class:`TakeKeys` per take). A bone map that does not fit raises ValueError naming what is missing."""
    plan = plan_of(record, settings, bone_map, exact)
    try:
        return plan, plan_takes(takes, plan)
    except bm.BoneMapError as exc:
        raise ValueError(missing_message(exc, record.rig.name)) from None


def segment_strips(segments: Sequence[tuple[str, int]], frames: int, fps: float, scene_fps: float,
                   frame_start: float) -> list[tuple[str, int, int]]:
    """A sequence take's segments ``[(prompt, first take frame)]`` (the take: ``frames`` frames at ``fps``) as NLA
    strips ``[(name, first scene frame, last scene frame)]`` back to back, each ending where the next begins, in the
    frames its keys are written at (the scene's rate from ``frame_start``)."""
    scale = float(scene_fps) / float(fps)
    firsts = [int(round(frame_start + first * scale)) for _, first in segments]
    last = int(round(frame_start + (frames - 1) * scale))
    return [(prompt, a, b) for (prompt, _), a, b in zip(segments, firsts, firsts[1:] + [last]) if b > a]
