"""What a take must hit, as differentiable costs on its joints: poses at given frames, a root path on the ground,
a loop. Take fix 2 (``meet_constraints.py``) refines a take's sampled latent, then its decoded features, against
them; the free path never touches this module.

Joints are the pipeline's output frame: metres, Y up, the root starting at the origin facing +Z. Frames are model
frames (20 fps); files with another fps are converted when read (:func:`read_keys`, :func:`read_path`). Each
constraint object checks itself when made (frames whole and 0 or more, coordinates finite, joints known) and raises
:class:`~mld_core.inputs.InputError`; frames beyond the take are refused once its length is known
(:meth:`Constraints.check_frames`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch

from mld_core.inputs import (InputError, check_prompt, finite_number, int_in_range, read_json_file, true_or_false,
                             whole_number)
from mld_core.motion import skeleton as sk
from mld_core.motion.features import FOOT_CONTACT, ROOT_LIN_VEL, features_to_joints
from mld_core.take_fixes.repair import FOOT_JOINTS
from mld_core.motion.skeleton import JOINT_NAMES

JOINT_INDEX = {name: i for i, name in enumerate(JOINT_NAMES)}


# -- checks each constraint makes on itself ---------------------------------------------------------------------
def frame_number(value, what: str) -> int:
    """A model frame: a whole number, 0 or more."""
    frame = whole_number(value, what)
    if frame < 0:
        raise InputError(f"{what} must be 0 or more, got {frame}")
    return frame


def _not_negative(value, what: str) -> float:
    number = finite_number(value, what)
    if number < 0:
        raise InputError(f"{what} must be 0 or more, got {number:g}")
    return number


def _length(value) -> int | None:
    """How many items a list, tuple or array holds; None for anything else (text, a dict, a number)."""
    if isinstance(value, (str, bytes, Mapping)):
        return None
    try:
        return len(value)
    except TypeError:
        return None


def brief(value) -> str:
    """``value`` for a one-line message: its repr on one line, at most 60 characters."""
    text = " ".join(repr(value).split())
    return text if len(text) <= 60 else text[:57] + "..."


def _point(value, size: int, what: str, shape: str) -> list[float]:
    """``size`` finite coordinates (a list, tuple or array)."""
    if _length(value) != size:
        raise InputError(f"{what} must be {shape} in metres, got {brief(value)}")
    return [finite_number(v, f"{what} {axis}") for v, axis in zip(value, "xyz" if size == 3 else "xz")]


def _check_weights(item) -> None:
    item.weight = _not_negative(item.weight, f"{type(item).__name__} weight")
    item.tolerance_m = _not_negative(item.tolerance_m, f"{type(item).__name__} tolerance_m")


@dataclass
class PoseKeys:
    """Target positions (metres) of some joints at some frames: ``targets[frame][joint] = (x, y, z)``."""

    targets: dict[int, dict[str, Sequence[float]]]
    weight: float = 1.0
    tolerance_m: float = 0.03  # a residual above this is reported as not met

    def __post_init__(self):
        if not isinstance(self.targets, Mapping):
            raise InputError("PoseKeys targets must be a dict {frame: {joint: (x, y, z)}}, got "
                             f"{type(self.targets).__name__}")
        if not self.targets:
            raise InputError("PoseKeys targets are empty: key at least one joint at one frame")
        targets: dict[int, dict[str, list[float]]] = {}
        for frame, keyed in self.targets.items():
            frame = frame_number(frame, "PoseKeys frame")
            at = f"PoseKeys frame {frame}"
            if not isinstance(keyed, Mapping) or not keyed:
                raise InputError(f"{at}: expected {{joint: (x, y, z)}} with at least one joint, got {brief(keyed)}")
            for joint, point in keyed.items():
                if joint not in JOINT_INDEX:
                    raise InputError(f"{at}: unknown joint {joint!r}; joints: {', '.join(JOINT_NAMES)}")
                targets.setdefault(frame, {})[joint] = _point(point, 3, f"{at}, {joint}", "(x, y, z)")
        self.targets = targets
        _check_weights(self)

    def last_frame(self) -> int:
        return max(self.targets)

    def cost(self, joints: torch.Tensor) -> torch.Tensor:
        """Mean squared distance (m^2) of the keyed joints from their targets; joints (B, T, 22, 3)."""
        frames, index, target = self._arrays(joints)
        return ((joints[:, frames, index] - target) ** 2).sum(-1).mean()

    def residual(self, joints: np.ndarray) -> float:
        """Mean distance (m) of the keyed joints from their targets; joints (T, 22, 3)."""
        frames, index, target = self._arrays(torch.as_tensor(joints)[None])
        return float(np.linalg.norm(np.asarray(joints)[frames, index] - target.numpy(), axis=-1).mean())

    def _arrays(self, joints: torch.Tensor):
        rows = [(f, JOINT_INDEX[j], p) for f, keyed in sorted(self.targets.items()) for j, p in keyed.items()]
        frames = [r[0] for r in rows]
        index = [r[1] for r in rows]
        target = torch.tensor(np.array([r[2] for r in rows], np.float32), dtype=joints.dtype)
        return frames, index, target


@dataclass
class RootPath:
    """Ground positions (x, z) of the pelvis at some frames, linearly interpolated in between."""

    frames: Sequence[int]
    points: np.ndarray  # (K, 2) metres
    weight: float = 1.0
    tolerance_m: float = 0.10

    def __post_init__(self):
        if not _length(self.frames):
            raise InputError(f"RootPath frames must be a list of whole frames 0 or more, got {brief(self.frames)}")
        frames = [frame_number(f, "RootPath frame") for f in self.frames]
        for a, b in zip(frames, frames[1:]):
            if b <= a:
                raise InputError(f"RootPath frames must increase, got {a} then {b}")
        points = self.points
        if _length(points) != len(frames):
            raise InputError(f"RootPath points must be one (x, z) per frame ({len(frames)}), got {brief(points)}")
        self.frames = frames
        self.points = np.array([_point(p, 2, f"RootPath point {n}", "(x, z)") for n, p in enumerate(points, 1)],
                               np.float64)  # (K, 2)
        _check_weights(self)

    def last_frame(self) -> int:
        return int(max(self.frames))

    def dense(self) -> tuple[np.ndarray, np.ndarray]:
        """(frames (N,), xz (N, 2)): every frame from the first to the last point."""
        frames = np.arange(int(min(self.frames)), int(max(self.frames)) + 1)
        pts = np.asarray(self.points, np.float64)
        xz = np.stack([np.interp(frames, self.frames, pts[:, i]) for i in range(2)], -1)
        return frames, xz

    def cost(self, joints: torch.Tensor) -> torch.Tensor:
        frames, xz = self.dense()
        target = torch.tensor(xz, dtype=joints.dtype)
        return ((joints[:, frames, 0][..., [0, 2]] - target) ** 2).sum(-1).mean()

    def residual(self, joints: np.ndarray) -> float:
        frames, xz = self.dense()
        return float(np.linalg.norm(np.asarray(joints)[frames, 0][:, [0, 2]] - xz, axis=-1).mean())


def root_relative(joints):
    """Joints (..., T, 22, 3) relative to each frame's root ground position (the pelvis at x = z = 0)."""
    ground = joints[..., :1, :] * (joints.new_tensor([1.0, 0.0, 1.0]) if isinstance(joints, torch.Tensor)
                                   else np.array([1.0, 0.0, 1.0]))
    return joints - ground


