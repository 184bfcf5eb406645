"""How well a retargeted rig follows its source, measured by forward kinematics on the rig (numpy only): effector
errors relative to limb length, feet below the source and below their rest height, heading and travel direction."""

from __future__ import annotations

from typing import Mapping

import numpy as np

from mld_core.rig.retarget import _EPS, JOINT_INDEX, RetargetResult, _to_world, standing_heights, wrap_angle


EFFECTOR_CHAINS = {
    "left_wrist": ("left_shoulder", "left_elbow", "left_wrist"),
    "right_wrist": ("right_shoulder", "right_elbow", "right_wrist"),
    "left_ankle": ("left_hip", "left_knee", "left_ankle"),
    "right_ankle": ("right_hip", "right_knee", "right_ankle"),
    "head": ("pelvis", "spine1", "spine2", "spine3", "neck", "head"),
}
FOOT_JOINTS = ("left_ankle", "right_ankle", "left_foot", "right_foot")


def facing_yaw(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Heading (radians, about world Z, 0 = facing -Y) from a left and a right joint (T, 3), unwrapped over time."""
    lat = left - right
    fwd = np.stack([lat[..., 1], -lat[..., 0]], -1)  # cross(lat, z) in the ground plane
    yaw = np.arctan2(fwd[..., 0], -fwd[..., 1])
    return np.unwrap(yaw)


LIMB_BONES = tuple((child, parent) for side in ("left", "right") for parent, child in (
    (f"{side}_shoulder", f"{side}_elbow"), (f"{side}_elbow", f"{side}_wrist"),
    (f"{side}_hip", f"{side}_knee"), (f"{side}_knee", f"{side}_ankle")))


def _direction_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (T,) in degrees between two (T, 3) direction series."""
    cos = (a * b).sum(-1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), _EPS)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def fidelity(result: RetargetResult, target_joints: Mapping[str, np.ndarray] | None = None) -> dict:
    """Compare the rig's FK with the placed source (both world space, source scaled by ``result.scale``).

    Effector error: for each wrist, ankle and the head, its position relative to the limb's root (shoulder, hip,
    pelvis) on the rig vs the source's, the source limb scaled to the rig's limb length; divided by that length
    (a fraction: 0.05 = 5% of limb length), averaged over frames; ``*_global`` the same for world positions
    against the placed source. Feet: ``sink_cm`` is the most any foot joint (ankles, toes) of the rig goes below
    the same joint of the placed source while that joint is down at the floor; ``below_rest_height_cm`` (rigs
    whose rest stands) the most a foot joint goes below its rest height above the floor. Direction: heading error
    from the hips' lateral axis (mean, degrees), total turn of source and rig, and the angle between their net
    travel directions. Limbs: ``limb_dir_deg``, the mean angle between the rig's upper arm, forearm, thigh and shin
    and the source's (the worst bone's mean in ``limb_dir_deg_max_bone``).
    ``target_joints`` (joint -> (T, 3) world positions) replaces the rig's FK, e.g. with Blender's own evaluation.
    """
    wj = result.world_joints() if target_joints is None else target_joints
    src = result.source_world
    J = JOINT_INDEX
    out: dict[str, float] = {}
    rest_world = _to_world(result.rig, result.rig.heads)
    rest = {j: rest_world[result.rig.index(b)] for j, b in zip(result.joints, result.bones)}
    errors, errors_global = [], []
    for eff, chain in EFFECTOR_CHAINS.items():
        chain = [j for j in chain if j in wj]
        if len(chain) < 2 or chain[-1] != eff:
            continue
        l_tgt = sum(np.linalg.norm(rest[b] - rest[a]) for a, b in zip(chain[:-1], chain[1:]))
        l_src = sum(np.linalg.norm(src[:, J[b]] - src[:, J[a]], axis=-1) for a, b in zip(chain[:-1], chain[1:]))
        rel_t = wj[eff] - wj[chain[0]]
        rel_s = (src[:, J[eff]] - src[:, J[chain[0]]]) * (l_tgt / np.maximum(l_src, _EPS))[:, None]
        err = np.linalg.norm(rel_t - rel_s, axis=-1) / l_tgt
        out[f"{eff}_err"] = float(err.mean())
        out[f"{eff}_err_max"] = float(err.max())
        glob = np.linalg.norm(wj[eff] - src[:, J[eff]], axis=-1) / l_tgt
        out[f"{eff}_err_global"] = float(glob.mean())
        errors.append(err.mean())
        errors_global.append(glob.mean())
    out["effector_err_mean"] = float(np.mean(errors))
    out["effector_err_global_mean"] = float(np.mean(errors_global))
    angles = [_direction_error_deg(wj[a] - wj[b], src[:, J[a]] - src[:, J[b]])
              for a, b in LIMB_BONES if a in wj and b in wj]
    if angles:  # how far each limb bone points from the source's: the pose as an animator reads it
        out["limb_dir_deg"] = float(np.mean([a.mean() for a in angles]))
        out["limb_dir_deg_max_bone"] = float(max(a.mean() for a in angles))
    locked = [_locked_knee(wj, src, side) for side in ("left", "right")
              if all(f"{side}_{j}" in wj for j in ("hip", "knee", "ankle"))]
    if locked:  # a knee snapped straight where the source's bends: legs of uneven length, a foot out of reach
        out["locked_knee_frac"] = float(max(locked))
    feet = [j for j in FOOT_JOINTS if j in wj]
    standing = standing_heights(result.rig, dict(zip(result.joints, result.bones)))
    floor = result.rig.object_matrix[2, 3]
    # Sinking: while a foot joint is down at the floor in the placed source (within 3 cm of its lowest 5%; the
    # source's feet stand on the floor, lifted or lowered to the rig's standing ankle height when the rig's rest
    # stands), how far the rig's same joint goes below it. A foot up in the air is not sinking.
    sink = 0.0
    for j in feet:
        z_src = src[:, J[j], 2]
        down = z_src <= np.percentile(z_src, 5) + 0.03 * result.scale
        sink = max(sink, float(np.max(z_src[down] - wj[j][down, 2])))
    out["sink_cm"] = max(0.0, sink) * 100
    if standing is not None:
        # Also: how far a foot joint goes below its own rest height above the floor the take stands on (the rig's
        # origin; the sole going under, for rigs whose rest pose is a plausible standing pose).
        below = max(float(np.max(standing[j] - (wj[j][:, 2] - floor))) for j in standing)
        out["below_rest_height_cm"] = max(0.0, below) * 100
    out["lowest_foot_cm"] = (min(float(np.min(wj[j][:, 2])) for j in feet) - floor) * 100
    yaw_t = facing_yaw(wj["left_hip"], wj["right_hip"])
    yaw_s = facing_yaw(src[:, J["left_hip"]], src[:, J["right_hip"]])
    out["facing_err_deg"] = float(np.degrees(np.mean(np.abs(wrap_angle(yaw_t - yaw_s)))))
    out["turn_src_deg"] = float(np.degrees(yaw_s[-1] - yaw_s[0]))
    out["turn_rig_deg"] = float(np.degrees(yaw_t[-1] - yaw_t[0]))
    hips_t = (wj["left_hip"] + wj["right_hip"]) / 2
    hips_s = (src[:, J["left_hip"]] + src[:, J["right_hip"]]) / 2
    travel_t = hips_t[-1, :2] - hips_t[0, :2]
    travel_s = hips_s[-1, :2] - hips_s[0, :2]
    out["travel_src_m"] = float(np.linalg.norm(travel_s))
    out["travel_rig_m"] = float(np.linalg.norm(travel_t))
    if np.linalg.norm(travel_s) > 1e-3 and np.linalg.norm(travel_t) > 1e-3:
        cos = np.dot(travel_t, travel_s) / (np.linalg.norm(travel_t) * np.linalg.norm(travel_s))
        out["travel_angle_deg"] = float(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    else:
        out["travel_angle_deg"] = 0.0
    return out


LOCKED_DEG, BENT_DEG = 2.0, 5.0


def knee_bend_deg(hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray) -> np.ndarray:
    """(T,) degrees between thigh and shin: 0 = the leg straight."""
    return _direction_error_deg(knee - hip, ankle - knee)


def _locked_knee(wj: Mapping[str, np.ndarray], src: np.ndarray, side: str) -> float:
    """Share of frames in which the rig's knee on ``side`` is straight (< 2 deg) while the source's bends (> 5)."""
    J = JOINT_INDEX
    rig = knee_bend_deg(wj[f"{side}_hip"], wj[f"{side}_knee"], wj[f"{side}_ankle"])
    source = knee_bend_deg(*(src[:, J[f"{side}_{j}"]] for j in ("hip", "knee", "ankle")))
    return float(np.mean((rig < LOCKED_DEG) & (source > BENT_DEG)))
