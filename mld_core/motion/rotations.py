"""Joint rotations of the canonical skeleton from HumanML3D features, and forward kinematics.

Convention (the usual one, as BVH and Blender use it): ``local[j]`` rotates joint j's children;
``G[j] = G[parent] * local[j]`` is j's world rotation, ``G[root] = local[root]``, and
``pos[j] = pos[parent] + G[parent] * offsets[j]``. The rest pose (all rotations identity) is the skeleton
given by ``offsets`` (default ``skeleton.REST_OFFSETS``); everything is in the features' world frame
(metres, Y up, facing +Z at frame 0).

How the rotations are found (`features_to_rotations`):
- joints with one child: the SWING comes from the recovered positions (the child lands on its joint
  exactly), the TWIST about the bone from HumanML3D's 6D channels (the IK rotation of that bone);
- pelvis and spine3 (three children each): the rotation that best maps the rest directions of the three
  child bones onto the recovered ones (Wahba's problem). This is exact when the clip's pelvis and chest
  have the rest pose's shape; see `rest_offsets_from_joints`;
- leaves (feet, head, wrists): identity (the features say nothing about them).
"""

from __future__ import annotations

import numpy as np
import torch

from . import skeleton as sk
from .features import ROT6D, features_to_joints, recover_root
from .quaternion import (
    cont6d_to_matrix,
    matrix_to_quat,
    normalize,
    qbetween,
    qinv,
    qmul,
    qrot,
)

# Branching joints: (joint, main child (straight up in the rest pose), left child, right child).
BRANCHES = ((0, 3, 1, 2), (9, 12, 13, 14))


def _children() -> list[list[int]]:
    kids: list[list[int]] = [[] for _ in range(sk.NUM_JOINTS)]
    for j, p in enumerate(sk.PARENTS):
        if p >= 0:
            kids[p].append(j)
    return kids


CHILDREN = _children()


def features_to_rotations(features, offsets=None) -> tuple[np.ndarray, np.ndarray]:
    """Features (T, 263) -> (local quaternions (T, 22, 4) wxyz float32, root positions (T, 3) float32).

    ``fk(*features_to_rotations(f), offsets)`` reproduces ``features_to_joints(f)`` (up to the bone
    lengths and branch shapes the features imply differing from ``offsets``).
    """
    feats = features.detach().cpu().numpy() if isinstance(features, torch.Tensor) else np.asarray(features)
    if feats.ndim != 2 or feats.shape[1] != sk.FEATURE_DIM:
        raise ValueError(f"features must have shape (T, {sk.FEATURE_DIM}), got {feats.shape}")
    feats = feats.astype(np.float64)
    rest = np.asarray(sk.REST_OFFSETS if offsets is None else offsets, dtype=np.float64)  # (22, 3)

    joints = features_to_joints(feats)  # (T, 22, 3)
    bone_rots = hml_bone_rotations(feats)  # (T, 22, 4) world rotation of each bone, raw -> actual
    world = np.zeros(joints.shape[:2] + (4,))  # (T, 22, 4)
    world[..., 0] = 1.0
    for j, kids in enumerate(CHILDREN):
        if len(kids) == 1:
            world[:, j] = _single_child_rotation(joints, bone_rots, rest, j, kids[0])
    for joint, *kids in BRANCHES:
        world[:, joint] = _branch_rotation(joints, rest, joint, kids)
    for j, kids in enumerate(CHILDREN):
        if not kids:  # leaves keep their parent's orientation
            world[:, j] = world[:, sk.PARENTS[j]]
    return _world_to_local(world).astype(np.float32), joints[:, 0].astype(np.float32)


def hml_bone_rotations(features: np.ndarray) -> np.ndarray:
    """World rotation of each bone parent(k) -> k that takes RAW_OFFSETS[k] onto it: (T, 22, 4).

    Composed as HumanML3D composes its 6D channels: every chain (the arm chains too) starts from the
    root rotation. Entry 0 is the root rotation itself (facing frame -> world).
    """
    feats = torch.from_numpy(np.asarray(features, dtype=np.float64))
    root_quat, _ = recover_root(feats)  # (T, 4) world -> facing
    # HumanML3D's IK composes from root_quat as if it were the root's world rotation; keep its algebra.
    local6d = feats[:, ROT6D].reshape(len(feats), 21, 6)  # (T, 21, 6)
    local = matrix_to_quat(cont6d_to_matrix(local6d)).numpy()  # (T, 21, 4)
    out = np.zeros((len(feats), sk.NUM_JOINTS, 4))
    out[:, 0] = root_quat.numpy()
    for chain in sk.KINEMATIC_CHAINS:
        rot = out[:, 0]
        for k in chain[1:]:
            rot = qmul(rot, local[:, k - 1])
            out[:, k] = rot
    return out


def _single_child_rotation(joints, bone_rots, rest, j: int, c: int) -> np.ndarray:
    """World rotation of j (T, 4): HumanML3D's bone rotation re-expressed for the rest direction of c,
    then swung so the rest bone lands exactly on the recovered bone j -> c."""
    rest_dir = rest[c] / np.linalg.norm(rest[c])
    raw_dir = sk.RAW_OFFSETS[c]
    rot = qmul(bone_rots[:, c], qbetween(rest_dir, raw_dir)[None])  # takes rest_dir to the 6D bone
    predicted = qrot(rot, np.broadcast_to(rest_dir, (len(rot), 3)))
    actual = joints[:, c] - joints[:, j]
    ok = np.linalg.norm(actual, axis=-1, keepdims=True) > 1e-8
    actual = np.where(ok, actual, predicted)
    return qmul(qbetween(predicted, actual), rot)