@dataclass
class Loop:
    """The last frame continues into the first: same pose (relative to the root's ground position) and velocity."""

    weight: float = 1.0
    tolerance_m: float = 0.01

    def __post_init__(self):
        _check_weights(self)

    def last_frame(self) -> int:
        return 0

    def cost(self, joints: torch.Tensor) -> torch.Tensor:
        local = root_relative(joints)
        gap = ((local[:, -1] - local[:, 0]) ** 2).sum(-1).mean()
        jump = (((joints[:, 1] - joints[:, 0]) - (joints[:, -1] - joints[:, -2])) ** 2).sum(-1).mean()
        return gap + jump

    def residual(self, joints: np.ndarray) -> float:
        local = root_relative(np.asarray(joints))
        return float(np.linalg.norm(local[-1] - local[0], axis=-1).max())


@dataclass
class Continuation:
    """The take's first frames repeat the pose of ``joints`` (K, 22, 3) relative to the root's ground position: how a
    take continues another (``MLDPipeline.sequence``). Where the root goes is the take's own: the sequence joins the
    takes' root velocities, so a segment may turn back or stop (a run, then a walk backwards) instead of being
    dragged on at the previous segment's speed."""

    joints: np.ndarray
    weight: float = 1.0
    tolerance_m: float = 0.02

    def __post_init__(self):
        try:
            joints = np.asarray(self.joints, np.float64)
        except (TypeError, ValueError):
            joints = None
        if joints is None or joints.ndim != 3 or joints.shape[1:] != (22, 3) or not len(joints):
            raise InputError("Continuation joints must be an array (K, 22, 3) of joint positions in metres, got "
                             f"{getattr(joints, 'shape', type(self.joints).__name__)}")
        if not np.isfinite(joints).all():
            raise InputError("Continuation joints must be finite (no NaN or inf)")
        _check_weights(self)

    def last_frame(self) -> int:
        return len(self.joints) - 1

    def cost(self, joints: torch.Tensor) -> torch.Tensor:
        target = root_relative(torch.as_tensor(np.asarray(self.joints, np.float32), dtype=joints.dtype))
        return ((root_relative(joints[:, : len(target)]) - target) ** 2).sum(-1).mean()

    def residual(self, joints: np.ndarray) -> float:
        own = root_relative(np.asarray(joints)[: len(self.joints)])
        return float(np.linalg.norm(own - root_relative(np.asarray(self.joints)), axis=-1).mean())


