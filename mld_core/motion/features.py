"""HumanML3D's 263-dim motion features on the 22-joint skeleton, both ways.

Layout of one frame (T frames of joints give T-1 feature rows):

====================  =======  ===============================================================
ROOT_ROT_VEL          0        per-frame root yaw change, as a HALF angle (radians)
ROOT_LIN_VEL          1:3      root xz velocity (m/frame) in the root's own facing frame
ROOT_Y                3        root height (m)
RIC                   4:67     joints 1..21 relative to the root, in the root's facing frame
ROT6D                 67:193   HumanML3D IK rotations of joints 1..21 as 6D (two matrix columns)
LOCAL_VEL             193:259  velocity of all 22 joints (m/frame) in the root's facing frame
FOOT_CONTACT          259:263  left ankle, left foot, right ankle, right foot contact (0/1)
====================  =======  ===============================================================

`joints_to_features` follows HumanML3D's motion_representation processing (uniform skeleton, floor,
origin, face +Z, foot contacts, IK, root velocities) including the quirk of its facing smoothing, but
fixes its +-180 degree root-velocity sign bug (see `_root_velocity_half_angle`).
"""

from __future__ import annotations

import re

import numpy as np
import torch

from . import skeleton as sk
from .quaternion import (cross, normalize, qbetween, qinv, qmul, qpositive, qrot, quat_to_cont6d, resampled_frames,
                         turn_about_y)

ROOT_ROT_VEL = slice(0, 1)
ROOT_LIN_VEL = slice(1, 3)
ROOT_Y = slice(3, 4)
RIC = slice(4, 4 + 21 * 3)
ROT6D = slice(RIC.stop, RIC.stop + 21 * 6)
LOCAL_VEL = slice(ROT6D.stop, ROT6D.stop + 22 * 3)
FOOT_CONTACT = slice(LOCAL_VEL.stop, LOCAL_VEL.stop + 4)
FEATURE_GROUPS = {
    "root_rot_vel": ROOT_ROT_VEL,
    "root_lin_vel": ROOT_LIN_VEL,
    "root_y": ROOT_Y,
    "ric": RIC,
    "rot6d": ROT6D,
    "local_vel": LOCAL_VEL,
    "foot_contact": FOOT_CONTACT,
}
assert FOOT_CONTACT.stop == sk.FEATURE_DIM

FOOT_CONTACT_THRESHOLD = 0.002  # squared displacement per frame (m^2) at 20 fps
FACING_SMOOTH_SIGMA = 20.0  # frames, Gaussian smoothing of the facing used by the IK
_UP = np.array([0.0, 1.0, 0.0])
_FORWARD = np.array([0.0, 0.0, 1.0])


# ----------------------------------------------------------------------------------------------------
# joints -> features
# ----------------------------------------------------------------------------------------------------


def joints_to_features(joints, fps: float = sk.FPS) -> np.ndarray:
    """Joint positions (T, 22, 3) in metres, Y up -> features (T'-1, 263) float32 at 20 fps.

    Clips at another frame rate are resampled to 20 fps first (T' frames after resampling).
    """
    pos = canonical_joints(joints, fps)  # (T, 22, 3)
    if len(pos) < 2:
        raise ValueError(f"need at least 2 frames at {sk.FPS} fps to compute velocities, got {len(pos)}")
    return features_of(pos, _smoothed_root_quat(pos))  # root: world -> facing frame, (T, 4)


