"""Take fix 3, repair (config ``repair``): a free take's features with planted feet that do not slide and one skeleton
(:class:`Repair`, :func:`repair_rows`; constrained takes are not repaired: their constraints place root and joints).

- :func:`plant_feet` re-estimates the root's ground velocity (feature channels 1-2) from the pose: while a foot
  joint is in contact (the take's own contact channels, and near its lowest height), the root moves so that the
  foot stays where it is; elsewhere the generated root velocity is kept. The pose, rotations and the root's
  height and turning are unchanged. docs/evaluation.md ("Where the skating comes from") has the measurements.
- :func:`lock_feet` holds each planted foot where it is: while the toe (or, if the toe is up, the ankle) is in
  contact, the foot is shifted against its own ground slide and the knee bends to reach it (two-bone IK); the
  shift is let go while the foot is in the air, and the leg never straightens to reach it. The root is unchanged:
  this removes the slide that planting the root leaves where the generated strides are too short for the
  generated travel (runs, dashes, sidesteps). Takes whose feet hardly leave the floor are not locked.
- :func:`keep_bone_lengths` rebuilds joints (T, 22, 3) with fixed bone lengths, keeping every bone's direction
  and the pelvis: the decoded joints otherwise stretch bones by 5-12 mm SD within a take.
- :func:`put_on_floor` moves the whole take up or down so that its lowest joint over the take is on the floor
  (y = 0), the convention every training clip was prepared with (HumanML3D's floor): a decoded take may otherwise
  sink into the floor or hover above it all take long.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from mld_core.motion import skeleton as sk
from mld_core.motion.features import FOOT_CONTACT, RIC, features_to_joints, gaussian_filter1d
from mld_core.motion.quaternion import turn_about_y

FOOT_JOINTS = (7, 10, 8, 11)  # the order of the contact channels: left ankle, left toe, right ankle, right toe


@dataclass
class RepairConfig:
    """The repairs a pipeline applies to each free take (a model folder's config.json "repair" entry)."""

    bone_lengths: bool = True  # features_with_bone_lengths: one skeleton per take
    plant_feet: bool = True  # plant_feet: the root moves so that planted feet do not slide
    contact_height_m: float = 0.05  # a foot joint counts as planted only this close to its lowest height
    model_weight: float = 0.05  # weight of the generated root step against a fully planted foot
    smooth_frames: float = 1.0  # Gaussian sigma (frames) applied to the correction of the root steps
    max_correction_m: float = 0.05  # per frame: a larger correction is no plant but a pose jump, and is capped
    keep_travel_frames: float = 0.0  # Gaussian sigma (frames) > 0: the root keeps its generated travel at this scale
    min_travel_kept: float = 0.8  # planting may shorten a take's travel (start to end) to this share, not below
    min_travel_m: float = 0.3  # takes that travel less than this are planted fully
    lock_feet: bool = True  # lock_feet: planted feet held in place by the leg (after the root is planted)
    lock_release: float = 0.5  # share of a foot's held shift let go per frame while that foot is in the air
    max_lock_shift_m: float = 0.25  # a foot is never held further than this from where it was generated
    lock_min_knee_deg: float = 5.0  # a foot is held only as far as the leg reaches with the knee bent this much
    lock_max_double_support: float = 0.7  # takes with both feet planted in more of their frames shuffle: not locked
    on_floor: bool = False  # put_on_floor: the take's lowest joint on the floor (after the other repairs)


def repair_features(features: np.ndarray, config: RepairConfig | None = None) -> np.ndarray:
    """One take's features (T, 263) with the repairs ``config`` turns on, in order: bone lengths, planted feet,
    locked feet, on the floor."""
    cfg = config or RepairConfig()
    out = np.asarray(features, dtype=np.float64)
    if cfg.bone_lengths:
        out = features_with_bone_lengths(out)
    if cfg.plant_feet:
        out = plant_feet(out, cfg)
    if cfg.lock_feet:
        out = lock_feet(out, cfg)
    if cfg.on_floor:
        out = put_on_floor(out)
    return out.astype(np.asarray(features).dtype)


def repair_rows(features: np.ndarray, lengths: list, config: RepairConfig) -> np.ndarray:
    """Each row's first ``lengths[i]`` frames of ``features`` (B, T, F) with the repairs of ``config`` applied (a copy;
    263-d features only)."""
    if features.shape[-1] != 263 or not (config.bone_lengths or config.plant_feet or config.lock_feet
                                         or config.on_floor):
        return features
    out = features.copy()
    for i, n in enumerate(lengths):
        out[i, :n] = repair_features(features[i, :n], config)
    return out


@dataclass
class Repair:
    """The fix: every take's features repaired (:func:`repair_rows`)."""

    config: RepairConfig
    timings: ClassVar[tuple] = ("repair_s",)

    def apply(self, takes, decoder):
        return replace(takes, features=repair_rows(takes.features, takes.lengths.tolist(), self.config))


def put_on_floor(features: np.ndarray) -> np.ndarray:
    """Features (T, 263) moved up or down as a whole so that the lowest joint over the take is at y = 0 (a copy):
    the root height and every joint's height (RIC keeps heights in world units) shift alike."""
    f = np.asarray(features, dtype=np.float64).copy()
    heights = f[:, RIC][:, 1::3]  # (T, 21): joints 1..21; the root's is channel 3
    floor = min(float(f[:, 3].min()), float(heights.min()))
    f[:, 3] -= floor
    f[:, RIC.start + 1:RIC.stop:3] -= floor
    return f


def _root_half_angle(features: np.ndarray) -> np.ndarray:
    """The half-angles a (T,) of the root rotations (cos a, 0, sin a, 0) of features (T, 263), as recover_root
    computes them, in numpy (a take's repair is many small operations: numpy keeps each one cheap)."""
    return np.cumsum(np.concatenate([[0.0], features[:-1, 0]]))  # (T,)


def _world_offsets(features: np.ndarray, half_angle: np.ndarray) -> np.ndarray:
    """Foot joints relative to the root's ground position, in world axes: (T, 4, 3)."""
    ric = features[:, RIC].reshape(len(features), 21, 3)  # (T, 21, 3)
    feet = ric[:, [j - 1 for j in FOOT_JOINTS]]  # (T, 4, 3)
    return turn_about_y(-half_angle[:, None], feet)


def plant_feet(features: np.ndarray, config: RepairConfig | None = None) -> np.ndarray:
    """Features (T, 263) with the root's ground velocity re-estimated so planted feet stay put (a copy)."""
    cfg = config or RepairConfig()
    f = np.asarray(features, dtype=np.float64)
    if len(f) < 3:
        return f.copy()
    half_angle = _root_half_angle(f)  # (T,)
    offsets = _world_offsets(f, half_angle)  # (T, 4, 3)
    model_step = _root_steps(f, half_angle)  # (T-1, 2) world displacement t -> t+1

    foot_step = -(offsets[1:, :, [0, 2]] - offsets[:-1, :, [0, 2]])  # (T-1, 4, 2) root steps that plant each joint
    height = offsets[:, :, 1] - offsets[:, :, 1].min(axis=0)  # (T, 4)
    low = (height[:-1] < cfg.contact_height_m) & (height[1:] < cfg.contact_height_m)  # (T-1, 4)
    weight = np.clip(f[:-1, FOOT_CONTACT], 0.0, 1.0) * low  # (T-1, 4)
    total = cfg.model_weight + weight.sum(axis=1, keepdims=True)  # (T-1, 1)
    step = (cfg.model_weight * model_step + (weight[:, :, None] * foot_step).sum(axis=1)) / total  # (T-1, 2)
    correction = step - model_step
    size = np.linalg.norm(correction, axis=1, keepdims=True)
    correction *= np.minimum(1.0, cfg.max_correction_m / np.maximum(size, 1e-12))
    if cfg.keep_travel_frames > 0:  # only the slide within steps goes: the take still travels as generated
        correction = correction - gaussian_filter1d(correction, cfg.keep_travel_frames)
    if cfg.smooth_frames > 0:
        correction = gaussian_filter1d(correction, cfg.smooth_frames)
    correction *= _travel_share(model_step, correction, cfg)
    step = model_step + correction

    world = np.zeros((len(f) - 1, 3))
    world[:, 0], world[:, 2] = step[:, 0], step[:, 1]
    local = turn_about_y(half_angle[1:], world)  # back into the next frame's facing frame
    out = f.copy()
    out[:-1, 1], out[:-1, 2] = local[:, 0], local[:, 2]
    return out


LEGS = ((1, 4, 7, 10), (2, 5, 8, 11))  # hip, knee, ankle, toe


def lock_feet(features: np.ndarray, config: RepairConfig | None = None, segments: list | None = None) -> np.ndarray:
    """Features (T, 263) whose planted feet do not slide (a copy): each foot is shifted on the ground against the
    slide of its planted joint (:func:`foot_hold_shifts`) and the leg reaches it by bending the knee; the root,
    the other joints, the foot's own shape and the contact channels are unchanged. A segment (``segments``: frame
    ranges [(start, end), ...], default the whole take) whose feet are both planted in more than
    ``lock_max_double_support`` of its frames shuffles rather than steps: no foot is held there."""
    cfg = config or RepairConfig()
    f = np.asarray(features, dtype=np.float64)
    if len(f) < 3:
        return f.copy()
    half_angle = _root_half_angle(f)  # (T,)
    local = np.zeros((len(f), sk.NUM_JOINTS, 3))  # (T, 22, 3) root-relative, in the facing frame
    local[:, 0, 1] = f[:, 3]
    local[:, 1:] = f[:, RIC].reshape(len(f), 21, 3)
    world = features_to_joints(f)  # (T, 22, 3)
    stepping = np.zeros(len(f), dtype=bool)  # (T,) frames of the segments whose feet step
    for a, b in segments or [(0, len(f))]:
        stepping[a:b] = double_support_share(world[a:b], f[a:b, FOOT_CONTACT], cfg) <= cfg.lock_max_double_support
    if not stepping.any():
        return f.copy()  # the feet hardly leave the floor: holding them would only drag them along (a glide)
    shifts = foot_hold_shifts(world, f[:, FOOT_CONTACT] * stepping[:, None], cfg)  # (T, 2, 2) per leg
    hip, knee, ankle, toe = (list(j) for j in zip(*LEGS))  # each [left, right]
    shift = np.zeros((len(f), 2, 3))
    shift[:, :, [0, 2]] = shifts
    ankle_goal = local[:, ankle] + turn_about_y(half_angle[:, None], shift)  # (T, 2, 3) back in the facing frame
    upper = np.linalg.norm(local[:, knee] - local[:, hip], axis=-1, keepdims=True)  # (T, 2, 1)
    lower = np.linalg.norm(local[:, ankle] - local[:, knee], axis=-1, keepdims=True)
    knee_at, ankle_at = two_bone_ik(local[:, hip], ankle_goal, local[:, knee], upper, lower)  # (T, 2, 3) each
    held = np.abs(shifts).max(axis=-1) > 0  # (T, 2) feet that are held: only their legs move
    out_local = local.copy()
    for leg in range(2):
        rows = held[:, leg]
        out_local[rows, knee[leg]], out_local[rows, ankle[leg]] = knee_at[rows, leg], ankle_at[rows, leg]
        foot = local[rows, toe[leg]] - local[rows, ankle[leg]]
        out_local[rows, toe[leg]] = ankle_at[rows, leg] + foot  # the foot keeps its shape
    out = f.copy()
    out[:, RIC] = out_local[:, 1:].reshape(len(f), -1)
    return out


def _root_steps(features: np.ndarray, half_angle: np.ndarray) -> np.ndarray:
    """The root's ground steps (T-1, 2) in world x, z from frame t to t+1, as recover_root turns the velocity
    channels."""
    vel = np.zeros((len(features) - 1, 3))
    vel[:, 0], vel[:, 2] = features[:-1, 1], features[:-1, 2]
    return turn_about_y(-half_angle[1:], vel)[:, [0, 2]]


def _planted(world: np.ndarray, contact: np.ndarray, cfg: RepairConfig) -> tuple[np.ndarray, np.ndarray]:
    """Which foot joints (T, 4: left ankle, left toe, right ankle, right toe) are planted: the contact channel is on
    and the joint is within ``contact_height_m`` of its lowest height; and those heights (T, 4)."""
    feet = world[:, list(FOOT_JOINTS), 1]  # (T, 4)
    height = feet - feet.min(axis=0)
    return (contact > 0.5) & (height < cfg.contact_height_m), height


def double_support_share(world: np.ndarray, contact: np.ndarray, config: RepairConfig | None = None) -> float:
    """Share of frames in which both feet (ankle or toe) are planted: real walks 0.18 (at most 0.62 over all Bandai
    clips), walks backwards 0.33; generated walks backwards whose feet shuffle without lifting 0.9."""
    planted, _ = _planted(world, contact, config or RepairConfig())
    return float(((planted[:, 0] | planted[:, 1]) & (planted[:, 2] | planted[:, 3])).mean())


def foot_hold_shifts(world: np.ndarray, contact: np.ndarray, config: RepairConfig | None = None) -> np.ndarray:
    """Ground shifts (T, 2 legs, 2) that hold planted feet still: world joints (T, 22, 3), contact channels (T, 4).

    A joint is planted where its contact channel is on and it is within ``contact_height_m`` of its lowest height.
    Between two frames in which the toe is planted (else the ankle), the shift takes back the joint's ground
    step, so the shifted joint stays put; while neither is planted and the ankle or the toe is lifted above
    ``contact_height_m``, the shift decays by ``lock_release`` per frame (a foot still on the floor keeps it: letting
    go there would slide it). Its length is capped at ``max_lock_shift_m``. Each frame's shift is then
    shortened (:func:`_reachable_share`; the hold itself stays) until the hip reaches the shifted ankle with the
    knee bent ``lock_min_knee_deg``: out of that reach the foot trails its hold rather than straighten the leg."""
    cfg = config or RepairConfig()
    feet = world[:, list(FOOT_JOINTS)]  # (T, 4, 3) left ankle, left toe, right ankle, right toe
    planted, height = _planted(world, contact, cfg)  # (T, 4) each
    step = np.diff(feet[:, :, [0, 2]], axis=0)  # (T-1, 4, 2) each joint's ground step into frame t
    both = planted[1:] & planted[:-1]  # (T-1, 4) planted in frame t and the one before
    lifted = height[1:] >= cfg.contact_height_m  # (T-1, 4) off the ground in frame t
    keep, cap = 1.0 - cfg.lock_release, cfg.max_lock_shift_m
    shifts = np.zeros((len(world), 2, 2))
    for leg in range(2):
        ankle, toe = 2 * leg, 2 * leg + 1
        plant_step = np.where(both[:, toe, None], step[:, toe], step[:, ankle])  # (T-1, 2) what a hold takes back
        holding = (both[:, toe] | both[:, ankle]).tolist()
        releasing = (lifted[:, ankle] | lifted[:, toe]).tolist()  # a foot lets go in the air, not on the floor
        x = z = 0.0  # plain floats: the recurrence runs frame by frame
        for t, (dx, dz) in enumerate(plant_step.tolist()):
            if holding[t]:
                x, z = x - dx, z - dz
            elif releasing[t]:
                x, z = x * keep, z * keep
            size = (x * x + z * z) ** 0.5
            if size > cap:
                x, z = x * cap / size, z * cap / size
            shifts[t + 1, leg] = x, z
    hips, knees, ankles = world[:, [1, 2]], world[:, [4, 5]], world[:, [7, 8]]  # (T, 2, 3) each
    reach = _leg_reach(hips, knees, ankles, cfg.lock_min_knee_deg)  # (T, 2)
    return shifts * _reachable_share(ankles - hips, shifts, reach)[..., None]  # the leg goes as far as it can


def _leg_reach(hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray, min_knee_deg: float) -> np.ndarray:
    """The hip-to-ankle distance (...) of legs (..., 3 per joint) with their knees bent ``min_knee_deg``."""
    upper = np.linalg.norm(knee - hip, axis=-1)
    lower = np.linalg.norm(ankle - knee, axis=-1)
    return np.sqrt(upper ** 2 + lower ** 2 + 2.0 * upper * lower * np.cos(np.radians(min_knee_deg)))


def _reachable_share(to_ankle: np.ndarray, shift: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """The largest share s (...) in [0, 1] of ground shifts (..., 2: x, z) with |to_ankle + s (x, 0, z)| <= reach
    (to_ankle (..., 3): hip to ankle), or, where the generated leg is already straighter than that, no further
    than the generated ankle: how much of a hold the leg reaches without straightening."""
    vv = (shift ** 2).sum(-1)
    av = to_ankle[..., 0] * shift[..., 0] + to_ankle[..., 2] * shift[..., 1]
    rest = np.minimum(0.0, (to_ankle ** 2).sum(-1) - reach ** 2)  # <= 0: the unshifted ankle is within reach
    inside = vv + 2.0 * av + rest <= 0.0  # the whole shift is reachable
    root = (-av + np.sqrt(np.maximum(av * av - vv * rest, 0.0))) / np.maximum(vv, 1e-18)
    return np.where(inside | (vv == 0.0), 1.0, np.clip(root, 0.0, 1.0))


def features_with_bone_lengths(features: np.ndarray, lengths: np.ndarray | None = None) -> np.ndarray:
    """Features (T, 263) whose root-relative joints (RIC) have one length per bone (default: the reference skeleton,
    which every training clip has): bones keep their directions (keep_bone_lengths), except the legs: each toe
    stays where it was generated, the ankle sits one foot length behind it along the generated foot, and the knee
    bends to reach it (two-bone IK), so planted feet stay planted. The root, rotations and contact channels are unchanged."""
    f = np.asarray(features, dtype=np.float64)
    target = np.asarray(sk.REFERENCE_BONE_LENGTHS if lengths is None else lengths, np.float64)
    local = np.zeros((len(f), sk.NUM_JOINTS, 3))  # (T, 22, 3) the pelvis at x = z = 0
    local[:, 0, 1] = f[:, 3]
    local[:, 1:] = f[:, RIC].reshape(len(f), 21, 3)
    fixed = keep_bone_lengths(local, target)
    for hip, knee, ankle, toe in LEGS:  # the toe stays; the ankle sits one foot length behind it, the knee bends
        foot = local[:, toe] - local[:, ankle]  # (T, 3)
        foot_dir = foot / np.maximum(np.linalg.norm(foot, axis=-1, keepdims=True), 1e-9)
        ankle_goal = local[:, toe] - foot_dir * target[toe]
        fixed[:, knee], fixed[:, ankle] = two_bone_ik(fixed[:, hip], ankle_goal, local[:, knee], target[knee],
                                                      target[ankle])
        fixed[:, toe] = fixed[:, ankle] + foot_dir * target[toe]
    out = f.copy()
    out[:, RIC] = fixed[:, 1:].reshape(len(f), -1)
    return out


def two_bone_ik(root: np.ndarray, goal: np.ndarray, pole: np.ndarray, upper: float, lower: float,
                forward=(0.0, 0.0, 1.0), forward_bias: float = 0.02):
    """Middle and end joints (T, 3) each of a chain root -> middle -> end with the given bone lengths whose end
    reaches ``goal`` (or points at it, fully stretched, when out of reach), bending towards ``pole``; a small bias
    towards ``forward`` (metres) decides the bend where the pole lies on the root-goal line (a straight leg)."""
    to_goal = goal - root  # (T, 3)
    dist = np.linalg.norm(to_goal, axis=-1, keepdims=True)  # (T, 1)
    axis = to_goal / np.maximum(dist, 1e-9)
    d = np.clip(dist, abs(upper - lower) + 1e-6, upper + lower - 1e-6)
    hint = (pole - root) + forward_bias * np.asarray(forward, np.float64)
    bend = hint - (hint * axis).sum(-1, keepdims=True) * axis  # the pole, perpendicular to the axis
    bend_len = np.linalg.norm(bend, axis=-1, keepdims=True)
    fallback = np.cross(axis, np.array([1.0, 0.0, 0.0]))  # knees forward (+Z when the leg hangs down)
    bend = np.where(bend_len > 1e-6, bend / np.maximum(bend_len, 1e-9), fallback)
    along = (upper ** 2 - lower ** 2 + d ** 2) / (2.0 * d)  # (T, 1) distance of the middle joint along the axis
    across = np.sqrt(np.maximum(upper ** 2 - along ** 2, 0.0))
    middle = root + axis * along + bend * across
    return middle, root + axis * d


def _travel_share(model_step: np.ndarray, correction: np.ndarray, cfg: RepairConfig) -> float:
    """How much of the correction to apply (0-1) so the take keeps ``min_travel_kept`` of its travel: where the
    generated legs do not carry the generated travel (feet that barely step on a walk backwards), planting them
    fully would stop the take; planting less keeps what the prompt asked for and some of the slide."""
    travel = np.linalg.norm(model_step.sum(axis=0))
    if travel < cfg.min_travel_m:
        return 1.0
    kept = np.linalg.norm((model_step + correction).sum(axis=0)) / travel
    if kept >= cfg.min_travel_kept:
        return 1.0
    return float(np.clip((1.0 - cfg.min_travel_kept) / max(1.0 - kept, 1e-9), 0.0, 1.0))


def _chains() -> np.ndarray:
    """(22, 21): row k marks the bones (by child joint - 1) from the pelvis to joint k."""
    chains = np.zeros((sk.NUM_JOINTS, sk.NUM_JOINTS - 1))
    for k in range(1, sk.NUM_JOINTS):  # parents come before children
        chains[k] = chains[sk.PARENTS[k]]
        chains[k, k - 1] = 1.0
    return chains


_CHAINS = _chains()


def keep_bone_lengths(joints: np.ndarray, lengths: np.ndarray | None = None) -> np.ndarray:
    """Joints (T, 22, 3) rebuilt from the pelvis outwards with one length per bone (default: the take's median
    lengths), each bone keeping its direction."""
    j = np.asarray(joints, dtype=np.float64)
    parents = np.asarray(sk.PARENTS)
    bones = j[:, 1:] - j[:, parents[1:]]  # (T, 21, 3)
    norm = np.linalg.norm(bones, axis=-1, keepdims=True)  # (T, 21, 1)
    target = np.median(norm[..., 0], axis=0) if lengths is None else np.asarray(lengths, np.float64)[1:]
    dirs = np.where(norm > 1e-9, bones / np.maximum(norm, 1e-9), sk.RAW_OFFSETS[1:])
    bones = (dirs * target[:, None]).transpose(1, 0, 2).reshape(len(target), -1)  # (21, T * 3)
    out = j[:, :1] + (_CHAINS @ bones).reshape(sk.NUM_JOINTS, len(j), 3).transpose(1, 0, 2)  # (T, 22, 3)
    return out.astype(np.asarray(joints).dtype if np.asarray(joints).dtype.kind == "f" else np.float64)