def _branch_rotation(joints, rest, joint: int, kids) -> np.ndarray:
    """Rotation (T, 4) best taking the rest child offsets of a branching joint onto the recovered ones."""
    actual = joints[:, kids] - joints[:, joint : joint + 1]  # (T, 3, 3) child offsets
    actual = normalize(actual + 1e-12)
    rest_off = rest[list(kids)]  # (3, 3)
    weights = np.linalg.norm(rest_off, axis=-1)  # longer bones count more
    rest_dir = rest_off / weights[:, None]
    # Wahba: maximise sum w tr(R^T a r^T) via the SVD of B = sum w a r^T.
    b = np.einsum("k,tki,kj->tij", weights, actual, rest_dir)  # (T, 3, 3)
    u, _, vt = np.linalg.svd(b)
    d = np.sign(np.linalg.det(u @ vt))  # (T,)
    fix = np.ones((len(b), 3))
    fix[:, 2] = d
    rot = (u * fix[:, None, :]) @ vt  # (T, 3, 3)
    return matrix_to_quat(rot)


def _world_to_local(world: np.ndarray) -> np.ndarray:
    local = np.empty_like(world)
    for j, p in enumerate(sk.PARENTS):
        local[:, j] = world[:, j] if p < 0 else qmul(qinv(world[:, p]), world[:, j])
    return _continuous(normalize(local))


def _continuous(q: np.ndarray) -> np.ndarray:
    """w >= 0 at frame 0, then no sign jumps along time (for clean interpolation)."""
    q = np.where(q[:1, ..., :1] < 0, -q, q) if len(q) else q
    flips = np.cumsum((q[1:] * q[:-1]).sum(-1) < 0, axis=0) % 2 == 1
    q[1:][flips] *= -1
    return q


def fk(local_quats, root_pos, offsets=None):
    """Forward kinematics: local quaternions (..., 22, 4), root positions (..., 3), rest offsets (22, 3)
    -> joint positions (..., 22, 3). numpy or torch (differentiable) in, the same out."""
    offsets = sk.REST_OFFSETS if offsets is None else offsets
    if isinstance(local_quats, torch.Tensor):
        offsets = torch.as_tensor(np.asarray(offsets), dtype=local_quats.dtype, device=local_quats.device)
        stack = lambda xs: torch.stack(xs, dim=-2)  # noqa: E731
    else:
        local_quats = np.asarray(local_quats, dtype=np.float64)
        offsets = np.asarray(offsets, dtype=np.float64)
        stack = lambda xs: np.stack(xs, axis=-2)  # noqa: E731
    world, pos = [], []
    for j, p in enumerate(sk.PARENTS):
        if p < 0:
            world.append(local_quats[..., j, :])
            pos.append(root_pos)
        else:
            world.append(qmul(world[p], local_quats[..., j, :]))
            pos.append(pos[p] + qrot(world[p], offsets[j]))
    return stack(pos)


def world_rotations(local_quats: np.ndarray) -> np.ndarray:
    """Local (..., 22, 4) -> world (..., 22, 4) rotations."""
    world = []
    for j, p in enumerate(sk.PARENTS):
        world.append(local_quats[..., j, :] if p < 0 else qmul(world[p], local_quats[..., j, :]))
    return np.stack(world, axis=-2)


def rest_offsets_from_joints(joints: np.ndarray) -> np.ndarray:
    """A rest pose (22, 3) fitted to a clip's pelvis and chest: reference bone lengths, RAW_OFFSETS
    directions, except the three child bones of the pelvis and of spine3, which take the clip's average
    shape with the main child (spine1, neck) straight up and the left-right axis along +X."""
    joints = np.asarray(joints, dtype=np.float64)
    rest = sk.RAW_OFFSETS * sk.REFERENCE_BONE_LENGTHS[:, None]  # (22, 3)
    for joint, main, left, right in BRANCHES:
        y = normalize(joints[:, main] - joints[:, joint])  # (T, 3)
        across = joints[:, left] - joints[:, right]
        x = normalize(across - (across * y).sum(-1, keepdims=True) * y)
        z = np.cross(x, y)
        frame = np.stack([x, y, z], axis=-2)  # (T, 3, 3) rows = axes
        for k in (main, left, right):
            d = normalize(joints[:, k] - joints[:, joint])  # (T, 3)
            local = normalize(np.einsum("tij,tj->ti", frame, d).mean(0))
            rest[k] = local * sk.REFERENCE_BONE_LENGTHS[k]
    return rest


def rotation_angle_deg(q: np.ndarray) -> np.ndarray:
    """Angle of each rotation (..., 4) in degrees."""
    q = np.asarray(q, dtype=np.float64)
    return np.degrees(2.0 * np.arctan2(np.linalg.norm(q[..., 1:], axis=-1), np.abs(q[..., 0])))


__all__ = [
    "BRANCHES",
    "features_to_rotations",
    "fk",
    "hml_bone_rotations",
    "rest_offsets_from_joints",
    "rotation_angle_deg",
    "world_rotations",
]