def features_of(pos: np.ndarray, root_quat: np.ndarray) -> np.ndarray:
    """Features (T-1, 263) of canonical joints (T, 22, 3) under per-frame root rotations (T, 4)."""
    root_rot_vel = _root_velocity_half_angle(root_quat)  # (T-1, 1)
    root_lin_vel = qrot(root_quat[1:], pos[1:, 0] - pos[:-1, 0])[:, [0, 2]]  # (T-1, 2)
    root_y = pos[:-1, 0, 1:2]  # (T-1, 1)
    ric = _root_relative(pos, root_quat)[:-1, 1:].reshape(len(pos) - 1, -1)  # (T-1, 63)
    rot6d = _ik_cont6d(pos, root_quat)[:-1].reshape(len(pos) - 1, -1)  # (T-1, 126)
    local_vel = qrot(root_quat[:-1, None], pos[1:] - pos[:-1]).reshape(len(pos) - 1, -1)  # (T-1, 66)
    contacts = _foot_contacts(pos)  # (T-1, 4)

    feats = np.concatenate([root_rot_vel, root_lin_vel, root_y, ric, rot6d, local_vel, contacts], axis=-1)
    return feats.astype(np.float32)


def _check_joints(joints) -> np.ndarray:
    if isinstance(joints, torch.Tensor):
        joints = joints.detach().cpu().numpy()
    pos = np.asarray(joints, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"joints must have shape (T, {sk.NUM_JOINTS}, 3), got {pos.shape}")
    if not np.isfinite(pos).all():
        raise ValueError("joints contain NaN or infinite values")
    return pos


def resample(joints: np.ndarray, fps_in: float, fps_out: float) -> np.ndarray:
    """Linear resampling along axis 0 from fps_in to fps_out, keeping the first frame and the duration."""
    lo, hi, w = resampled_frames(len(joints), fps_in, fps_out)
    w = w.reshape(-1, *([1] * (joints.ndim - 1)))
    return joints[lo] * (1 - w) + joints[hi] * w


def uniform_skeleton(pos: np.ndarray) -> np.ndarray:
    """Rebuild every bone with the reference length, keeping its direction; scale the root by leg length.

    This is what HumanML3D's IK -> FK with the target offsets amounts to (its IK rotations take each rest
    direction exactly onto the bone direction).
    """
    parents = list(sk.PARENTS[1:])
    bones = pos[:, 1:] - pos[:, parents]  # (T, 21, 3)
    lengths = np.linalg.norm(bones, axis=-1, keepdims=True)  # (T, 21, 1)
    legs = [j - 1 for j in sk.LEG_JOINTS]
    src_leg = lengths[0, legs, 0].sum()
    if src_leg <= 1e-6:
        raise ValueError("the first frame has zero-length legs; cannot scale the skeleton")
    scale = sk.REFERENCE_BONE_LENGTHS[list(sk.LEG_JOINTS)].sum() / src_leg
    safe = lengths > 1e-9
    dirs = np.where(safe, bones / np.where(safe, lengths, 1.0), sk.RAW_OFFSETS[1:])  # (T, 21, 3)

    out = np.empty_like(pos)
    out[:, 0] = pos[:, 0] * scale
    for j in range(1, sk.NUM_JOINTS):  # parents come before children in SMPL order
        out[:, j] = out[:, sk.PARENTS[j]] + dirs[:, j - 1] * sk.REFERENCE_BONE_LENGTHS[j]
    return out


def canonical_joints(joints, fps: float = sk.FPS) -> np.ndarray:
    """The joints that `joints_to_features` describes (T, 22, 3) float64: resampled to 20 fps, rebuilt on
    the reference skeleton, floor at y = 0, frame-0 root at the xz origin and facing +Z.

    features_to_joints(joints_to_features(j)) equals canonical_joints(j)[:-1].
    """
    pos = _check_joints(joints)
    if fps != sk.FPS:
        pos = resample(pos, fps, sk.FPS)
    return _canonicalise(uniform_skeleton(pos))


def _canonicalise(pos: np.ndarray) -> np.ndarray:
    """Floor at y = 0, frame-0 root over the xz origin, frame-0 facing along +Z."""
    pos = pos.copy()
    pos[..., 1] -= pos[..., 1].min()
    pos = pos - pos[0, 0] * np.array([1.0, 0.0, 1.0])
    forward = normalize(_forward(pos[:1], hip_sign=1.0))  # (1, 3)
    turn = qbetween(forward, _FORWARD[None])  # (1, 4)
    return qrot(turn[:, None], pos)