@dataclass
class Constraints:
    """Everything a take must hit, and how hard to try (Adam steps on the sampled latent)."""

    items: list = field(default_factory=list)
    steps: int = 40  # Adam steps on the latent (through the decoder)
    lr: float = 0.1
    feature_steps: int = 120  # then on the decoded features
    feature_lr: float = 0.05
    smooth_weight: float = 0.1  # mean squared feature acceleration
    smooth_change_only: bool | None = None  # ... of the change to the decoded features, so their own motion is not
    # damped (None: unless the take loops and travels; a run cycle's seam needs the features themselves smooth: see
    # smooths_change_only)
    in_place_speed_m_s: float = 0.3  # a looped take whose root moves slower than this stays in place (a wave)
    prior_weight: float = 1e-3  # keeps latent and features near the sample: the motion stays the prompt's
    planted_weight: float = 1.0  # planted feet (the sample's contact channels) keep still while the root moves
    planted_toe_height_m: float = 0.05  # ... and so does a toe this near the take's lowest toe (0: the channels only)
    bone_weight: float = 10.0  # bones keep the reference skeleton's lengths (else planted feet stretch the legs)
    slide_weight: float = 1.0  # with stepping on, the latent stage also lowers the feet's slide (stepping.slide_cost)
    keyed_slide_weight: float = 0.03  # ... instead, with pose keys among the items (keys place the feet themselves)

    def __post_init__(self):
        if not isinstance(self.items, (list, tuple)):
            raise InputError(f"Constraints takes a list of constraints, e.g. Constraints([Loop()]), got "
                             f"{type(self.items).__name__}")
        for n, item in enumerate(self.items, start=1):
            if not isinstance(item, CONSTRAINT_KINDS):
                raise InputError(f"Constraints item {n} is a {type(item).__name__}, not a constraint: use "
                                 f"{', '.join(k.__name__ for k in CONSTRAINT_KINDS)} (mld_core.take_fixes.constraints)")
        self.items = list(self.items)
        for name in ("steps", "feature_steps"):
            setattr(self, name, int_in_range(getattr(self, name), f"Constraints {name}", 0, MAX_STEPS))
        for name in ("lr", "feature_lr", "smooth_weight", "in_place_speed_m_s", "prior_weight", "planted_weight",
                     "planted_toe_height_m", "bone_weight", "slide_weight", "keyed_slide_weight"):
            setattr(self, name, _not_negative(getattr(self, name), f"Constraints {name}"))
        if self.smooth_change_only is not None:
            true_or_false(self.smooth_change_only, "Constraints smooth_change_only (or None)")

    def __bool__(self) -> bool:
        return bool(self.items)

    def smooths_change_only(self) -> bool:
        """Whether the feature stage keeps only its change to the decoded features smooth, for a take that travels
        (``smooth_change_only``; by default yes, unless a Loop is among the items: smoothing the features themselves
        keeps a run cycle's seam within real motion's acceleration, 0.75x against 1.20x its 95th percentile on 4
        seeds)."""
        if self.smooth_change_only is not None:
            return bool(self.smooth_change_only)
        return not any(isinstance(item, Loop) for item in self.items)

    def change_only_rows(self, root_speed_m_s) -> np.ndarray:
        """(B,) bool: ``smooths_change_only`` per take, from each take's mean horizontal root speed (m/s). By default
        a take slower than ``in_place_speed_m_s`` (a looped wave) keeps its change only smooth even in a loop: the
        features' own smoothness flattened looped waves (2 of 8 seeds waved, against 6)."""
        speed = np.asarray(root_speed_m_s, np.float64)
        travelling = self.smooths_change_only()
        if self.smooth_change_only is not None or travelling:  # an explicit choice, or no loop: one for all
            return np.full(len(speed), travelling)
        return speed < self.in_place_speed_m_s  # a loop, by default: only a take that travels smooths its features

    def latent_slide_weight(self) -> float:
        """The weight of the feet's slide in the latent stage: lower with pose keys, which the slide would resist
        (pose keys met 0.979 -> 0.938 at 1.0 on 48 test clips; paths and loops skate a third as much as at 0.03)."""
        keyed = any(isinstance(item, PoseKeys) for item in self.items)
        return self.keyed_slide_weight if keyed else self.slide_weight

    def check_frames(self, frames: int) -> None:
        for item in self.items:
            if item.last_frame() >= frames:
                raise InputError(f"a {type(item).__name__} constraint reaches frame {item.last_frame()}, but the "
                                 f"take has {frames} frames (0..{frames - 1} at 20 fps)")

    def cost(self, joints: torch.Tensor) -> torch.Tensor:
        return sum(item.weight * item.cost(joints) for item in self.items)

    def residuals(self, joints: np.ndarray) -> list[tuple[str, float, bool]]:
        """Per constraint: (kind, residual in metres, met)."""
        out = []
        for item in self.items:
            r = item.residual(joints)
            out.append((type(item).__name__, r, r <= item.tolerance_m))
        return out


