"""Is a prepared take real human motion? Leading frames that cannot belong to the motion, and the plausibility of
what is left, for every library preparation (``data prepare bvh``, ``data prepare cmu-joints``).

A capture often starts with a frame or two that are not motion: the skeleton's rest pose, a calibration pose, a
frame before the markers were found. Such a frame is not always a T-pose; what gives it away is the jump into the
next frame, which no body can make at the clip's frame rate. After trimming, a take is written only when it looks
like a person: a body of human size, feet that reach the floor, no joint faster than a human can move one.

Everything here reads joints (T, 22, 3) in metres, Y up, SMPL-22 order (``mld_core.motion.skeleton``).
"""

from __future__ import annotations

import numpy as np

from mld_core.motion.skeleton import JOINT_NAMES

_J = {name: i for i, name in enumerate(JOINT_NAMES)}
_FEET = [_J[n] for n in ("left_ankle", "right_ankle", "left_foot", "right_foot")]

# No joint of a real take moves faster than this (a kicking foot or a throwing hand peaks at 10-14 m/s; the rest
# pose jumping into the first captured frame moves at 11-53 m/s in the CMU BVH re-exports).
MAX_JOINT_SPEED_MPS = 15.0
# Leading frames are searched for such a jump within this many seconds of the start.
LEAD_SEARCH_S = 1.0
# A human body: legs (hip -> knee -> ankle) plus pelvis -> head, in metres.
BODY_HEIGHT_M = (1.1, 2.3)
# The feet reach the floor: the lowest foot joint is within FLOOR_NEAR_M of the floor in at least FLOOR_FRACTION of
# the frames (a take floating above a floor taken from one stray frame never is).
FLOOR_NEAR_M = 0.10
FLOOR_FRACTION = 0.10
# The floor is the lowest joint over the take (HumanML3D's convention); it must agree with a robust estimate, the
# FLOOR_PERCENTILE of each frame's lowest joint, within FLOOR_AGREE_M (else one frame dips below the real floor).
FLOOR_PERCENTILE = 5.0
FLOOR_AGREE_M = 0.08


def joint_speeds(joints: np.ndarray, fps: float) -> np.ndarray:
    """The fastest joint's speed between consecutive frames (T-1,) in m/s."""
    step = np.linalg.norm(np.diff(joints, axis=0), axis=-1)  # (T-1, J)
    return step.max(axis=1) * fps


def leading_jump_frames(joints: np.ndarray, fps: float) -> int:
    """How many first frames to drop: everything up to the last impossible jump (a joint faster than
    MAX_JOINT_SPEED_MPS) within LEAD_SEARCH_S of the start; 0 when the take starts cleanly."""
    if len(joints) < 2:
        return 0
    speeds = joint_speeds(joints, fps)
    window = speeds[: max(1, int(round(LEAD_SEARCH_S * fps)))]
    jumps = np.flatnonzero(window > MAX_JOINT_SPEED_MPS)
    return int(jumps[-1] + 1) if len(jumps) else 0


def body_height(joints: np.ndarray) -> float:
    """Mean leg length (hip -> knee -> ankle) plus mean pelvis -> head distance, in metres."""
    def bone(a: str, b: str) -> float:
        return float(np.linalg.norm(joints[:, _J[a]] - joints[:, _J[b]], axis=-1).mean())

    legs = np.mean([bone(f"{s}_hip", f"{s}_knee") + bone(f"{s}_knee", f"{s}_ankle") for s in ("left", "right")])
    return float(legs + bone("pelvis", "head"))


def implausible(joints: np.ndarray, fps: float) -> str | None:
    """Why ``joints`` cannot be a person's motion, or None when they can: a body too small or too large, a joint
    faster than MAX_JOINT_SPEED_MPS, a floor that one frame pulls below the others, or feet that never reach it."""
    j = np.asarray(joints, dtype=np.float64)
    if j.ndim != 3 or j.shape[1:] != (len(JOINT_NAMES), 3) or len(j) < 2:
        return f"joints of shape {j.shape}, expected (T >= 2, 22, 3)"
    if not np.isfinite(j).all():
        return "NaN or infinite joint positions"
    height = body_height(j)
    if not BODY_HEIGHT_M[0] <= height <= BODY_HEIGHT_M[1]:
        return f"body height {height:.2f} m is outside {BODY_HEIGHT_M[0]}-{BODY_HEIGHT_M[1]} m"
    lowest = j[:, :, 1].min(axis=1)  # (T,)
    floor, robust = float(lowest.min()), float(np.percentile(lowest, FLOOR_PERCENTILE))
    if robust - floor > FLOOR_AGREE_M:
        return f"one part of the take dips {100 * (robust - floor):.0f} cm below the floor of the rest"
    feet = j[:, _FEET, 1].min(axis=1) - floor  # (T,)
    near = float((feet <= FLOOR_NEAR_M).mean())
    if near < FLOOR_FRACTION:
        return (f"the feet float: within {100 * FLOOR_NEAR_M:.0f} cm of the floor in {100 * near:.0f}% of the frames "
                f"(lowest {100 * feet.min():.0f} cm)")
    speeds = joint_speeds(j, fps)
    if speeds.max() > MAX_JOINT_SPEED_MPS:
        return (f"a joint moves at {speeds.max():.0f} m/s at {int(speeds.argmax()) / fps:.2f} s "
                f"(over {MAX_JOINT_SPEED_MPS:g} m/s)")
    return None