def _forward(pos: np.ndarray, hip_sign: float) -> np.ndarray:
    """Horizontal facing (T, 3) from hips and shoulders: up x (across hips + across shoulders).

    hip_sign=-1 reproduces HumanML3D's IK, which unpacks the face joints as (l_hip, r_hip, ...) although
    they are given as (r_hip, l_hip, ...): its smoothed facing flips the hip term.
    """
    r_hip, l_hip, r_sdr, l_sdr = sk.FACE_JOINTS
    across = hip_sign * (pos[:, r_hip] - pos[:, l_hip]) + (pos[:, r_sdr] - pos[:, l_sdr])
    across = normalize(across)
    return cross(np.broadcast_to(_UP, across.shape), across)


def _smoothed_root_quat(pos: np.ndarray) -> np.ndarray:
    """Per-frame root rotation (T, 4) taking the smoothed facing onto +Z (HumanML3D's IK root).

    Frame 0 keeps the identity: the clip was already turned to face +Z by its (unsmoothed) frame-0
    facing, and HumanML3D's IK pins the first root rotation (the golden sample needs it).
    """
    forward = gaussian_filter1d(_forward(pos, hip_sign=-1.0), FACING_SMOOTH_SIGMA)
    forward = normalize(forward)
    root_quat = qbetween(forward, np.broadcast_to(_FORWARD, forward.shape))
    root_quat[0] = (1.0, 0.0, 0.0, 0.0)
    return root_quat


def gaussian_filter1d(x: np.ndarray, sigma: float, truncate: float = 4.0) -> np.ndarray:
    """Gaussian smoothing along axis 0 with edge replication (scipy's mode='nearest')."""
    radius = int(truncate * sigma + 0.5)
    taps = np.arange(-radius, radius + 1, dtype=np.float64)
    kernel = np.exp(-0.5 * (taps / sigma) ** 2)
    kernel /= kernel.sum()
    padded = np.concatenate([np.repeat(x[:1], radius, 0), x, np.repeat(x[-1:], radius, 0)], axis=0)
    out = np.zeros_like(x, dtype=np.float64)
    for k, weight in enumerate(kernel):
        out += weight * padded[k : k + len(x)]
    return out


def _root_velocity_half_angle(root_quat: np.ndarray) -> np.ndarray:
    """Feature 0: arcsin of the y component of q[t+1] * q[t]^-1, i.e. half the yaw change.

    HumanML3D takes the arcsin as is; when the facing crosses +-180 degrees the product lands on the
    w < 0 hemisphere and the sign of the turn flips. We take the w >= 0 representative (a fix).
    """
    step = qpositive(qmul(root_quat[1:], qinv(root_quat[:-1])))  # (T-1, 4)
    return np.arcsin(np.clip(step[:, 2:3], -1.0, 1.0))


def _root_relative(pos: np.ndarray, root_quat: np.ndarray) -> np.ndarray:
    """Joints minus the root's xz, turned into the root's facing frame: (T, 22, 3)."""
    local = pos - pos[:, :1] * np.array([1.0, 0.0, 1.0])
    return qrot(root_quat[:, None], local)


def _ik_cont6d(pos: np.ndarray, root_quat: np.ndarray) -> np.ndarray:
    """HumanML3D's IK rotations of joints 1..21 as 6D: (T, 21, 6).

    The rotation stored at joint k turns the rest direction RAW_OFFSETS[k] onto the bone parent(k)->k,
    relative to the bone before it in its chain (the root rotation starts every chain, the arm chains too).
    """
    local = np.zeros(pos.shape[:2] + (4,))  # (T, 22, 4)
    for chain in sk.KINEMATIC_CHAINS:
        parent_rot = root_quat
        for a, b in zip(chain[:-1], chain[1:]):
            bone_rot = qbetween(np.broadcast_to(sk.RAW_OFFSETS[b], pos[:, b].shape), pos[:, b] - pos[:, a])
            local[:, b] = qmul(qinv(parent_rot), bone_rot)
            parent_rot = bone_rot
    return quat_to_cont6d(local[:, 1:])


