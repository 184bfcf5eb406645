"""Physical checks on joint positions: what a viewer notices first about a generated motion.

Does the motion raise or wave the hand named in the prompt, turn the named way, walk, run or walk
backwards, bow, kick? Every check reads joints (T, 22, 3) in metres, Y up, facing +Z at frame 0, on the
SMPL-22 skeleton (``mld_core.motion.skeleton``), where the performer's left is +X, and returns a
:class:`Check`: a verdict plus the number it was decided on (and a few more numbers in ``detail``).

Conventions:

- ``across``: the body's horizontal left direction, (left hip - right hip) + (left shoulder - right
  shoulder) with Y removed; ``forward`` = across x up (+Z at frame 0 of a canonical clip).
- Yaw: the angle of ``forward`` from +Z towards +X, i.e. positive about +Y (counter-clockwise seen from
  above). Turning to the performer's LEFT makes the yaw grow: measured on Bandai Namco walk-turn-left
  clips (median +93 degrees) and walk-turn-right clips (median -93 degrees).

The thresholds are module constants, calibrated on the real clips of the Bandai Namco data prepared by
``python -m mld_core data prepare bandai`` (6,152 clips incl. mirrored copies; all splits, since nothing
here is learned); each constant's comment says what it separates. On the test split every content passes
its own checks at 0.91-1.00 (byebye 0.5 of 4 clips) and every sided clip uses its named side
(``python research/side_accuracy.py --data DIR --real-only`` prints the table).

Only numpy: this runs on generated motions inside the evaluation scripts and in tests.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mld_core.motion import skeleton as sk

__all__ = [
    "Check",
    "body_frame",
    "facing_yaw",
    "raised_hand",
    "waving",
    "turn",
    "locomotion",
    "drift",
    "bow",
    "kick",
    "jump",
    "get_low",
    "on_ground",
    "crawl",
    "reach_floor",
    "inverted",
    "stand_up",
    "climb",
    "throw",
    "shows",
    "SHOWN_VERBS",
    "classify",
    "verdicts",
    "expected_for",
    "passes",
    "failed_checks",
    "side_of",
    "side_check_for",
    "detected_side",
    "mirror_label",
    "CHECKED_LABELS",
    "CHECKS",
]

# Joint indices (SMPL-22 order).
PELVIS, L_HIP, R_HIP = 0, 1, 2
L_ANKLE, R_ANKLE, L_FOOT, R_FOOT = 7, 8, 10, 11
NECK, HEAD = 12, 15
L_SHOULDER, R_SHOULDER, L_ELBOW, R_ELBOW, L_WRIST, R_WRIST = 16, 17, 18, 19, 20, 21
assert sk.JOINT_NAMES[L_WRIST] == "left_wrist" and sk.JOINT_NAMES[R_SHOULDER] == "right_shoulder"
assert sk.JOINT_NAMES[NECK] == "neck" and sk.JOINT_NAMES[L_FOOT] == "left_foot"

# ---- thresholds (calibrated on the real Bandai Namco clips, see the module docstring) -----------------------

# Raised hand: the wrist, held for RAISE_HOLD_S, is at most 10 cm below its shoulder. On the real clips the
# raised wrist of raise-up-*/wave-* reaches >= -0.05 m (feminine style raises only to shoulder height, hence
# not "above the head"), the other wrist of one-hand clips stays <= -0.26 m, and 92% of the clips that only
# walk/run/bow keep both wrists below -0.085 m.
RAISE_ABOVE_SHOULDER_M = -0.10
RAISE_HOLD_S = 0.25

# Waving: while the wrist is raised (above shoulder + WAVE_ABOVE_SHOULDER_M) its sideways position relative
# to the shoulder (along ``across``) swings back and forth; a swing is a move of >= WAVE_SWING_M against the
# previous direction (hysteresis). Raising and lowering an arm moves the wrist sideways about once each way.
# Swept over height -0.10..-0.30 m, swing 3-4 cm, 3-4 swings: this choice gives wave-* clips 0.97-0.99 and
# one-hand raise-up-* clips 0.001 false waves (walks 0.07: some styles swing the arms high); lower heights
# catch a few more of the slow, low "bye" waves but make 15-50% of walks and runs "wave".
WAVE_ABOVE_SHOULDER_M = -0.10
WAVE_SWING_M = 0.03
WAVE_MIN_SWINGS = 4

# Turn: yaw change between the median over the first and the last TURN_WINDOW of the clip. Real walks
# turn <= 23 degrees, walk-turn-* clips 81-104 degrees (5th-95th percentile). Medians over a fifth of the
# clip ignore the turn-around some performers make in the last half second of a clip.
TURN_MIN_DEG = 45.0
TURN_WINDOW = 0.2

# Locomotion from the pelvis' horizontal velocity. Standing clips (bow, wave, raise, guide) move the
# pelvis <= 0.2 m/s on average, the slowest walks 0.38 m/s. Travel without stepping is a "glide" (a body
# sliding over the floor, which an undertrained decoder produces): the ankles' fore-aft separation spans
# < GLIDE_MAX_STRIDE_M over the clip (real walks, runs and walk-backs: >= 0.39 m, 98% >= 0.47 m). Running:
# a flight phase - no ankle or toe on the ground, i.e. each one both moving >= FOOT_STILL_MPS and higher
# than FOOT_GROUND_M above the floor (the lowest foot's 5th percentile), so that feet sliding over the floor
# count as grounded - in >= RUN_MIN_FLIGHT of the frames (walks: 0 in every clip), or a mean speed
# >= RUN_MIN_SPEED (walks <= 1.94 m/s). Real runs pass 0.91 (0.93 if sliding feet counted as flying), dash
# 1.0; the jogs without a flight phase (the "elderly" runs, 1.2-1.5 m/s) read as walks.
MOVE_MIN_SPEED = 0.3
GLIDE_MAX_STRIDE_M = 0.3
FOOT_STILL_MPS = 0.6
FOOT_GROUND_M = 0.01
RUN_MIN_FLIGHT = 0.1
RUN_MIN_SPEED = 2.0
# Direction of travel relative to the body's own facing (heading 0 = forward, +90 = to the left):
# forward within +-60 degrees, backward beyond +-120 (walk-back: 179 degrees), sideways in between.
FORWARD_MAX_DEG = 60.0
BACKWARD_MIN_DEG = 120.0

# Drift: walking forward diagonally without turning (walk-left / walk-right: 17-55 degrees to the side;
# straight walks <= 10 degrees and walk-turn-* <= 13).
DRIFT_MIN_DEG = 15.0

# Bow: the spine (pelvis -> neck) leans forward >= BOW_MIN_PITCH_DEG and the head drops >= BOW_MIN_DROP_M
# relative to the pelvis, held for BOW_HOLD_S, and the head comes back up at least half of the drop later.
# Real bows: pitch >= 24 degrees, drop >= 0.08 m, all come back up, pelvis speed <= 0.2 m/s; runs lean
# and bob as much, hence the speed limit; guide and call, which lean forward to gesture or shout, pass it.
BOW_MIN_PITCH_DEG = 20.0
BOW_MIN_DROP_M = 0.06
BOW_HOLD_S = 0.15
BOW_RETURN_FRACTION = 0.5
BOW_MAX_SPEED = 0.5

# Kick: an ankle >= KICK_MIN_HEIGHT_M above the floor and >= KICK_MIN_FORWARD_M in front of the pelvis
# (running lifts the heels up to 0.7 m, but behind the body). Real kicks: 1.0 m.
KICK_MIN_HEIGHT_M = 0.5
KICK_MIN_FORWARD_M = 0.25
KICK_HOLD_S = 0.1

# Jump: every foot joint at least JUMP_FEET_M above the floor for at least JUMP_MIN_FLIGHT_S (and at most
# JUMP_MAX_FLIGHT_S) while the pelvis is at least JUMP_RISE_M above its median height (a running stride's flight keeps
# the pelvis level and lasts 0.1-0.2 s).
JUMP_FEET_M = 0.05
JUMP_MIN_FLIGHT_S = 0.15
JUMP_RISE_M = 0.08
# A "flight" longer than this is standing on something higher (a step, a platform, uneven terrain), not a jump; the
# longest real CMU jumps fly about 0.6 s.
JUMP_MAX_FLIGHT_S = 1.0

# The new verbs of the CMU data (calibrated on its real trials: docs/physical_checks.md, "The CMU verbs"). Heights
# are above the floor, the FLOOR_PERCENTILE of each frame's lowest joint (a body lying down has no foot lower than
# the rest). The reference skeleton stands with its pelvis at about 0.93 m and its head at about 1.6 m.
FLOOR_PERCENTILE = 5.0
# Gets low (sit, squat, kneel, crouch): the pelvis held at most LOW_PELVIS_M above the floor for LOW_HOLD_S.
LOW_PELVIS_M = 0.70
LOW_HOLD_S = 0.3
# On the ground (lie, fall, sit on the floor): the pelvis held at most GROUND_PELVIS_M above the floor.
GROUND_PELVIS_M = 0.40
GROUND_HOLD_S = 0.3
# Crawl: on all fours (head at most CRAWL_HEAD_M, pelvis at most CRAWL_PELVIS_M, a wrist at most CRAWL_WRIST_M above
# the floor) for at least CRAWL_MIN_S in all, travelling at least CRAWL_TRAVEL_M horizontally while so.
CRAWL_HEAD_M = 0.85
CRAWL_PELVIS_M = 0.75
CRAWL_WRIST_M = 0.25
CRAWL_MIN_S = 1.0
CRAWL_TRAVEL_M = 0.4
# Reaches the floor (pick up): a wrist held at most REACH_WRIST_M above the floor for REACH_HOLD_S while the pelvis is
# at least REACH_PELVIS_M up (not lying or sitting on the ground).
REACH_WRIST_M = 0.33
REACH_HOLD_S = 0.1
REACH_PELVIS_M = 0.35
# Inverted (handstand, cartwheel, flip): both ankles above the head for INVERTED_HOLD_S.
INVERTED_HOLD_S = 0.1
# Stands up: the pelvis held at most STAND_LOW_M for STAND_LOW_S, then later held at least STAND_HIGH_M for
# STAND_HIGH_S.
STAND_LOW_M = 0.60
STAND_LOW_S = 0.3
STAND_HIGH_M = 0.80
STAND_HIGH_S = 0.5
# Climb: both feet held at least CLIMB_FEET_M above the floor for CLIMB_HOLD_S (a jump's flight is shorter).
CLIMB_FEET_M = 0.25
CLIMB_HOLD_S = 0.6
# Throw: a wrist moves at least THROW_MPS relative to the pelvis, mostly forward, with the hand at least at
# THROW_WRIST_M below its shoulder (not a swinging arm at the hip).
THROW_MPS = 3.2
THROW_FORWARD = 0.5
THROW_WRIST_M = -0.35

SIDES = ("left", "right")


@dataclass(frozen=True)
class Check:
    """One check's outcome: ``verdict`` (a word or a bool), ``value`` the number it was decided on, more numbers
    in ``detail``."""

    verdict: str | bool
    value: float
    detail: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"verdict": self.verdict, "value": float(self.value), **{k: _plain(v) for k, v in self.detail.items()}}


def _plain(v):
    return float(v) if isinstance(v, (float, np.floating)) else int(v) if isinstance(v, np.integer) else v


# ---- helpers ----------------------------------------------------------------------------------------------


def _as_joints(joints) -> np.ndarray:
    j = np.asarray(joints, dtype=np.float64)
    if j.ndim != 3 or j.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"joints must have shape (T, 22, 3), got {j.shape}")
    if len(j) < 2:
        raise ValueError(f"need at least 2 frames, got {len(j)}")
    if not np.isfinite(j).all():
        raise ValueError("joints contain NaN or infinite values")
    return j


def _frames(seconds: float, fps: float) -> int:
    return max(1, int(round(seconds * fps)))


def _held_max(x: np.ndarray, n: int) -> float:
    """The highest level that ``x`` stays at or above for ``n`` consecutive frames (max over windows of the min)."""
    if len(x) <= n:
        return float(x.min())
    return float(np.lib.stride_tricks.sliding_window_view(x, n).min(axis=1).max())


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True."""
    m = np.concatenate([[False], mask.astype(bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist()))


def _swings(x: np.ndarray, amplitude: float) -> int:
    """Number of moves of at least ``amplitude`` that alternate in direction (a peak detector with hysteresis)."""
    if len(x) < 2:
        return 0
    lo = hi = float(x[0])
    direction, extreme, count = 0, 0.0, 0
    for v in map(float, x):
        if direction == 0:
            lo, hi = min(lo, v), max(hi, v)
            if v - lo >= amplitude:
                direction, extreme, count = 1, v, 1
            elif hi - v >= amplitude:
                direction, extreme, count = -1, v, 1
        elif direction > 0:
            if v > extreme:
                extreme = v
            elif extreme - v >= amplitude:
                direction, extreme, count = -1, v, count + 1
        else:
            if v < extreme:
                extreme = v
            elif v - extreme >= amplitude:
                direction, extreme, count = 1, v, count + 1
    return count


def _side(left: bool, right: bool) -> str:
    return "both" if left and right else "left" if left else "right" if right else "none"


def body_frame(joints) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame horizontal unit vectors (across = the body's left, forward), each (T, 3)."""
    j = _as_joints(joints)
    across = (j[:, L_HIP] - j[:, R_HIP]) + (j[:, L_SHOULDER] - j[:, R_SHOULDER])  # (T, 3)
    across[:, 1] = 0.0
    norm = np.linalg.norm(across, axis=1, keepdims=True)
    across = np.where(norm > 1e-8, across / np.maximum(norm, 1e-8), np.array([1.0, 0.0, 0.0]))
    forward = np.stack([-across[:, 2], np.zeros(len(j)), across[:, 0]], axis=1)  # across x up, (T, 3)
    return across, forward


def facing_yaw(joints) -> np.ndarray:
    """Unwrapped facing yaw (T,) in radians: 0 = facing +Z, positive = turned towards +X (to the left)."""
    _, forward = body_frame(joints)
    return np.unwrap(np.arctan2(forward[:, 0], forward[:, 2]))


# ---- the checks --------------------------------------------------------------------------------------------


def raised_hand(joints, fps: float = sk.FPS) -> Check:
    """Which wrists are held up near or above shoulder height: "left", "right", "both" or "none".

    value: the held height (m) of the higher wrist relative to its shoulder; detail: each side's held
    height relative to its shoulder and to the head.
    """
    j = _as_joints(joints)
    n = _frames(RAISE_HOLD_S, fps)
    left = _held_max(j[:, L_WRIST, 1] - j[:, L_SHOULDER, 1], n)
    right = _held_max(j[:, R_WRIST, 1] - j[:, R_SHOULDER, 1], n)
    verdict = _side(left > RAISE_ABOVE_SHOULDER_M, right > RAISE_ABOVE_SHOULDER_M)
    detail = {
        "left_above_shoulder_m": left,
        "right_above_shoulder_m": right,
        "left_above_head_m": _held_max(j[:, L_WRIST, 1] - j[:, HEAD, 1], n),
        "right_above_head_m": _held_max(j[:, R_WRIST, 1] - j[:, HEAD, 1], n),
    }
    return Check(verdict, max(left, right), detail)


def _hand_swings(j: np.ndarray, across: np.ndarray, wrist: int, shoulder: int) -> tuple[int, float]:
    raised = (j[:, wrist, 1] - j[:, shoulder, 1]) > WAVE_ABOVE_SHOULDER_M
    lateral = np.einsum("tc,tc->t", j[:, wrist] - j[:, shoulder], across)  # (T,) sideways, + = body's left
    swings, amplitude = 0, 0.0
    for a, b in _runs(raised):
        swings += _swings(lateral[a:b], WAVE_SWING_M)
        amplitude = max(amplitude, float(np.ptp(lateral[a:b])))
    return swings, amplitude


def waving(joints, fps: float = sk.FPS) -> Check:
    """Which raised hands swing side to side: "left", "right", "both" or "none".

    value: the larger swing count; detail: swings and sideways range (m) per hand, swings per second.
    """
    j = _as_joints(joints)
    across, _ = body_frame(j)
    ls, la = _hand_swings(j, across, L_WRIST, L_SHOULDER)
    rs, ra = _hand_swings(j, across, R_WRIST, R_SHOULDER)
    verdict = _side(ls >= WAVE_MIN_SWINGS, rs >= WAVE_MIN_SWINGS)
    seconds = len(j) / fps
    detail = {"left_swings": ls, "right_swings": rs, "left_range_m": la, "right_range_m": ra,
              "swings_per_s": max(ls, rs) / seconds}
    return Check(verdict, max(ls, rs), detail)


def turn(joints, fps: float = sk.FPS) -> Check:
    """Turn direction "left" / "right" / "none" and the angle (degrees, positive = left, counter-clockwise
    seen from above) between the median facing of the first and the last fifth of the clip."""
    yaw = facing_yaw(joints)
    k = max(1, int(round(TURN_WINDOW * len(yaw))))
    angle = float(np.degrees(np.median(yaw[-k:]) - np.median(yaw[:k])))
    verdict = "left" if angle >= TURN_MIN_DEG else "right" if angle <= -TURN_MIN_DEG else "none"
    total = float(np.degrees(yaw.max() - yaw.min()))
    return Check(verdict, angle, {"yaw_range_deg": total})


def _travel(j: np.ndarray, fps: float) -> dict:
    across, forward = body_frame(j)
    v = np.diff(j[:, PELVIS], axis=0) * fps  # (T-1, 3) m/s
    v[:, 1] = 0.0
    speed = float(np.linalg.norm(v, axis=1).mean())
    fwd = float(np.einsum("tc,tc->t", v, forward[:-1]).mean())
    lat = float(np.einsum("tc,tc->t", v, across[:-1]).mean())
    feet = j[:, [L_ANKLE, L_FOOT, R_ANKLE, R_FOOT]]  # (T, 4, 3)
    floor = float(np.percentile(feet[:, :, 1].min(axis=1), 5))
    moving = np.linalg.norm(np.diff(feet, axis=0), axis=2) * fps >= FOOT_STILL_MPS  # (T-1, 4)
    raised = feet[1:, :, 1] - floor > FOOT_GROUND_M  # (T-1, 4)
    flight = float((moving & raised).all(axis=1).mean())
    stride = float(np.ptp(np.einsum("tc,tc->t", j[:, L_ANKLE] - j[:, R_ANKLE], forward)))
    heading = float(np.degrees(np.arctan2(lat, fwd))) if abs(fwd) + abs(lat) > 1e-9 else 0.0
    return {"speed_mps": speed, "forward_mps": fwd, "lateral_mps": lat, "heading_deg": heading,
            "flight_fraction": flight, "stride_m": stride}


def locomotion(joints, fps: float = sk.FPS) -> Check:
    """How the body travels: "stand", "walk", "run", "backward", "sideways" or "glide" (moving without steps).

    value: mean horizontal pelvis speed (m/s); detail: mean forward / leftward speed in the body's own
    frame, heading (degrees from the facing, + = left), the fraction of frames with no foot on the ground
    and the range of the ankles' fore-aft separation (m).
    """
    j = _as_joints(joints)
    t = _travel(j, fps)
    h = abs(t["heading_deg"])
    if t["speed_mps"] < MOVE_MIN_SPEED:
        verdict = "stand"
    elif t["stride_m"] < GLIDE_MAX_STRIDE_M:
        verdict = "glide"
    elif h >= BACKWARD_MIN_DEG:
        verdict = "backward"
    elif h > FORWARD_MAX_DEG:
        verdict = "sideways"
    elif t["flight_fraction"] >= RUN_MIN_FLIGHT or t["speed_mps"] >= RUN_MIN_SPEED:
        verdict = "run"
    else:
        verdict = "walk"
    return Check(verdict, t["speed_mps"], t)


def drift(joints, fps: float = sk.FPS) -> Check:
    """Travelling forward but diagonally to one side without facing it: "left" / "right" / "none";
    value: heading (degrees, + = left)."""
    j = _as_joints(joints)
    t = _travel(j, fps)
    h = t["heading_deg"]
    moving = t["speed_mps"] >= MOVE_MIN_SPEED and abs(h) <= FORWARD_MAX_DEG
    verdict = "none"
    if moving and h >= DRIFT_MIN_DEG:
        verdict = "left"
    elif moving and h <= -DRIFT_MIN_DEG:
        verdict = "right"
    return Check(verdict, h, {"speed_mps": t["speed_mps"]})


def bow(joints, fps: float = sk.FPS) -> Check:
    """A bow: the spine leans forward and the head drops relative to the pelvis, then comes back up.

    value: held forward lean of the spine (degrees); detail: the head's held drop (m) and whether it returned.
    """
    j = _as_joints(joints)
    _, forward = body_frame(j)
    n = _frames(BOW_HOLD_S, fps)
    spine = j[:, NECK] - j[:, PELVIS]  # (T, 3)
    pitch = np.degrees(np.arctan2(np.einsum("tc,tc->t", spine, forward), spine[:, 1]))  # (T,) + = forward
    held_pitch = _held_max(pitch, n)
    head = j[:, HEAD, 1] - j[:, PELVIS, 1]  # (T,)
    upright = float(np.percentile(head, 90))
    drop = _held_max(upright - head, n)
    deepest = int(np.argmin(head))
    returned = bool(drop > 0 and (head[deepest + 1:] >= upright - BOW_RETURN_FRACTION * drop).any())
    speed = float(np.linalg.norm(np.diff(j[:, PELVIS, ::2], axis=0), axis=1).mean() * fps)
    verdict = bool(held_pitch >= BOW_MIN_PITCH_DEG and drop >= BOW_MIN_DROP_M and returned and speed <= BOW_MAX_SPEED)
    return Check(verdict, held_pitch, {"head_drop_m": drop, "returned": returned, "speed_mps": speed})


def kick(joints, fps: float = sk.FPS) -> Check:
    """Which foot kicks (held high in front of the body): "left", "right", "both" or "none";
    value: the highest held ankle height above the floor (m)."""
    j = _as_joints(joints)
    _, forward = body_frame(j)
    n = _frames(KICK_HOLD_S, fps)
    floor = float(np.percentile(j[:, [L_ANKLE, R_ANKLE, L_FOOT, R_FOOT], 1].min(axis=1), 5))
    out = {}
    for side, ankle in (("left", L_ANKLE), ("right", R_ANKLE)):
        height = j[:, ankle, 1] - floor
        ahead = np.einsum("tc,tc->t", j[:, ankle] - j[:, PELVIS], forward)
        out[side] = _held_max(np.where(ahead >= KICK_MIN_FORWARD_M, height, -1.0), n)
    verdict = _side(out["left"] >= KICK_MIN_HEIGHT_M, out["right"] >= KICK_MIN_HEIGHT_M)
    return Check(verdict, max(out.values()), {"left_height_m": out["left"], "right_height_m": out["right"]})


def jump(joints, fps: float = sk.FPS) -> Check:
    """A jump: both feet off the floor with the pelvis rising; verdict True/False; value: the longest such flight
    (s)."""
    j = _as_joints(joints)
    feet = j[:, [L_ANKLE, R_ANKLE, L_FOOT, R_FOOT], 1]  # (T, 4)
    floor = float(np.percentile(feet.min(axis=1), 5))
    rise = j[:, PELVIS, 1] - float(np.median(j[:, PELVIS, 1]))
    flying = (feet.min(axis=1) - floor >= JUMP_FEET_M) & (rise >= JUMP_RISE_M)
    flights = [(b - a) / fps for a, b in _runs(flying) if (b - a) / fps <= JUMP_MAX_FLIGHT_S]
    longest = max(flights, default=0.0)
    return Check(longest >= JUMP_MIN_FLIGHT_S, longest, {"max_rise_m": float(rise.max())})


def _floor(j: np.ndarray) -> float:
    """The floor: the FLOOR_PERCENTILE of each frame's lowest joint height."""
    return float(np.percentile(j[:, :, 1].min(axis=1), FLOOR_PERCENTILE))


def get_low(joints, fps: float = sk.FPS) -> Check:
    """The body gets low (sits, squats, kneels, crouches): True/False; value: the lowest held pelvis height (m)."""
    j = _as_joints(joints)
    pelvis = j[:, PELVIS, 1] - _floor(j)
    low = -_held_max(-pelvis, _frames(LOW_HOLD_S, fps))
    return Check(bool(low <= LOW_PELVIS_M), low)


def on_ground(joints, fps: float = sk.FPS) -> Check:
    """The body is on the ground (lies, falls, sits on the floor): True/False; value: the lowest held pelvis
    height (m)."""
    j = _as_joints(joints)
    pelvis = j[:, PELVIS, 1] - _floor(j)
    low = -_held_max(-pelvis, _frames(GROUND_HOLD_S, fps))
    return Check(bool(low <= GROUND_PELVIS_M), low)


def crawl(joints, fps: float = sk.FPS) -> Check:
    """Crawling: on all fours and travelling; True/False; value: the seconds on all fours."""
    j = _as_joints(joints)
    floor = _floor(j)
    wrists = j[:, [L_WRIST, R_WRIST], 1].min(axis=1) - floor
    fours = (j[:, HEAD, 1] - floor <= CRAWL_HEAD_M) & (j[:, PELVIS, 1] - floor <= CRAWL_PELVIS_M) & \
        (wrists <= CRAWL_WRIST_M)  # (T,)
    step = np.linalg.norm(np.diff(j[:, PELVIS, ::2], axis=0), axis=1)  # (T-1,)
    travel = float(step[fours[:-1] & fours[1:]].sum())
    seconds = float(fours.sum()) / fps
    return Check(bool(seconds >= CRAWL_MIN_S and travel >= CRAWL_TRAVEL_M), seconds, {"travel_m": travel})


def reach_floor(joints, fps: float = sk.FPS) -> Check:
    """A hand reaches down to the floor (picks something up): True/False; value: the lowest held wrist height
    (m) while the pelvis is up."""
    j = _as_joints(joints)
    floor = _floor(j)
    wrist = j[:, [L_WRIST, R_WRIST], 1].min(axis=1) - floor
    up = j[:, PELVIS, 1] - floor >= REACH_PELVIS_M
    low = -_held_max(np.where(up, -wrist, -10.0), _frames(REACH_HOLD_S, fps))
    return Check(bool(low <= REACH_WRIST_M), low)


def inverted(joints, fps: float = sk.FPS) -> Check:
    """Upside down (handstand, cartwheel, flip): both ankles above the head; True/False; value: how far the lower
    ankle is held above the head (m)."""
    j = _as_joints(joints)
    above = j[:, [L_ANKLE, R_ANKLE], 1].min(axis=1) - j[:, HEAD, 1]
    held = _held_max(above, _frames(INVERTED_HOLD_S, fps))
    return Check(bool(held > 0.0), held)


def stand_up(joints, fps: float = sk.FPS) -> Check:
    """Stands up: the pelvis low first, standing height later; True/False; value: the held standing pelvis height
    after the low part (m)."""
    j = _as_joints(joints)
    pelvis = j[:, PELVIS, 1] - _floor(j)
    n_low, n_high = _frames(STAND_LOW_S, fps), _frames(STAND_HIGH_S, fps)
    if len(pelvis) <= n_low:
        return Check(False, 0.0)
    lows = np.lib.stride_tricks.sliding_window_view(pelvis, n_low).max(axis=1) <= STAND_LOW_M  # (W,)
    if not lows.any():
        return Check(False, 0.0)
    after = pelvis[int(np.argmax(lows)) + n_low:]
    high = _held_max(after, n_high) if len(after) else 0.0
    return Check(bool(high >= STAND_HIGH_M), high)


def climb(joints, fps: float = sk.FPS) -> Check:
    """Climbing: both feet held above the floor on something higher; True/False; value: the held height of the
    lower foot (m)."""
    j = _as_joints(joints)
    feet = j[:, [L_ANKLE, R_ANKLE, L_FOOT, R_FOOT], 1].min(axis=1) - _floor(j)
    held = _held_max(feet, _frames(CLIMB_HOLD_S, fps))
    return Check(bool(held >= CLIMB_FEET_M), held)


def throw(joints, fps: float = sk.FPS) -> Check:
    """A throw: a hand flung forward fast; True/False; value: the fastest such wrist speed relative to the pelvis
    (m/s)."""
    j = _as_joints(joints)
    _, forward = body_frame(j)
    best = 0.0
    for wrist, shoulder in ((L_WRIST, L_SHOULDER), (R_WRIST, R_SHOULDER)):
        rel = j[:, wrist] - j[:, PELVIS]  # (T, 3)
        v = np.diff(rel, axis=0) * fps  # (T-1, 3)
        speed = np.linalg.norm(v, axis=1)
        ahead = np.einsum("tc,tc->t", v, forward[:-1]) >= THROW_FORWARD * speed
        high = (j[1:, wrist, 1] - j[1:, shoulder, 1]) >= THROW_WRIST_M
        best = max(best, float(np.where(ahead & high, speed, 0.0).max()))
    return Check(bool(best >= THROW_MPS), best)


CHECKS = {
    "raised": raised_hand,
    "waving": waving,
    "turn": turn,
    "locomotion": locomotion,
    "drift": drift,
    "bow": bow,
    "kick": kick,
    "jump": jump,
    "get_low": get_low,
    "on_ground": on_ground,
    "crawl": crawl,
    "reach_floor": reach_floor,
    "inverted": inverted,
    "stand_up": stand_up,
    "climb": climb,
    "throw": throw,
}
# What each verb of mld_core.data.verbs must show (the check of the same name; kick: either foot), and the plain
# locomotion words a window of a long trial can be found by.
_VERB_SHOWS = {"jump": ("jump", {True}), "get_low": ("get_low", {True}), "on_ground": ("on_ground", {True}),
               "crawl": ("crawl", {True}), "reach_floor": ("reach_floor", {True}), "inverted": ("inverted", {True}),
               "stand_up": ("stand_up", {True}), "climb": ("climb", {True}), "kick": ("kick", {"left", "right", "both"}),
               "throw": ("throw", {True}), "walk": ("locomotion", {"walk"}), "run": ("locomotion", {"run"})}
SHOWN_VERBS = tuple(_VERB_SHOWS)


def shows(joints, verb: str, fps: float = sk.FPS, result: dict | None = None) -> bool:
    """True when the motion shows ``verb`` (a verb of mld_core.data.verbs, or "walk" / "run")."""
    if result is None:
        return verb_result(joints, verb, fps)[0]
    name, ok = _verb_check(verb)
    return result[name].verdict in ok


def verb_result(joints, verb: str, fps: float = sk.FPS) -> tuple[bool, float]:
    """Whether the motion shows ``verb``, and the value of the check that decides it, in that check's unit (a throw's
    wrist speed in m/s, a kick's held ankle height in m, ...)."""
    name, ok = _verb_check(verb)
    check = CHECKS[name](joints, fps)
    return check.verdict in ok, float(check.value)


def _verb_check(verb: str) -> tuple[str, set]:
    if verb not in _VERB_SHOWS:
        raise ValueError(f"no physical check for the verb {verb!r}; checked: {', '.join(SHOWN_VERBS)}")
    return _VERB_SHOWS[verb]


def classify(joints, fps: float = sk.FPS) -> dict[str, Check]:
    """Run every check (the names of ``CHECKS``) -> Check."""
    j = _as_joints(joints)
    return {name: fn(j, fps) for name, fn in CHECKS.items()}


def verdicts(joints, fps: float = sk.FPS) -> dict:
    """{check name: verdict} for every check."""
    return {name: c.verdict for name, c in classify(joints, fps).items()}


# ---- what each Bandai Namco content should show -----------------------------------------------------------

_EXPECTED = {
    "raise-up-left-hand": {"raised": {"left"}},
    "raise-up-right-hand": {"raised": {"right"}},
    "raise-up-both-hands": {"raised": {"both"}},
    "wave-left-hand": {"waving": {"left"}},
    "wave-right-hand": {"waving": {"right"}},
    "wave-both-hands": {"waving": {"both"}},
    # "bye" is waving one hand; actions.json keeps the label "bye" for the mirrored copies (left hand).
    "bye": {"waving": {"left", "right"}},
    "byebye": {"waving": {"both"}},
    "respond": {"raised": {"left", "right"}},
    "slash": {"raised": {"both"}},
    "walk": {"locomotion": {"walk"}, "turn": {"none"}},
    "run": {"locomotion": {"run"}},
    "dash": {"locomotion": {"run"}},
    "walk-back": {"locomotion": {"backward"}},
    "walk-left": {"locomotion": {"walk"}, "drift": {"left"}},
    "walk-right": {"locomotion": {"walk"}, "drift": {"right"}},
    "walk-turn-left": {"locomotion": {"walk"}, "turn": {"left"}},
    "walk-turn-right": {"locomotion": {"walk"}, "turn": {"right"}},
    "bow": {"bow": {True}},
    "kick": {"kick": {"left", "right", "both"}},
    "jump": {"jump": {True}},  # not a Bandai content: CMU's jumps (docs/library.md)
}
CHECKED_LABELS = tuple(sorted(_EXPECTED))

# The check whose verdict names the side of a sided content.
_SIDE_CHECK = {"raise-up": "raised", "wave": "raised", "walk-turn": "turn", "walk": "drift"}


def expected_for(label: str) -> dict | None:
    """{check name: set of acceptable verdicts} for a Bandai Namco content label; None when no check
    describes it (call, punch, guide, dance-short)."""
    exp = _EXPECTED.get(str(label).strip().lower())
    return None if exp is None else {k: set(v) for k, v in exp.items()}


def failed_checks(joints, label: str, result: dict | None = None, fps: float = sk.FPS) -> list[str]:
    """Names of the expected checks that ``joints`` fail for ``label`` (empty = passes)."""
    exp = expected_for(label)
    if exp is None:
        raise ValueError(f"no physical check describes the content {label!r}; checked: {', '.join(CHECKED_LABELS)}")
    result = classify(joints, fps) if result is None else result
    return [name for name, ok in exp.items() if result[name].verdict not in ok]


def passes(joints, label: str, result: dict | None = None, fps: float = sk.FPS) -> bool:
    """True when the motion shows what the content ``label`` should (every check of expected_for(label)).
    ``result`` may be a classify() output already computed for these joints."""
    return not failed_checks(joints, label, result, fps)


def side_of(label: str) -> str | None:
    """"left" / "right" for a content that names a side (raise-up-left-hand, walk-turn-right, walk-left, ...)."""
    words = str(label).lower().split("-")
    return "left" if "left" in words else "right" if "right" in words else None


def side_check_for(label: str) -> str | None:
    """The check whose verdict tells which side a sided content used ("raised", "turn", "drift")."""
    if side_of(label) is None:
        return None
    for prefix, check in _SIDE_CHECK.items():
        if str(label).lower().startswith(prefix):
            return check
    return None


def detected_side(result: dict, label: str) -> str | None:
    """The side the motion used, read from the check that matters for ``label`` (None for unsided labels).

    Hands: "left", "right", "both" or "none": for wave-* the hand(s) that wave, or when none waves the
    hand(s) raised; for raise-up-* the hand(s) raised. Turns and drifts: "left", "right" or "none"."""
    check = side_check_for(label)
    if check is None:
        return None
    if str(label).lower().startswith("wave") and result["waving"].verdict != "none":
        return result["waving"].verdict
    return result[check].verdict


def mirror_label(label: str) -> str:
    """The content label of the mirror image (left <-> right)."""
    words = str(label).split("-")
    swap = {"left": "right", "right": "left"}
    return "-".join(swap.get(w, w) for w in words)