CONSTRAINT_KINDS = (PoseKeys, RootPath, Loop, Continuation)
MAX_STEPS = 100_000  # Adam steps of either stage

FEET = list(FOOT_JOINTS)  # left ankle, left toe (foot), right ankle, right toe: the order of the contact channels


def planted_feet(features: torch.Tensor, toe_height_m: float = 0.0) -> torch.Tensor:
    """(B, T, 4) bool, the feet the feature stage holds still (left ankle, left toe, right ankle, right toe): those
    the decoded features' contact channels plant, and each toe within ``toe_height_m`` of the take's lowest toe
    (where foot skating is counted: a run's channels miss many of those frames). ``features`` (B, T, 263)
    denormalised, every row of one length."""
    planted = features[..., FOOT_CONTACT] > 0.5  # (B, T, 4)
    if toe_height_m > 0:
        toes = features_to_joints(features)[:, :, [FEET[1], FEET[3]], 1]  # (B, T, 2) heights
        low = toes - toes.amin(dim=(1, 2), keepdim=True) < toe_height_m  # (B, T, 2)
        planted = planted.clone()
        planted[..., [1, 3]] |= low
    return planted


def root_speed(features: torch.Tensor) -> np.ndarray:
    """(B,) each take's mean horizontal root speed in m/s; ``features`` (B, T, 263) denormalised, every row of one
    length."""
    per_frame = features[..., ROOT_LIN_VEL].detach().float().norm(dim=-1)  # (B, T) metres per frame
    return (per_frame.mean(dim=1) * sk.FPS).cpu().numpy()