def _foot_contacts(pos: np.ndarray) -> np.ndarray:
    """1 where a foot joint moved less than the threshold between frames: (T-1, 4) left ankle/foot, right."""
    feet = list(sk.FOOT_LEFT) + list(sk.FOOT_RIGHT)
    moved = ((pos[1:, feet] - pos[:-1, feet]) ** 2).sum(-1)  # (T-1, 4)
    return (moved < FOOT_CONTACT_THRESHOLD).astype(np.float64)


# ----------------------------------------------------------------------------------------------------
# features -> joints
# ----------------------------------------------------------------------------------------------------


def features_to_joints(features):
    """Features (..., T, 263) -> joints (..., T, 22, 3), from the root channels and RIC.

    numpy in -> numpy out (same dtype, computed in float64); torch in -> torch out (same dtype and
    device, differentiable).
    """
    if isinstance(features, torch.Tensor):
        _check_features(features.shape)
        return _recover_joints(features)
    arr = np.asarray(features)
    _check_features(arr.shape)
    out = _recover_joints_numpy(arr.astype(np.float64))
    return out.astype(arr.dtype if arr.dtype.kind == "f" else np.float32)


def _check_features(shape) -> None:
    if len(shape) < 2 or shape[-1] != sk.FEATURE_DIM:
        raise ValueError(f"features must have shape (..., T, {sk.FEATURE_DIM}), got {tuple(shape)}")


