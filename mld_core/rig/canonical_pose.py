"""From generated motion to pose-bone channels of the canonical armature (bpy-free, numpy only).

Conventions
-----------
- The model works in metres, Y up, the body facing +Z (its left on +X). Blender is Z up and a character
  faces -Y (its left still on +X). ``AXES`` maps one to the other: (x, y, z) -> (x, -z, y), a proper
  rotation (+90 degrees about X).
- Local rotations (T, J, 4) are unit quaternions (w, x, y, z) in the model frame, one per joint, relative
  to the parent joint, on the rest pose of the canonical skeleton (``REST_OFFSETS``: every rest frame
  is aligned with the world). FK: ``G_j = G_parent(j) @ R(q_j)`` and ``p_j = p_parent(j) + G_parent(j) @
  offset_j`` (the rotation of a joint moves its children, as a Blender bone does).
- A Blender pose bone j with rest matrix ``B_j`` (3x3, armature space) and head ``h_j`` evaluates
  ``pose_j = pose_parent @ rest_parent^-1 @ rest_j @ basis_j`` with ``basis_j = T(loc_j) R(M_j)``.
  Choosing ``M_j = B_j^T Q_j B_j`` (``Q_j`` the local rotation in Blender axes) gives the bone the global
  rotation ``G_j B_j``; choosing ``loc_j = B_j^T (G_parent^T (t_j - t_parent) - (h_j - h_parent))`` puts its
  head exactly on the target joint position ``t_j`` (root: ``loc_0 = B_0^T (t_0 - h_0)``). When the
  rotations agree with the joints, ``loc_j`` is only the generated bone-length jitter; keying it makes the
  armature's joints equal the generated joints ("exact" mode).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# model (Y up, facing +Z) -> Blender (Z up, facing -Y)
AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

MIN_BONE_LENGTH = 0.03  # metres; Blender drops zero-length bones
LEAF_LENGTH = {  # metres, for bones without a child joint to point at
    "head": 0.16,
    "left_foot": 0.08,
    "right_foot": 0.08,
    "left_wrist": 0.10,
    "right_wrist": 0.10,
}


# -- quaternions (w, x, y, z), numpy, vectorised over leading axes -------------------------------------------
def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    m = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) with w >= 0."""
    m = np.asarray(m, np.float64)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # four candidate (unnormalised) quaternions; take the numerically largest one per element
    cands = np.stack(
        [
            np.stack([1 + m00 + m11 + m22, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            np.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            np.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1]], -1),
            np.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )  # (..., 4 candidates, 4)
    diag = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions (mld_core's, imported when first needed)."""
    from mld_core.motion.quaternion import slerp as _slerp

    return _slerp(q0, q1, t)


def make_continuous(quats: np.ndarray, axis: int = 0) -> np.ndarray:
    """Flip signs along ``axis`` (time) so consecutive quaternions are in the same hemisphere."""
    q = np.moveaxis(np.array(quats, np.float64, copy=True), axis, 0)
    if len(q) > 1:
        flips = np.cumsum(np.sum(q[1:] * q[:-1], axis=-1) < 0, axis=0) % 2 == 1  # (T-1, ...)
        q[1:][flips] *= -1
    return np.moveaxis(q, 0, axis)


# -- the canonical rest pose -----------------------------------------------------------------------------------
def to_blender(points: np.ndarray) -> np.ndarray:
    """Model coordinates (..., 3) -> Blender coordinates (..., 3)."""
    return np.asarray(points, np.float64) @ AXES.T


def rest_heads(offsets: np.ndarray, parents) -> np.ndarray:
    """Rest joint positions (J, 3) in Blender coordinates, the lowest joint on the floor (z = 0)."""
    offsets = np.asarray(offsets, np.float64)
    heads = np.zeros_like(offsets)
    for j, p in enumerate(parents):
        heads[j] = offsets[j] if p < 0 else heads[p] + offsets[j]
    heads = to_blender(heads)
    heads[:, 2] -= heads[:, 2].min()
    return heads


def rest_tails(heads: np.ndarray, parents, names) -> np.ndarray:
    """A tail per bone: toward its (first) child joint, or along its incoming bone for leaf joints."""
    heads = np.asarray(heads, np.float64)
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        if p >= 0:
            children.setdefault(p, []).append(j)
    tails = np.zeros_like(heads)
    for j, name in enumerate(names):
        kids = children.get(j, [])
        if j == 0 or len(kids) > 1:
            # pelvis and spine3 branch: point along the spine
            spine = [k for k in kids if abs(heads[k, 0] - heads[j, 0]) < 1e-6] or kids
            direction = heads[spine[0]] - heads[j]
        elif kids:
            direction = heads[kids[0]] - heads[j]
        else:
            direction = heads[j] - heads[parents[j]]
            norm = np.linalg.norm(direction)
            direction = direction / norm * LEAF_LENGTH.get(name, 0.08) if norm > 0 else np.array([0, 0, 0.1])
        length = np.linalg.norm(direction)
        if length < MIN_BONE_LENGTH:
            direction = direction / length * MIN_BONE_LENGTH if length > 0 else np.array([0, 0, MIN_BONE_LENGTH])
        tails[j] = heads[j] + direction
    return tails


def canonical_rig():
    """(names, parents, rest heads (22, 3), rest tails (22, 3)) of the canonical armature, Blender axes."""
    from mld_core.motion import skeleton as sk

    offsets = sk.REST_OFFSETS  # the rest pose the rotations are relative to
    heads = rest_heads(offsets, sk.PARENTS)
    return tuple(sk.JOINT_NAMES), tuple(int(p) for p in sk.PARENTS), heads, rest_tails(heads, sk.PARENTS, sk.JOINT_NAMES)


@dataclass
class RigRest:
    """A rig's rest state as Blender sees it (armature space): names, parents, heads (J, 3), rest
    rotation matrices (J, 3, 3) (``bone.matrix_local``'s 3x3 part)."""

    names: tuple
    parents: tuple
    heads: np.ndarray
    matrices: np.ndarray


@dataclass
class BoneChannels:
    """Per-frame pose-bone values: quaternions (F, J, 4) w-first and locations (F, J, 3)."""

    names: tuple
    quaternions: np.ndarray
    locations: np.ndarray
    fps: float
    keyed_locations: tuple  # bone indices whose location is keyed (the root, or all in exact mode)

    @property
    def frames(self) -> int:
        return self.quaternions.shape[0]


# -- resampling -----------------------------------------------------------------------------------------------
def resample_times(frames: int, src_fps: float, dst_fps: float) -> np.ndarray:
    """Source frame positions (fractional) of each destination frame covering the same duration."""
    if frames < 1:
        raise ValueError("no frames")
    if abs(src_fps - dst_fps) < 1e-9:
        return np.arange(frames, dtype=np.float64)
    duration = (frames - 1) / src_fps
    count = int(np.floor(duration * dst_fps + 1e-6)) + 1
    return np.minimum(np.arange(count) * (src_fps / dst_fps), frames - 1)


def resample_positions(values: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Linear interpolation of (T, ...) at fractional frame ``positions``."""
    values = np.asarray(values, np.float64)
    lo = np.floor(positions).astype(int)
    hi = np.minimum(lo + 1, len(values) - 1)
    w = (positions - lo).reshape((-1,) + (1,) * (values.ndim - 1))
    return values[lo] * (1 - w) + values[hi] * w


def resample_quaternions(quats: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Slerp of (T, J, 4) at fractional frame ``positions``."""
    quats = np.asarray(quats, np.float64)
    lo = np.floor(positions).astype(int)
    hi = np.minimum(lo + 1, len(quats) - 1)
    w = np.broadcast_to((positions - lo)[:, None], (len(positions), quats.shape[1]))
    return slerp(quats[lo], quats[hi], w)


# -- channels ---------------------------------------------------------------------------------------------------
def global_rotations(local_quats: np.ndarray, parents) -> np.ndarray:
    """Local quaternions (T, J, 4) -> global rotation matrices (T, J, 3, 3) (same axes)."""
    local = quat_to_matrix(local_quats)
    glob = np.empty_like(local)
    for j, p in enumerate(parents):
        glob[:, j] = local[:, j] if p < 0 else glob[:, p] @ local[:, j]
    return glob


def forward_kinematics(local_quats: np.ndarray, root_positions: np.ndarray, offsets: np.ndarray, parents) -> np.ndarray:
    """Joint positions (T, J, 3) from local quaternions, root positions and rest offsets (same axes)."""
    glob = global_rotations(local_quats, parents)
    offsets = np.asarray(offsets, np.float64)
    joints = np.empty(glob.shape[:2] + (3,))
    for j, p in enumerate(parents):
        joints[:, j] = root_positions if p < 0 else joints[:, p] + glob[:, p] @ offsets[j]
    return joints


def pose_channels(
    local_quats: np.ndarray,
    joints: np.ndarray,
    rest: RigRest,
    *,
    src_fps: float = 20.0,
    dst_fps: float | None = None,
    exact: bool = True,
) -> BoneChannels:
    """Pose-bone quaternions and locations that put the rig on the generated motion.

    ``local_quats`` (T, J, 4) and ``joints`` (T, J, 3) are in model axes (joint order = ``rest.names``);
    ``rest`` is in Blender armature space. With ``exact`` every bone's location is keyed so its head lands
    on the generated joint; otherwise only the root's.
    """
    local_quats = np.asarray(local_quats, np.float64)
    joints = np.asarray(joints, np.float64)
    T, J = joints.shape[:2]
    if local_quats.shape != (T, J, 4):
        raise ValueError(f"rotations {local_quats.shape} do not match joints {joints.shape}")
    if len(rest.names) != J:
        raise ValueError(f"the rig has {len(rest.names)} bones, the motion {J} joints")
    parents = rest.parents
    if dst_fps is not None and abs(dst_fps - src_fps) > 1e-9:
        positions = resample_times(T, src_fps, dst_fps)
        local_quats = resample_quaternions(make_continuous(local_quats), positions)
        joints = resample_positions(joints, positions)
    fps = float(dst_fps or src_fps)

    targets = to_blender(joints)  # (F, J, 3)
    local = AXES @ quat_to_matrix(local_quats) @ AXES.T  # (F, J, 3, 3) Blender axes
    glob = np.empty_like(local)
    for j, p in enumerate(parents):
        glob[:, j] = local[:, j] if p < 0 else glob[:, p] @ local[:, j]
    B = np.asarray(rest.matrices, np.float64)  # (J, 3, 3)
    Bt = np.swapaxes(B, -1, -2)
    basis = Bt[None] @ local @ B[None]  # (F, J, 3, 3)
    quats = make_continuous(matrix_to_quat(basis))

    heads = np.asarray(rest.heads, np.float64)
    locs = np.zeros(targets.shape)
    keyed = []
    for j, p in enumerate(parents):
        if p < 0:
            locs[:, j] = (targets[:, j] - heads[j]) @ B[j]  # B^T v as row vectors
            keyed.append(j)
        elif exact:
            rel = np.einsum("fji,fj->fi", glob[:, p], targets[:, j] - targets[:, p])  # G_p^T (t_j - t_p)
            locs[:, j] = (rel - (heads[j] - heads[p])) @ B[j]
            keyed.append(j)
    return BoneChannels(tuple(rest.names), quats.astype(np.float32), locs.astype(np.float32), fps, tuple(keyed))


def evaluate_pose(channels: BoneChannels, rest: RigRest) -> np.ndarray:
    """Blender's pose evaluation in numpy: posed bone heads (F, J, 3) in armature space (for checks)."""
    B = np.asarray(rest.matrices, np.float64)
    heads = np.asarray(rest.heads, np.float64)
    M = quat_to_matrix(channels.quaternions.astype(np.float64))
    loc = channels.locations.astype(np.float64)
    F, J = M.shape[:2]
    pose_rot = np.empty((F, J, 3, 3))
    pose_head = np.empty((F, J, 3))
    for j, p in enumerate(rest.parents):
        if p < 0:
            pose_rot[:, j] = B[j] @ M[:, j]
            pose_head[:, j] = heads[j] + loc[:, j] @ B[j].T
        else:
            # pose_p @ rest_p^-1 @ rest_j @ basis_j
            A = pose_rot[:, p] @ B[p].T  # (F, 3, 3)
            pose_rot[:, j] = A @ B[j] @ M[:, j]
            local_point = loc[:, j] @ B[j].T + (heads[j] - heads[p])
            pose_head[:, j] = pose_head[:, p] + np.einsum("fij,fj->fi", A, local_point)
    return pose_head


def canonical_rest(rig) -> RigRest:
    """The canonical bones of ``rig`` (a ``retarget.RigRest`` read from an armature that has them), in skeleton
    order: heads and rest rotations in armature space."""
    from mld_core.motion.skeleton import JOINT_NAMES, PARENTS

    missing = [n for n in JOINT_NAMES if n not in rig]
    if missing:
        raise ValueError(f"armature {rig.name!r} lacks the bones {', '.join(missing)}")
    idx = [rig.index(n) for n in JOINT_NAMES]
    return RigRest(tuple(JOINT_NAMES), tuple(int(p) for p in PARENTS), rig.heads[idx].copy(),
                   rig.matrices[idx, :3, :3].copy())


def channels_to_keys(channels: BoneChannels, frame_start: float):
    """The exact pose as the one keys object (``keyframes.BakedKeys``): a LINEAR key on every frame, quaternion
    rotations, per bone its location curves (when keyed) then its rotation curves."""
    from mld_core.rig.keyframes import BakedKeys, CurveKeys

    frames = frame_start + np.arange(channels.frames, dtype=np.float64)
    keyed = set(channels.keyed_locations)
    curves = []
    for j, bone in enumerate(channels.names):
        base = f'pose.bones["{bone}"]'
        if j in keyed:
            curves += [CurveKeys(base + ".location", i, bone, frames, channels.locations[:, j, i]) for i in range(3)]
        curves += [CurveKeys(base + ".rotation_quaternion", i, bone, frames, channels.quaternions[:, j, i])
                   for i in range(4)]
    return BakedKeys(curves, fps=channels.fps, frame_start=float(frame_start), num_frames=channels.frames,
                     interpolation="LINEAR", handle_type=None, auto_smoothing=None,
                     rotation_modes={bone: "QUATERNION" for bone in channels.names},
                     stats={"reduction_ratio": 1.0})