def planted_foot_speed(joints: torch.Tensor, contacts: torch.Tensor) -> torch.Tensor:
    """Mean squared ground speed (m/frame)^2 of the ankles and toes while ``contacts`` (B, T, 4: left ankle, left
    toe, right ankle, right toe) says they are planted, per take, averaged over the takes (each take's share does
    not depend on the others': a batch equals single runs); joints (B, T, 22, 3)."""
    feet = joints[:, :, FEET][..., [0, 2]]  # (B, T, 4, 2)
    step = feet[:, 1:] - feet[:, :-1]  # (B, T-1, 4, 2)
    planted = (contacts[:, 1:] & contacts[:, :-1]).to(joints.dtype)  # (B, T-1, 4)
    per_take = ((step ** 2).sum(-1) * planted).sum(dim=(1, 2)) / planted.sum(dim=(1, 2)).clamp(min=1.0)  # (B,)
    return per_take.mean()


def bone_stretch(joints: torch.Tensor) -> torch.Tensor:
    """Mean squared difference (m^2) of the bone lengths of joints (B, T, 22, 3) from the reference skeleton's."""
    parents = list(sk.PARENTS[1:])
    lengths = (joints[:, :, 1:] - joints[:, :, parents]).norm(dim=-1)  # (B, T, 21)
    reference = torch.as_tensor(sk.REFERENCE_BONE_LENGTHS[1:], dtype=joints.dtype, device=joints.device)
    return ((lengths - reference) ** 2).mean()


def path_along(points: np.ndarray, frames: int, units_per_metre: float = 1.0) -> RootPath:
    """A root path following ``points`` (N, 3) of a curve in Blender's axes (Z up, the character facing -Y) from its
    first point, spread evenly by arc length over ``frames`` model frames: the take starts where it stands and the
    root traces the curve's shape (model x = Blender x, model z = -Blender y)."""
    pts = np.asarray(points, np.float64)[:, :2] / units_per_metre
    rel = pts - pts[0]
    xz = np.stack([rel[:, 0], -rel[:, 1]], -1)  # (N, 2)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xz, axis=0), axis=-1))])
    if len(xz) < 2 or arc[-1] <= 0:
        raise InputError("the curve has no length to follow")
    at = np.linspace(0.0, arc[-1], frames)
    dense = np.stack([np.interp(at, arc, xz[:, i]) for i in range(2)], -1)
    return RootPath(list(range(frames)), dense)


def keys_from_blender(poses: dict[int, dict[str, Sequence[float]]], origin: Sequence[float]) -> PoseKeys:
    """Pose keys from joint positions read off an armature in Blender's world (Z up, the character facing -Y),
    ``poses[model_frame][joint] = (x, y, z)``, relative to the armature's ``origin`` (where the take starts)."""
    ox, oy, oz = (float(v) for v in origin)
    targets = {int(f): {j: [float(p[0]) - ox, float(p[2]) - oz, -(float(p[1]) - oy)] for j, p in keyed.items()}
               for f, keyed in poses.items() if keyed}
    if not targets:
        raise InputError("the armature has no keys in the take's frame range to use")
    return PoseKeys(targets)


# -- files ----------------------------------------------------------------------------------------------------------
def _load_json(path: Path, what: str):
    """The user's JSON file, read by the one reader of user files (size, depth and number limits)."""
    return read_json_file(path, what)


def _model_frame(frame, fps: float, where: str) -> int:
    frame = whole_number(frame, f"{where}: frame")
    if frame < 0:
        raise InputError(f"{where}: frame must be 0 or more, got {frame}")
    return int(round(frame * 20.0 / fps))


def _fps(data: dict, where: str) -> float:
    fps = finite_number(data.get("fps", 20), f"{where}: fps")
    if not 1 <= fps <= 1000:
        raise InputError(f"{where}: fps must be between 1 and 1000, got {fps:g}")
    return fps