def recover_root(features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Root rotation (..., T, 4) (world -> facing frame, identity at frame 0) and position (..., T, 3)."""
    half = features[..., 0]  # (..., T)
    angle = torch.cumsum(torch.cat([torch.zeros_like(half[..., :1]), half[..., :-1]], dim=-1), dim=-1)
    zero = torch.zeros_like(angle)
    root_quat = torch.stack([torch.cos(angle), zero, torch.sin(angle), zero], dim=-1)  # (..., T, 4)

    vel = features[..., :-1, 1:3]  # (..., T-1, 2) in the facing frame of the next frame
    step = torch.stack([vel[..., 0], torch.zeros_like(vel[..., 0]), vel[..., 1]], dim=-1)
    step = torch.cat([torch.zeros_like(step[..., :1, :]), step], dim=-2)  # (..., T, 3)
    xz = torch.cumsum(qrot(qinv(root_quat), step), dim=-2)
    root_pos = torch.stack([xz[..., 0], features[..., 3], xz[..., 2]], dim=-1)  # (..., T, 3)
    return root_quat, root_pos


def _recover_joints(features: torch.Tensor) -> torch.Tensor:
    root_quat, root_pos = recover_root(features)
    ric = features[..., RIC].reshape(features.shape[:-1] + (21, 3))  # (..., T, 21, 3)
    world = qrot(qinv(root_quat)[..., None, :], ric)
    root_xz = root_pos * root_pos.new_tensor([1.0, 0.0, 1.0])
    world = world + root_xz[..., None, :]
    return torch.cat([root_pos[..., None, :], world], dim=-2)  # (..., T, 22, 3)


def _recover_joints_numpy(f: np.ndarray) -> np.ndarray:
    """_recover_joints in numpy, float64 (a take is many small operations: numpy keeps each one cheap)."""
    half = f[..., 0]  # (..., T)
    angle = np.cumsum(np.concatenate([np.zeros_like(half[..., :1]), half[..., :-1]], axis=-1), axis=-1)
    step = np.zeros(f.shape[:-1] + (3,))  # (..., T, 3): frame t-1 -> t in the facing frame of frame t
    step[..., 1:, 0], step[..., 1:, 2] = f[..., :-1, 1], f[..., :-1, 2]
    xz = np.cumsum(turn_about_y(-angle, step), axis=-2)  # the inverse of the root rotation: facing -> world
    root_pos = np.stack([xz[..., 0], f[..., 3], xz[..., 2]], axis=-1)  # (..., T, 3)
    ric = f[..., RIC].reshape(f.shape[:-1] + (21, 3))  # (..., T, 21, 3)
    world = turn_about_y(-angle[..., None], ric)
    world[..., 0] += root_pos[..., None, 0]
    world[..., 2] += root_pos[..., None, 2]
    return np.concatenate([root_pos[..., None, :], world], axis=-2)  # (..., T, 22, 3)


# ----------------------------------------------------------------------------------------------------
# mirroring and normalisation statistics
# ----------------------------------------------------------------------------------------------------

_MIRROR_X = (-1.0, 1.0, 1.0)


def mirror_joints(joints):
    """Swap left and right: (..., 22, 3) numpy or torch -> the mirror image across the YZ plane."""
    out = joints[..., list(sk.MIRROR_INDEX), :]
    if isinstance(joints, torch.Tensor):
        return out * out.new_tensor(_MIRROR_X)
    return out * np.asarray(_MIRROR_X, dtype=out.dtype)


def _mirror_feature_map() -> tuple[np.ndarray, np.ndarray]:
    """For each output channel: the input channel it comes from and the sign to apply."""
    index = np.arange(sk.FEATURE_DIM)
    sign = np.ones(sk.FEATURE_DIM)
    sign[ROOT_ROT_VEL] = -1.0  # yaw turns the other way
    sign[ROOT_LIN_VEL.start] = -1.0  # x velocity
    mirror = np.asarray(sk.MIRROR_INDEX)
    for j in range(1, sk.NUM_JOINTS):  # RIC: per joint (x, y, z)
        base, src = RIC.start + 3 * (j - 1), RIC.start + 3 * (mirror[j] - 1)
        index[base : base + 3] = np.arange(src, src + 3)
        sign[base] = -1.0
    # ROT6D: M R M with M = diag(-1, 1, 1): first column (R00, -R10, -R20), second (-R01, R11, R21).
    for j in range(1, sk.NUM_JOINTS):
        base, src = ROT6D.start + 6 * (j - 1), ROT6D.start + 6 * (mirror[j] - 1)
        index[base : base + 6] = np.arange(src, src + 6)
        sign[base : base + 6] = (1.0, -1.0, -1.0, -1.0, 1.0, 1.0)
    for j in range(sk.NUM_JOINTS):  # LOCAL_VEL
        base, src = LOCAL_VEL.start + 3 * j, LOCAL_VEL.start + 3 * mirror[j]
        index[base : base + 3] = np.arange(src, src + 3)
        sign[base] = -1.0
    index[FOOT_CONTACT] = np.r_[FOOT_CONTACT.start + 2 : FOOT_CONTACT.stop, FOOT_CONTACT.start : FOOT_CONTACT.start + 2]
    return index, sign


_MIRROR_INDEX_263, _MIRROR_SIGN_263 = _mirror_feature_map()


def mirror_features(features):
    """Mirror features (..., 263) directly (numpy or torch): features_to_joints of the result is
    mirror_joints of features_to_joints. (Re-extracting mirrored joints differs slightly, because
    HumanML3D's reference skeleton is not left/right symmetric.)"""
    out = features[..., _MIRROR_INDEX_263]
    if isinstance(features, torch.Tensor):
        return out * out.new_tensor(_MIRROR_SIGN_263)
    return out * _MIRROR_SIGN_263.astype(out.dtype)


_TEXT_SWAPS = {
    "left": "right",
    "right": "left",
    "lefts": "rights",
    "rights": "lefts",
    "leftward": "rightward",
    "rightward": "leftward",
    "leftwards": "rightwards",
    "rightwards": "leftwards",
    "leftmost": "rightmost",
    "rightmost": "leftmost",
    "clockwise": "counterclockwise",
    "counterclockwise": "clockwise",
    "counter-clockwise": "clockwise",
    "anticlockwise": "clockwise",
    "anti-clockwise": "clockwise",
}
# Longest first so that "counter-clockwise" wins over "clockwise".
_TEXT_PATTERN = re.compile(
    r"\b(" + "|".join(re.escape(w) for w in sorted(_TEXT_SWAPS, key=len, reverse=True)) + r")\b",
    re.IGNORECASE,
)


def _match_case(word: str, like: str) -> str:
    if like.isupper() and len(like) > 1:
        return word.upper()
    if like[0].isupper():
        return word[0].upper() + word[1:]
    return word


# "left" is also the past of "leave" ("he left the room", "she has left"): after a subject or an auxiliary and
# not before a body part or side word, it is the verb and stays.
_LEAVERS = {"he", "she", "they", "i", "we", "you", "it", "who", "that", "person", "man", "woman", "someone",
            "somebody", "one", "has", "have", "had", "just", "already", "never"}
_SIDE_NOUNS = {"hand", "hands", "arm", "arms", "leg", "legs", "foot", "feet", "side", "shoulder", "knee", "elbow",
               "wrist", "hip", "ankle", "toe", "heel", "fist", "palm", "turn", "and", "or"}
_WORD = re.compile(r"[A-Za-z']+")


def _verb_left(text: str, start: int, end: int) -> bool:
    """Whether the "left" at text[start:end] follows a subject or an auxiliary and no body part or side word
    follows it ("and" counts only after "came": "came and left")."""
    before, after = _WORD.findall(text[:start]), _WORD.findall(text[end:])
    previous = before[-1].lower() if before else ""
    following = after[0].lower() if after else ""
    if previous == "and":
        return len(before) >= 2 and before[-2].lower() == "came" and following not in _SIDE_NOUNS
    return previous in _LEAVERS and following not in _SIDE_NOUNS


def mirror_text(text: str) -> str:
    """Swap left/right and clockwise/counterclockwise words (whole words, keeping their case); "left" as the past of
    "leave" ("he left the room") is not a side and stays."""

    def swap(m: re.Match) -> str:
        word = m.group(0)
        if word.lower() == "left" and _verb_left(text, m.start(), m.end()):
            return word
        return _match_case(_TEXT_SWAPS[word.lower()], word)

    return _TEXT_PATTERN.sub(swap, text)


MIN_STD = 1e-8


def mean_std(feature_arrays) -> tuple[np.ndarray, np.ndarray]:
    """HumanML3D's normalisation statistics over all frames of all clips: (mean (263,), std (263,)).

    The mean is per dimension; the std is the per-dimension (population) std averaged within each of the
    7 groups of FEATURE_GROUPS (HumanML3D divides those group means by 1.0, i.e. by nothing). A group
    with no variation gets MIN_STD so that normalising never divides by zero.
    """
    arrays = [np.asarray(a).reshape(-1, sk.FEATURE_DIM) for a in feature_arrays]  # (T_i, 263) each, as given
    frames = sum(len(a) for a in arrays)
    if frames == 0:
        raise ValueError("mean_std needs at least one frame of features")
    if not all(np.isfinite(a).all() for a in arrays):
        raise ValueError("features contain NaN or infinite values")
    # Two passes in float64, one clip at a time: a library of hours is never copied whole (numpy's mean and std
    # over the concatenation, to float rounding).
    mean = sum(a.sum(axis=0, dtype=np.float64) for a in arrays) / frames
    std = np.sqrt(sum(((a - mean) ** 2).sum(axis=0) for a in arrays) / frames)
    for s in FEATURE_GROUPS.values():
        std[s] = max(std[s].mean(), MIN_STD)
    return mean.astype(np.float32), std.astype(np.float32)