def keys_from_data(data, where: str) -> PoseKeys:
    """``{"fps": 20, "keys": [{"frame": 40, "joints": {"pelvis": [x, y, z], ...}}, ...]}``."""
    if not isinstance(data, dict) or not isinstance(data.get("keys"), list) or not data["keys"]:
        raise InputError(f"{where}: expected {{\"fps\": 20, \"keys\": [{{\"frame\": F, \"joints\": {{...}}}}]}}")
    fps = _fps(data, where)
    targets: dict[int, dict] = {}
    for n, key in enumerate(data["keys"], start=1):
        at = f"{where}, key {n}"
        if not isinstance(key, dict) or not isinstance(key.get("joints"), dict) or not key["joints"]:
            raise InputError(f"{at}: expected {{\"frame\": F, \"joints\": {{\"pelvis\": [x, y, z], ...}}}}")
        frame = _model_frame(key.get("frame"), fps, at)
        for joint, point in key["joints"].items():
            if joint not in JOINT_INDEX:
                raise InputError(f"{at}: unknown joint {joint!r}; joints: {', '.join(JOINT_NAMES)}")
            if not isinstance(point, list) or len(point) != 3:
                raise InputError(f"{at}: {joint} must be [x, y, z] in metres")
            targets.setdefault(frame, {})[joint] = [finite_number(v, f"{at}: {joint}") for v in point]
    return PoseKeys(targets)


def path_from_data(data, where: str) -> RootPath:
    """``{"fps": 20, "points": [[frame, x, z], ...]}`` (at least two points, frames increasing)."""
    points = data.get("points") if isinstance(data, dict) else None
    if not isinstance(points, list) or len(points) < 2:
        raise InputError(f"{where}: expected {{\"fps\": 20, \"points\": [[frame, x, z], ...]}} with 2+ points")
    fps = _fps(data, where)
    frames, xz = [], []
    for n, p in enumerate(points, start=1):
        at = f"{where}, point {n}"
        if not isinstance(p, list) or len(p) != 3:
            raise InputError(f"{at}: expected [frame, x, z]")
        frames.append(_model_frame(p[0], fps, at))
        xz.append([finite_number(p[1], f"{at}: x"), finite_number(p[2], f"{at}: z")])
    if any(b <= a for a, b in zip(frames, frames[1:])):
        raise InputError(f"{where}: frames must increase")
    return RootPath(frames, np.asarray(xz, np.float64))


def sequence_from_data(data, where: str) -> list[tuple[str, float]]:
    """``[{"prompt": "a person walks forward", "seconds": 3.0}, ...]`` (at least one segment)."""
    if not isinstance(data, list) or not data:
        raise InputError(f"{where}: expected [{{\"prompt\": \"...\", \"seconds\": 3.0}}, ...]")
    segments = []
    for n, seg in enumerate(data, start=1):
        at = f"{where}, segment {n}"
        if not isinstance(seg, dict) or not isinstance(seg.get("prompt"), str):
            raise InputError(f"{at}: expected {{\"prompt\": \"...\", \"seconds\": 3.0}}")
        try:
            prompt = check_prompt(seg["prompt"])
        except InputError as exc:
            raise InputError(f"{at}: {exc}") from None
        segments.append((prompt, finite_number(seg.get("seconds", 4.0), f"{at}: seconds")))
    return segments


def read_keys(path: Path) -> PoseKeys:
    return keys_from_data(_load_json(path, "--keys"), f"--keys {path}")


def read_path(path: Path) -> RootPath:
    return path_from_data(_load_json(path, "--path"), f"--path {path}")


def read_sequence(path: Path) -> list[tuple[str, float]]:
    return sequence_from_data(_load_json(path, "--sequence"), f"--sequence {path}")


def constraints_from_job(job: dict, where: str) -> Constraints:
    """A batch job's ``keys``, ``path`` and ``loop`` (the formats of --keys, --path and --loop) as Constraints."""
    items = []
    if job.get("keys") is not None:
        items.append(keys_from_data(job["keys"], f"{where}: keys"))
    if job.get("path") is not None:
        items.append(path_from_data(job["path"], f"{where}: path"))
    if job.get("loop") is not None and true_or_false(job["loop"], f"{where}: loop"):
        items.append(Loop())
    return Constraints(items)
