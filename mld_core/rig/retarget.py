"""Retarget canonical 22-joint motion onto any humanoid armature (numpy only, no bpy).

The source is a take of joint positions ``(T, 22, 3)`` in metres, Y up, facing +Z at frame 0 (the layout of
``mld_core.motion.skeleton``). The target is an armature's rest pose as plain arrays (:class:`RigRest`, read from
Blender by :mod:`blender_addon.rig_io` or loaded from a fixture). A bone map says which bone plays which canonical
joint: the bone whose head sits at that joint (``left_hip`` -> the thigh bone, ``left_knee`` -> the shin bone, ...).

How each mapped bone is posed (every frame, parents before children):

* Its *segment* runs from its head to the head of the next mapped bone down the canonical chain (pelvis -> spine1
  -> ... -> head, hip -> knee -> ankle -> foot, collar -> shoulder -> elbow -> wrist). Bones in between that are not
  mapped stay at rest relative to their parent and are carried along rigidly.
* The segment's direction is matched *absolutely*: the posed target segment points where the source segment points.
  Rest poses therefore do not matter (T-pose, A-pose, or a degenerate BVH rest with every bone along one axis).
* Swing: the minimal rotation from where the bone's rest segment points once carried by its posed parent to the
  source direction, so a bone has no twist relative to its parent unless a twist reference says otherwise.
* Twist about the segment, from a reference computed the same way on the source joints and on the rig's rest joints:
  the hips' lateral axis for the pelvis, a blend of hip and shoulder lateral axes along the spine, the torso's up
  axis for the collars, and the elbow / knee hinge axis for the upper arm / thigh (the hinge is known only when the
  limb is bent; a straight limb keeps the twist it had, so it never snaps). Forearm, shin and foot get swing only,
  which makes elbows and knees pure hinges once the parent's twist is right.
* Bones with no mapped segment end (head, hands, toes) keep their rest rotation relative to their parent.
* The pelvis bone gets a location: the source is converted to Blender's Z up (facing -Y), scaled by the ratio of
  the rig's leg length to the source's (a hip-height ratio that also works for rigs whose rest pose is not standing),
  recentred on the armature object's origin, and the pelvis is placed so that the midpoint of the rig's hips lands
  on the scaled source hips' midpoint.

Pose-bone conventions follow Blender: ``pose = parent_pose @ parent_rest^-1 @ rest @ T(location) @ R(quaternion)``
with rest matrices ``bone.matrix_local`` in armature space and quaternions ``(w, x, y, z)``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from typing import Mapping

import numpy as np

from mld_core.motion import skeleton as _sk

JOINT_NAMES: tuple[str, ...] = tuple(_sk.JOINT_NAMES)
JOINT_INDEX = {name: i for i, name in enumerate(JOINT_NAMES)}

# The next joint down the canonical chain that a joint's bone points at (leaves: head, feet, wrists).
CHAIN_CHILD = {
    "pelvis": "spine1", "spine1": "spine2", "spine2": "spine3", "spine3": "neck", "neck": "head",
    "left_hip": "left_knee", "left_knee": "left_ankle", "left_ankle": "left_foot",
    "right_hip": "right_knee", "right_knee": "right_ankle", "right_ankle": "right_foot",
    "left_collar": "left_shoulder", "left_shoulder": "left_elbow", "left_elbow": "left_wrist",
    "right_collar": "right_shoulder", "right_shoulder": "right_elbow", "right_elbow": "right_wrist",
}

# Joints every bone map must cover: enough to pose the legs, arms and head and to find the body's axes.
REQUIRED_JOINTS = (
    "pelvis", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "head",
)

# Y-up source (x, y, z) -> Blender Z-up (x, -z, y): +Z facing becomes -Y facing, left stays +X.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

_EPS = 1e-9


class RetargetError(ValueError):
    """The rig or the bone map cannot be retargeted onto (the message says why)."""


# --------------------------------------------------------------------------------------------------------------
# Small rotation helpers (matrices act on column vectors; quaternions are (w, x, y, z)).


def normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, _EPS)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (normalised here, as Blender does) -> (..., 3, 3)."""
    q = normalize(np.asarray(q, dtype=np.float64))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    m = np.empty(q.shape[:-1] + (3, 3))
    m[..., 0, 0] = 1 - 2 * (y * y + z * z)
    m[..., 0, 1] = 2 * (x * y - w * z)
    m[..., 0, 2] = 2 * (x * z + w * y)
    m[..., 1, 0] = 2 * (x * y + w * z)
    m[..., 1, 1] = 1 - 2 * (x * x + z * z)
    m[..., 1, 2] = 2 * (y * z - w * x)
    m[..., 2, 0] = 2 * (x * z - w * y)
    m[..., 2, 1] = 2 * (y * z + w * x)
    m[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return m


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions with w >= 0."""
    m = np.asarray(m, dtype=np.float64)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # Four candidate |components|, pick the largest for numerical stability (Shepperd's method).
    cand = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = np.argmax(cand, axis=-1)
    s = np.sqrt(np.maximum(np.take_along_axis(cand, best[..., None], -1)[..., 0], _EPS)) * 2  # 4 * |component|
    q = np.empty(m.shape[:-2] + (4,))
    r21, r12 = m[..., 2, 1], m[..., 1, 2]
    r02, r20 = m[..., 0, 2], m[..., 2, 0]
    r10, r01 = m[..., 1, 0], m[..., 0, 1]
    sel = [best == i for i in range(4)]
    q[..., 0] = np.select(sel, [s / 4, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s])
    q[..., 1] = np.select(sel, [(r21 - r12) / s, s / 4, (r01 + r10) / s, (r02 + r20) / s])
    q[..., 2] = np.select(sel, [(r02 - r20) / s, (r01 + r10) / s, s / 4, (r12 + r21) / s])
    q[..., 3] = np.select(sel, [(r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, s / 4])
    q = normalize(q)
    return np.where(q[..., :1] < 0, -q, q)


def axis_angle_matrix(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation by ``angle`` (...) radians about unit ``axis`` (..., 3) -> (..., 3, 3) (Rodrigues)."""
    axis = normalize(axis)
    angle = np.asarray(angle, dtype=np.float64)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    c, s = np.cos(angle), np.sin(angle)
    t = 1 - c
    m = np.empty(axis.shape[:-1] + (3, 3))
    m[..., 0, 0] = c + x * x * t
    m[..., 0, 1] = x * y * t - z * s
    m[..., 0, 2] = x * z * t + y * s
    m[..., 1, 0] = y * x * t + z * s
    m[..., 1, 1] = c + y * y * t
    m[..., 1, 2] = y * z * t - x * s
    m[..., 2, 0] = z * x * t - y * s
    m[..., 2, 1] = z * y * t + x * s
    m[..., 2, 2] = c + z * z * t
    return m


def any_perpendicular(v: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to each unit ``v`` (..., 3)."""
    v = normalize(v)
    helper = np.where(np.abs(v[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    return normalize(np.cross(v, helper))


def rotation_between(a: np.ndarray, b: np.ndarray, fallback_axis: np.ndarray | None = None) -> np.ndarray:
    """Minimal rotation (..., 3, 3) taking unit vectors ``a`` onto ``b``.

    Opposite vectors have no unique minimal rotation: they turn by 180 degrees about ``fallback_axis``
    (made perpendicular to ``a``) or about an arbitrary perpendicular.
    """
    a = normalize(a)
    b = normalize(b)
    a, b = np.broadcast_arrays(a, b)
    axis = np.cross(a, b)
    sin = np.linalg.norm(axis, axis=-1)
    cos = np.sum(a * b, axis=-1)
    angle = np.arctan2(sin, cos)
    opposite = (sin < 1e-8) & (cos < 0)
    if np.any(opposite):
        perp = any_perpendicular(a)
        if fallback_axis is not None:
            f = np.broadcast_to(fallback_axis, a.shape)
            f = f - np.sum(f * a, -1, keepdims=True) * a
            ok = np.linalg.norm(f, axis=-1, keepdims=True) > 1e-6
            perp = np.where(ok, normalize(f), perp)
        axis = np.where(opposite[..., None], perp, axis)
    axis = np.where((sin < 1e-12)[..., None] & ~opposite[..., None], np.array([1.0, 0.0, 0.0]), axis)
    return axis_angle_matrix(axis, angle)


def signed_angle(u: np.ndarray, v: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Angle (radians, (-pi, pi]) turning ``u`` onto ``v`` about ``axis`` (all (..., 3))."""
    return np.arctan2(np.sum(axis * np.cross(u, v), -1), np.sum(u * v, -1))


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


# --------------------------------------------------------------------------------------------------------------
# The target rig's rest pose.


@dataclass
class RigRest:
    """An armature's rest pose as arrays (what Blender's ``bone.matrix_local`` holds, in armature space).

    names: bone names; parents: (B,) index of each bone's parent, -1 for roots (parents come before children is
    not required); matrices: (B, 4, 4) rest matrices, columns = the bone's X, Y (head -> tail), Z axes and head;
    tails: (B, 3); object_matrix: (4, 4) the armature object's world matrix (rotation, uniform scale, location)
    when the rest was read; use_connect / use_local_location: per-bone flags (informative).
    """

    names: list[str]
    parents: np.ndarray
    matrices: np.ndarray
    tails: np.ndarray
    object_matrix: np.ndarray = field(default_factory=lambda: np.eye(4))
    use_connect: np.ndarray | None = None
    name: str = ""

    def __post_init__(self) -> None:
        self.names = [str(n) for n in self.names]
        self.parents = np.asarray(self.parents, dtype=np.int64).reshape(-1)
        self.matrices = np.asarray(self.matrices, dtype=np.float64).reshape(-1, 4, 4)
        self.tails = np.asarray(self.tails, dtype=np.float64).reshape(-1, 3)
        self.object_matrix = np.asarray(self.object_matrix, dtype=np.float64).reshape(4, 4)
        n = len(self.names)
        if not (len(self.parents) == len(self.matrices) == len(self.tails) == n):
            raise RetargetError("rig arrays disagree in length (names, parents, matrices, tails)")
        if len(set(self.names)) != n:
            raise RetargetError("rig has duplicate bone names")
        if np.any(self.parents >= n) or np.any(self.parents < -1):
            raise RetargetError("rig parent index out of range")
        if self.use_connect is not None:
            self.use_connect = np.asarray(self.use_connect, dtype=bool).reshape(-1)
        self._index = {nm: i for i, nm in enumerate(self.names)}
        self.order = _topological_order(self.parents)

    @property
    def heads(self) -> np.ndarray:
        return self.matrices[:, :3, 3]

    def index(self, name: str) -> int:
        try:
            return self._index[name]
        except KeyError:
            raise RetargetError(f"the armature has no bone named {name!r}") from None

    def __contains__(self, name: str) -> bool:
        return name in self._index

    def parent_name(self, name: str) -> str | None:
        p = self.parents[self.index(name)]
        return None if p < 0 else self.names[p]

    def ancestors(self, i: int) -> list[int]:
        out = []
        p = self.parents[i]
        while p >= 0:
            out.append(int(p))
            p = self.parents[p]
        return out

    def world_scale(self) -> float:
        """Uniform scale of the object matrix (world units per armature unit)."""
        return float(np.cbrt(abs(np.linalg.det(self.object_matrix[:3, :3]))))

    def with_parents(self, overrides: Mapping[str, str]) -> "RigRest":
        """A copy in which some bones follow another bone than their real parent.

        For control rigs whose controls hang off helper bones driven by constraints (Rigify's FK controls), the
        bone that a control effectively moves with is not its parent in the hierarchy.
        """
        if not overrides:
            return self
        parents = self.parents.copy()
        for child, parent in overrides.items():
            if child in self and parent in self:
                parents[self.index(child)] = self.index(parent)
        return replace(self, parents=parents)

    # --- (de)serialisation, for fixtures and caching --------------------------------------------------------

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "names": list(self.names),
            "parents": [int(p) for p in self.parents],
            "matrices": np.round(self.matrices[:, :3, :], 6).tolist(),
            "tails": np.round(self.tails, 6).tolist(),
            "object_matrix": np.round(self.object_matrix, 6).tolist(),
            "use_connect": None if self.use_connect is None else [bool(c) for c in self.use_connect],
        }

    @classmethod
    def from_dict(cls, d: Mapping) -> "RigRest":
        m34 = np.asarray(d["matrices"], dtype=np.float64).reshape(-1, 3, 4)
        mats = np.zeros((len(m34), 4, 4))
        mats[:, :3, :] = m34
        mats[:, 3, 3] = 1.0
        # Re-orthonormalise the rotation part that was rounded for storage.
        u, _, vt = np.linalg.svd(mats[:, :3, :3])
        mats[:, :3, :3] = u @ vt
        return cls(
            names=list(d["names"]),
            parents=d["parents"],
            matrices=mats,
            tails=d["tails"],
            object_matrix=d.get("object_matrix", np.eye(4).tolist()),
            use_connect=d.get("use_connect"),
            name=d.get("name", ""),
        )

    def save(self, path: str | os.PathLike) -> None:
        tmp = f"{os.fspath(path)}.tmp"
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(self.to_dict(), fh, separators=(",", ":"))
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "RigRest":
        with open(path, encoding="utf-8") as fh:
            return cls.from_dict(json.load(fh))


def _topological_order(parents: np.ndarray) -> list[int]:
    n = len(parents)
    depth = np.full(n, -1)
    for i in range(n):
        chain = []
        j = i
        while j >= 0 and depth[j] < 0:
            chain.append(j)
            if len(chain) > n:
                raise RetargetError("rig hierarchy has a cycle")
            j = parents[j]
        d = depth[j] if j >= 0 else -1
        for k in reversed(chain):
            d += 1
            depth[k] = d
    return [int(i) for i in np.argsort(depth, kind="stable")]


def rig_from_heads(
    names: list[str],
    parents: list[int],
    heads: np.ndarray,
    tails: np.ndarray,
    *,
    rolls: np.ndarray | None = None,
    object_matrix: np.ndarray | None = None,
    name: str = "",
) -> RigRest:
    """Build a :class:`RigRest` from bone heads, tails and rolls (radians) the way Blender's edit bones do."""
    heads = np.asarray(heads, dtype=np.float64)
    tails = np.asarray(tails, dtype=np.float64)
    rolls = np.zeros(len(names)) if rolls is None else np.asarray(rolls, dtype=np.float64)
    mats = np.tile(np.eye(4), (len(names), 1, 1))
    for i in range(len(names)):
        mats[i, :3, :3] = bone_rest_matrix(tails[i] - heads[i], rolls[i])
        mats[i, :3, 3] = heads[i]
    return RigRest(
        names=names, parents=parents, matrices=mats, tails=tails,
        object_matrix=np.eye(4) if object_matrix is None else object_matrix, name=name,
    )


def bone_rest_matrix(vector: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Blender's ``vec_roll_to_mat3``: the rest rotation of a bone pointing along ``vector`` with ``roll``."""
    y = normalize(np.asarray(vector, dtype=np.float64))
    # Minimal rotation from +Y onto the bone's direction (Blender's special case for -Y: a half turn about Z).
    if y[1] < -1 + 1e-6:
        base = np.diag([-1.0, -1.0, 1.0])
    else:
        base = rotation_between(np.array([0.0, 1.0, 0.0]), y)
    return base @ axis_angle_matrix(np.array([0.0, 1.0, 0.0]), roll)


def canonical_rig(offsets: np.ndarray | None = None, *, leaf_length: float = 0.08) -> RigRest:
    """The canonical armature: one bone per joint of ``mld_core.motion.skeleton``, named after the joint.

    Each bone's head is its joint (the reference skeleton, Z up, facing -Y); its tail is the head of its chain child
    (a short stub along the parent's direction for head, wrists and feet); rolls are 0. Bones are connected where
    the tail of the parent is the head of the child.
    """
    if offsets is None:  # the rest pose the motion's rotations refer to, where the skeleton module defines one
        offsets = _sk.REST_OFFSETS
    offsets = np.asarray(offsets, dtype=np.float64)
    n = len(JOINT_NAMES)
    pos = np.zeros((n, 3))
    for j in range(n):
        p = _sk.PARENTS[j]
        pos[j] = offsets[j] if p < 0 else pos[p] + offsets[j]
    pos = pos @ Y_UP_TO_Z_UP.T
    # Stand on the floor: ankles and toes (level in the reference skeleton) 5 cm above it.
    pos[:, 2] -= pos[:, 2].min() - 0.05
    heads = pos
    tails = np.zeros_like(heads)
    for j, name in enumerate(JOINT_NAMES):
        child = CHAIN_CHILD.get(name)
        if child is not None:
            tails[j] = heads[JOINT_INDEX[child]]
        else:
            p = _sk.PARENTS[j]
            direction = normalize(heads[j] - heads[p])
            if name == "head":
                direction = np.array([0.0, 0.0, 1.0])
            tails[j] = heads[j] + leaf_length * direction
        if np.linalg.norm(tails[j] - heads[j]) < 1e-4:  # zero-length bone (e.g. pelvis -> spine1 overlap)
            tails[j] = heads[j] + np.array([0.0, 0.0, leaf_length])
    return rig_from_heads(list(JOINT_NAMES), list(_sk.PARENTS), heads, tails, name="canonical")


# --------------------------------------------------------------------------------------------------------------
# Forward kinematics on the target rig (Blender's pose-bone convention).


def fk(
    rig: RigRest,
    rotations: np.ndarray | None = None,
    locations: np.ndarray | None = None,
    bones: list[int] | None = None,
) -> np.ndarray:
    """Posed armature-space matrices (T, B, 4, 4) from local quaternions (T, B, 4) and locations (T, B, 3).

    ``pose[b] = pose[parent] @ rest[parent]^-1 @ rest[b] @ T(location[b]) @ R(rotation[b])``; roots use
    ``rest[b] @ T @ R``. ``None`` means rest (identity / zero) for every bone. ``bones``: only these bones (and
    their ancestors) are computed; the other entries are left undefined.
    """
    if rotations is None and locations is None:
        rotations = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (1, len(rig.names), 1))
    T = (rotations if rotations is not None else locations).shape[0]
    B = len(rig.names)
    local = np.tile(np.eye(4), (T, B, 1, 1))
    if rotations is not None:
        local[:, :, :3, :3] = quat_to_matrix(rotations)
    if locations is not None:
        local[:, :, :3, 3] = locations
    rest = rig.matrices
    rest_inv = np.linalg.inv(rest)
    pose = np.empty((T, B, 4, 4))
    order = rig.order
    if bones is not None:
        needed = set()
        for b in bones:
            needed.add(int(b))
            needed.update(rig.ancestors(int(b)))
        order = [b for b in order if b in needed]
    for b in order:
        p = rig.parents[b]
        if p < 0:
            pose[:, b] = rest[b] @ local[:, b]
        else:
            pose[:, b] = pose[:, p] @ (rest_inv[p] @ rest[b]) @ local[:, b]
    return pose


# --------------------------------------------------------------------------------------------------------------
# Retargeting.


@dataclass
class RetargetOptions:
    """How the take is placed on the rig.

    yaw_deg: extra turn about world Z (0: the take faces -Y at its first frame, Blender's front view).
    recenter: start the take over the armature object's origin (else keep the source's absolute ground position).
    scale: world units per source metre; None: the rig's leg length over the source's (thigh + shin).
    twist: use twist references (hinges, lateral axes); False gives swing-only rotations.
    match: "effectors" (default) keeps hands, feet and head where the source puts them relative to the limb's
        root, the source limb scaled to the rig's limb length: arms and legs are solved as two-bone chains in the
        source's bend plane, the spine aims each bone at the scaled source's next joint. "directions" turns every
        segment exactly along the source's (effectors then drift by the difference in proportions).
    floor: for rigs whose rest pose stands, shift the take vertically so the source's standing ankle height (its
        5th percentile over the take) becomes the rig's rest ankle height, pitch the feet so a foot planted flat
        in the source is as flat as the rig's rest foot, and keep every foot joint (ankles, toes) at or above
        its rest height (the rig's feet never go through the floor it stands on at rest).
    """

    yaw_deg: float = 0.0
    recenter: bool = True
    scale: float | None = None
    twist: bool = True
    match: str = "effectors"
    floor: bool = True


@dataclass
class RetargetResult:
    """Pose-bone keys for the mapped bones, at the source's frame rate.

    bones: mapped bone names (parents before children); joints: the canonical joint of each;
    rotations: (T, K, 4) pose-bone quaternions (w, x, y, z), sign-continuous over time;
    root_bone / root_location: the pelvis bone and its pose-bone location (T, 3) in its local rest space
    (armature units); scale: world units per source metre; source_world: (T, 22, 3) the placed source joints in
    world space (Z up, scaled) that the rig follows; rig: the rest used (with any parent overrides).
    """

    bones: list[str]
    joints: list[str]
    rotations: np.ndarray
    root_bone: str
    root_location: np.ndarray
    scale: float
    fps: float
    source_world: np.ndarray
    rig: RigRest

    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[0])

    def full_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(T, B, 4) rotations and (T, B, 3) locations over all bones of the rig (rest for unmapped bones)."""
        T, B = self.num_frames, len(self.rig.names)
        rot = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (T, B, 1))
        loc = np.zeros((T, B, 3))
        for k, name in enumerate(self.bones):
            rot[:, self.rig.index(name)] = self.rotations[:, k]
        loc[:, self.rig.index(self.root_bone)] = self.root_location
        return rot, loc

    def world_joints(self) -> dict[str, np.ndarray]:
        """World-space (T, 3) head position of every mapped bone after FK, keyed by canonical joint."""
        rot, loc = self.full_pose()
        idx = [self.rig.index(b) for b in self.bones]
        pose = fk(self.rig, rot, loc, bones=idx)
        return {j: _to_world(self.rig, pose[:, i, :3, 3]) for j, i in zip(self.joints, idx)}


def _to_world(rig: RigRest, points: np.ndarray) -> np.ndarray:
    m = rig.object_matrix
    return points @ m[:3, :3].T + m[:3, 3]


def _to_armature(rig: RigRest, points: np.ndarray) -> np.ndarray:
    inv = np.linalg.inv(rig.object_matrix)
    return points @ inv[:3, :3].T + inv[:3, 3]


def check_joints(joints: np.ndarray) -> np.ndarray:
    joints = np.asarray(joints, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (len(JOINT_NAMES), 3):
        raise RetargetError(f"source joints must have shape (T, {len(JOINT_NAMES)}, 3), got {joints.shape}")
    if joints.shape[0] < 1:
        raise RetargetError("source take has no frames")
    if not np.all(np.isfinite(joints)):
        raise RetargetError("source joints contain NaN or infinite values")
    return joints


def leg_length(points: Mapping[str, np.ndarray]) -> np.ndarray:
    """Mean of the two legs' thigh + shin lengths, from joint positions (..., 3)."""
    total = 0.0
    for side in ("left", "right"):
        hip, knee, ankle = points[f"{side}_hip"], points[f"{side}_knee"], points[f"{side}_ankle"]
        total = total + np.linalg.norm(knee - hip, axis=-1) + np.linalg.norm(ankle - knee, axis=-1)
    return total / 2


def place_source(
    joints: np.ndarray, rig: RigRest, bone_map: Mapping[str, str], options: RetargetOptions | None = None
) -> tuple[np.ndarray, float]:
    """Source joints (T, 22, 3) Y-up metres -> world space (Z up, facing -Y, scaled, over the rig's origin)."""
    options = options or RetargetOptions()
    joints = check_joints(joints)
    src = joints @ Y_UP_TO_Z_UP.T  # (T, 22, 3) Z up
    yaw = math.radians(options.yaw_deg)
    if yaw:
        src = src @ axis_angle_matrix(np.array([0.0, 0.0, 1.0]), yaw).T
    if options.scale is not None:
        scale = float(options.scale)
    else:
        src_len = float(np.median(leg_length({n: src[:, JOINT_INDEX[n]] for n in JOINT_NAMES})))
        world_heads = _to_world(rig, rig.heads)
        tgt_len = float(leg_length({j: world_heads[rig.index(b)] for j, b in bone_map.items()}))
        if src_len < 1e-6 or tgt_len < 1e-9:
            raise RetargetError("cannot measure leg length (zero-length thigh or shin) to scale the take")
        scale = tgt_len / src_len
    ground = np.zeros(3)
    if options.recenter:
        ground[:2] = src[0, JOINT_INDEX["pelvis"], :2]
    origin = rig.object_matrix[:3, 3]
    world = (src - ground) * scale + origin
    standing = standing_heights(rig, bone_map)
    if standing is not None and options.floor:
        # Lift or lower the take so the source's feet stand as high above the floor as the rig's feet do at rest
        # (ankle joints sit at different heights above the sole on different skeletons).
        ankles = world[:, [JOINT_INDEX["left_ankle"], JOINT_INDEX["right_ankle"]], 2] - origin[2]
        src_stand = float(np.percentile(ankles, 5))
        rig_stand = (standing["left_ankle"] + standing["right_ankle"]) / 2
        world[..., 2] += rig_stand - src_stand
        # Feet: a foot planted flat in the source should be flat on the rig too, whatever angle each skeleton's
        # ankle -> toe line makes with the floor. Pitch the source's feet by the difference between the rig's rest
        # pitch and the source's pitch while standing (frames where that ankle is low).
        heads = _to_world(rig, rig.heads)
        for side in ("left", "right"):
            ankle, toe = f"{side}_ankle", f"{side}_foot"
            if toe not in standing:
                continue
            rig_pitch = _pitch(heads[rig.index(bone_map[toe])] - heads[rig.index(bone_map[ankle])])
            foot = world[:, JOINT_INDEX[toe]] - world[:, JOINT_INDEX[ankle]]  # (T, 3)
            height = world[:, JOINT_INDEX[ankle], 2]
            planted = height <= np.percentile(height, 10) + 1e-9
            src_pitch = float(np.median(_pitch(foot[planted])))
            # Turn the foot about the hips' (horizontal) lateral axis: well defined however steep the foot is.
            lateral = world[:, JOINT_INDEX["left_hip"]] - world[:, JOINT_INDEX["right_hip"]]
            lateral[:, 2] = 0.0
            turn = axis_angle_matrix(normalize(lateral), np.full(len(foot), rig_pitch - src_pitch))
            world[:, JOINT_INDEX[toe]] = world[:, JOINT_INDEX[ankle]] + np.einsum("tij,tj->ti", turn, foot)
        # The floor: no foot joint lower above the floor the take stands on (the rig's origin) than it stands
        # above its own soles at rest (generated feet dip a few centimetres below their standing height); the legs
        # and feet are solved to reach the lifted joints. (A BVH rig rests with its feet below its origin, at the
        # hips: its absolute rest heights are not the floor the take walks on.)
        for joint in standing:
            z_min = origin[2] + standing[joint]
            world[:, JOINT_INDEX[joint], 2] = np.maximum(world[:, JOINT_INDEX[joint], 2], z_min)
    return world, scale


def _pitch(v: np.ndarray) -> np.ndarray:
    """Angle (radians) of vectors (..., 3) below the horizontal plane (world Z up)."""
    return np.arctan2(-v[..., 2], np.linalg.norm(v[..., :2], axis=-1))


def standing_heights(rig: RigRest, bone_map: Mapping[str, str]) -> dict[str, float] | None:
    """Height above the floor of each mapped foot joint (ankles, toes) in the rig's rest pose, in world units, if
    the rest pose stands (thighs and shins pointing down); None otherwise (e.g. a BVH rest along one axis).

    The floor is the armature object's origin, or the lowest foot joint if that is lower.
    """
    heads = _to_world(rig, rig.heads)
    p = {j: heads[rig.index(b)] for j, b in bone_map.items()}
    for side in ("left", "right"):
        for a, b in ((f"{side}_hip", f"{side}_knee"), (f"{side}_knee", f"{side}_ankle")):
            if a not in p or b not in p or normalize(p[b] - p[a])[2] > -0.8:
                return None
    feet = [j for j in ("left_ankle", "right_ankle", "left_foot", "right_foot") if j in p]
    floor = min(rig.object_matrix[2, 3], min(p[j][2] for j in feet))
    return {j: float(p[j][2] - floor) for j in feet}


def _segment_end(joint: str, mapped: Mapping[str, str], heads: Mapping[str, np.ndarray] | None = None,
                 min_length: float = 0.0) -> str | None:
    """The next mapped joint down the chain, skipping any whose rest head coincides with this joint's."""
    child = CHAIN_CHILD.get(joint)
    while child is not None and (
        child not in mapped
        or (heads is not None and np.linalg.norm(heads[child] - heads[joint]) <= min_length)
    ):
        child = CHAIN_CHILD.get(child)
    return child


def _body_axes(p: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    lat_h = normalize(p["left_hip"] - p["right_hip"])
    # The collars hang off the chest at fixed offsets, so they give its lateral axis best; else the shoulders.
    if "left_collar" in p and "right_collar" in p:
        lat_s = normalize(p["left_collar"] - p["right_collar"])
    else:
        lat_s = normalize(p["left_shoulder"] - p["right_shoulder"])
    up = normalize(p["head"] - p["pelvis"])
    return {
        "lat_h": lat_h,
        "lat_s": lat_s,
        "up": up,
        "fwd_h": normalize(np.cross(lat_h, up)),
        "fwd_s": normalize(np.cross(lat_s, up)),
    }


def _bend_weight(u: np.ndarray, v: np.ndarray, lo_deg: float = 10.0, hi_deg: float = 30.0) -> np.ndarray:
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, -1)))
    return _smoothstep((angle - lo_deg) / (hi_deg - lo_deg))


def twist_reference(joint: str, p: Mapping[str, np.ndarray], rest: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """The twist reference axis (..., 3) of a joint's bone and its confidence weight (...), or None (swing only).

    ``p`` maps the mapped joints' names to positions (the same joints on the source and on the rest).
    ``rest=True`` computes it on a rig's rest pose, where limbs may be straight: the hinge axis is then the
    anatomical one (perpendicular to the limb and the body's facing), which has the sign the measured hinge has
    when an elbow or knee bends the natural way.
    """
    ax = _body_axes(p)
    one = np.ones(ax["up"].shape[:-1])
    if joint == "pelvis":
        return ax["lat_h"], one
    if joint == "spine1":
        return normalize(2 * ax["lat_h"] + ax["lat_s"]), one
    if joint == "spine2":
        return normalize(ax["lat_h"] + 2 * ax["lat_s"]), one
    if joint in ("spine3", "neck"):
        return ax["lat_s"], one
    if joint in ("left_collar", "right_collar"):
        return ax["up"], one
    for side in ("left", "right"):
        if joint == f"{side}_shoulder":
            upper = normalize(p[f"{side}_elbow"] - p[joint])
            if rest:
                return normalize(np.cross(upper, ax["fwd_s"])), one
            fore = normalize(p[f"{side}_wrist"] - p[f"{side}_elbow"])
            return normalize(np.cross(upper, fore)), _bend_weight(upper, fore)
        if joint == f"{side}_hip":
            thigh = normalize(p[f"{side}_knee"] - p[joint])
            if rest:
                return normalize(np.cross(ax["fwd_h"], thigh)), one
            shin = normalize(p[f"{side}_ankle"] - p[f"{side}_knee"])
            return normalize(np.cross(thigh, shin)), _bend_weight(thigh, shin)
    return None


def check_bone_map(bone_map: Mapping[str, str], rig: RigRest) -> dict[str, str]:
    """The map's non-empty entries, checked against the canonical joints and the rig (RetargetError)."""
    bone_map = {j: b for j, b in bone_map.items() if b}
    unknown = [j for j in bone_map if j not in JOINT_INDEX]
    if unknown:
        raise RetargetError(f"bone map names unknown joints: {', '.join(unknown)}")
    missing = [j for j in REQUIRED_JOINTS if j not in bone_map]
    if missing:
        raise RetargetError(f"bone map is missing required joints: {', '.join(missing)}")
    absent = [b for b in bone_map.values() if b not in rig]
    if absent:
        raise RetargetError(f"the armature has no bones named: {', '.join(absent)}")
    if len(set(bone_map.values())) != len(bone_map):
        raise RetargetError("bone map uses a bone for more than one joint")
    return _pelvis_carries_the_trunk(bone_map, rig)


def _pelvis_carries_the_trunk(bone_map: dict[str, str], rig: RigRest) -> dict[str, str]:
    """The pelvis bone carries the whole body (its location is the take's root motion). Where the legs hang from a
    pelvis bone beside the spine (iClone: Hip -> Pelvis -> thighs and Hip -> Waist -> spine), the bone both hang
    from is keyed as the pelvis instead; the bone between it and the thighs stays at rest."""
    pelvis = rig.index(bone_map["pelvis"])
    for joint in ("spine1", "spine2", "spine3", "neck", "head"):
        if joint not in bone_map:
            continue
        above = rig.ancestors(rig.index(bone_map[joint]))
        if pelvis in above:
            continue
        common = next((a for a in [pelvis] + rig.ancestors(pelvis) if a in above), None)
        if common is None or rig.names[common] in bone_map.values():
            raise RetargetError(f"the pelvis bone {bone_map['pelvis']!r} does not carry the {joint} bone "
                                f"{bone_map[joint]!r}: map the pelvis to a bone both hang from")
        pelvis = common
        bone_map = {**bone_map, "pelvis": rig.names[common]}
    return bone_map


def retarget(
    joints: np.ndarray,
    rig: RigRest,
    bone_map: Mapping[str, str],
    options: RetargetOptions | None = None,
    *,
    parent_overrides: Mapping[str, str] | None = None,
    fps: float = _sk.FPS,
) -> RetargetResult:
    """Pose-bone rotations (and the pelvis location) that make ``rig`` follow the source ``joints``.

    joints: (T, 22, 3) metres, Y up (canonical joint order); bone_map: canonical joint name -> bone name (at least
    :data:`REQUIRED_JOINTS`); parent_overrides: bone -> bone it effectively moves with (see
    :meth:`RigRest.with_parents`). Unmapped bones stay at rest.
    """
    options = options or RetargetOptions()
    if options.match not in ("effectors", "directions"):
        raise RetargetError(f"unknown match mode {options.match!r} (use 'effectors' or 'directions')")
    joints = check_joints(joints)
    bone_map = check_bone_map(bone_map, rig)
    rig = rig.with_parents(parent_overrides or {})
    world, scale = place_source(joints, rig, bone_map, options)  # (T, 22, 3)
    solve = _Solve(rig, bone_map, _to_armature(rig, world), scale, options)
    for b in solve.mapped_idx:  # parents before children
        solve.pose_bone(b)
    rotations = np.stack([matrix_to_quat(solve.local_rot[b]) for b in solve.mapped_idx], axis=1)  # (T, K, 4)
    return RetargetResult(
        bones=[rig.names[b] for b in solve.mapped_idx],
        joints=[solve.joint_of[rig.names[b]] for b in solve.mapped_idx],
        rotations=quat_continuity(rotations),
        root_bone=rig.names[solve.pelvis_idx],
        root_location=solve.local_loc[solve.pelvis_idx],
        scale=scale,
        fps=float(fps),
        source_world=world,
        rig=rig,
    )


class _Solve:
    """The state of one retarget: the source in armature space, the rig's rest, and the pose found so far
    (bones are solved parents first; a bone's posed matrix is cached until the pelvis moves)."""

    def __init__(self, rig: RigRest, bone_map: dict[str, str], src: np.ndarray, scale: float,
                 options: RetargetOptions):
        self.rig, self.options = rig, options
        self.T = src.shape[0]
        self.sp = {n: src[:, JOINT_INDEX[n]] for n in JOINT_NAMES}  # source joints, armature space
        self.sp_mapped = {j: self.sp[j] for j in bone_map}
        self.rp = {j: rig.heads[rig.index(b)] for j, b in bone_map.items()}  # rest heads of mapped joints
        self.min_length = 1e-3 * float(leg_length(self.rp))  # heads closer than this count as the same place
        self.bone_of = dict(bone_map)
        self.joint_of = {b: j for j, b in bone_map.items()}
        self.mapped_idx = sorted((rig.index(b) for b in bone_map.values()), key=rig.order.index)
        self.pelvis_idx = rig.index(bone_map["pelvis"])
        if any(i in set(rig.ancestors(self.pelvis_idx)) for i in self.mapped_idx):
            raise RetargetError("the pelvis bone must not be below another mapped bone")
        self.rest = rig.matrices
        self.rest_inv = np.linalg.inv(self.rest)
        self.up = normalize(np.linalg.inv(rig.object_matrix[:3, :3]) @ np.array([0.0, 0.0, 1.0]))  # world Z
        self.units = scale / rig.world_scale()  # armature units per source metre
        self.local_rot: dict[int, np.ndarray] = {}  # bone index -> (T, 3, 3)
        self.local_loc: dict[int, np.ndarray] = {}  # bone index -> (T, 3)
        self.pose_cache: dict[int, np.ndarray] = {}
        self.desired: dict[str, np.ndarray] = {}  # joint -> (T, 3) where its head should go (armature space)
        self.ik_chains = dict(LIMBS)  # two-bone chains: root joint -> (middle, end); the spine's last two added

    def pose(self, b: int) -> np.ndarray:
        """(T, 4, 4) posed armature-space matrix of bone b (ancestors must be solved already)."""
        if b in self.pose_cache:
            return self.pose_cache[b]
        m = np.broadcast_to(self._base(b), (self.T, 4, 4)).copy()
        if b in self.local_loc:
            m[:, :3, 3] += np.einsum("tij,tj->ti", m[:, :3, :3], self.local_loc[b])
        if b in self.local_rot:
            m[:, :3, :3] = m[:, :3, :3] @ self.local_rot[b]
        self.pose_cache[b] = m
        return m

    def carried(self, b: int) -> np.ndarray:
        """(T, 4, 4): where bone b's rest frame is carried by its posed parent (before its own transform)."""
        return np.broadcast_to(self._base(b), (self.T, 4, 4))

    def _base(self, b: int) -> np.ndarray:
        p = self.rig.parents[b]
        return self.rest[b] if p < 0 else self.pose(p) @ (self.rest_inv[p] @ self.rest[b])

    def pose_bone(self, b: int) -> None:
        """Solve bone b: its rotation (aim at its segment's end, twist), and for the pelvis its location."""
        joint = self.joint_of[self.rig.names[b]]
        end = _segment_end(joint, self.bone_of, self.rp, self.min_length)
        C = self.carried(b)
        Crot, head = C[:, :3, :3], C[:, :3, 3]
        if self.options.match == "effectors" and joint in self.ik_chains:
            self.plan_limb(joint, end, head)
        if end is None:
            self.local_rot[b] = np.tile(np.eye(3), (self.T, 1, 1))
        else:
            self.local_rot[b] = np.swapaxes(Crot, -1, -2) @ self.aim(b, joint, end, Crot, head)
        if b == self.pelvis_idx:
            self.place_pelvis(b, joint, Crot)

    def plan_limb(self, joint: str, end: str | None, head: np.ndarray) -> None:
        """Where a two-bone chain starting at ``joint`` puts its middle and end joints (``desired``)."""
        sp, rp = self.sp, self.rp
        mid, eff = self.ik_chains[joint]
        if end != mid or _segment_end(mid, self.bone_of, rp, self.min_length) != eff:
            return
        upper = float(np.linalg.norm(rp[mid] - rp[joint]))
        lower = float(np.linalg.norm(rp[eff] - rp[mid]))
        if eff in self.desired:  # the spine's neck + head: the head's aim point is already known
            goal = self.desired[eff]
            pole = self.desired.get(mid, goal) - head
        elif joint in ("left_hip", "right_hip"):
            # Feet go where the scaled source puts them (no sinking, no sliding); the leg bends to reach.
            goal = self.leg_goal(joint, mid, eff, head, upper + lower)
            pole = sp[mid] - sp[joint]
        else:
            # Hands relative to the shoulder, the source arm scaled to the rig's arm length.
            src_len = np.linalg.norm(sp[mid] - sp[joint], axis=-1) + np.linalg.norm(sp[eff] - sp[mid], axis=-1)
            k = (upper + lower) / np.maximum(src_len, _EPS)
            goal = head + k[:, None] * (sp[eff] - sp[joint])
            pole = sp[mid] - sp[joint]
        self.desired[mid] = two_bone_middle(head, goal, upper, lower, pole)
        self.desired[eff] = goal

    def leg_goal(self, hip: str, knee: str, ankle: str, head: np.ndarray, length: float) -> np.ndarray:
        """(T, 3) where a leg of ``length`` from ``head`` puts its ankle: the scaled source's ankle, but no further
        from the hip, in the leg's own length, than the source's ankle is from its hip. The take is scaled by the
        mean of the rig's legs, so on a rig whose legs differ in length the shorter one could not reach and its
        knee snapped straight; that foot is drawn up the leg instead (it stands as high as its shorter leg
        allows). A longer leg still bends more than the source's: its foot stays on the source's."""
        sp = self.sp
        src_len = np.linalg.norm(sp[knee] - sp[hip], axis=-1) + np.linalg.norm(sp[ankle] - sp[knee], axis=-1)
        reach = length * np.linalg.norm(sp[ankle] - sp[hip], axis=-1) / np.maximum(src_len, _EPS)  # (T,)
        offset = sp[ankle] - head
        dist = np.linalg.norm(offset, axis=-1)
        return head + offset * (np.minimum(dist, reach) / np.maximum(dist, _EPS))[:, None]

    def aim(self, b: int, joint: str, end: str, Crot: np.ndarray, head: np.ndarray) -> np.ndarray:
        """(T, 3, 3) armature-space rotation of bone b: its segment along the desired direction, twisted."""
        rest, sp, rp, options = self.rest, self.sp, self.rp, self.options
        seg_rest = self.rig.heads[self.rig.index(self.bone_of[end])] - self.rig.heads[b]
        v_local = rest[b, :3, :3].T @ normalize(seg_rest)
        a = Crot @ v_local  # (T, 3)
        d = normalize((self.desired[end] - head) if end in self.desired else (sp[end] - sp[joint]))  # (T, 3)
        if options.match == "effectors" and (joint, end) in _FEET:
            # A fixed-length rig foot aimed along the source's ankle -> toe line digs its toe into the floor
            # whenever the source's foot is shorter (generated joints do not keep bone lengths): while the
            # source's toe is down, pitch the foot so the rig's toe stands exactly as high as the source's.
            d = _toe_on_floor(d, head, sp[end], float(np.linalg.norm(seg_rest)), self.up, self.units)
        ref = twist_reference(joint, self.sp_mapped, rest=False) if options.twist else None
        W = rotation_between(a, d, ref[0] if ref is not None else None) @ Crot  # (T, 3, 3)
        if ref is not None:
            W = self._twist(b, joint, W, d, ref, seg_rest)
        if joint == "pelvis" and options.twist and options.match == "effectors":
            # The hips' lateral axis decides the facing and where the legs hang: match it exactly, and the
            # pelvis segment as closely as that allows.
            lat_src = normalize(sp["left_hip"] - sp["right_hip"])
            lat_rest = rest[b, :3, :3].T @ normalize(rp["left_hip"] - rp["right_hip"])
            F_rest = _frame(Crot @ lat_rest, Crot @ v_local)
            W = _frame(lat_src, d) @ np.swapaxes(F_rest, -1, -2) @ Crot
        return W

    def _twist(self, b: int, joint: str, W: np.ndarray, d: np.ndarray, ref, seg_rest: np.ndarray) -> np.ndarray:
        """Turn W about the segment direction d so the bone's side axis follows the source's (``ref``)."""
        h_rest, _ = twist_reference(joint, self.rp, rest=True)
        h_rest = h_rest - np.dot(h_rest, normalize(seg_rest)) * normalize(seg_rest)
        if np.linalg.norm(h_rest) < 1e-6:
            h_rest = any_perpendicular(normalize(seg_rest))
        h_local = self.rest[b, :3, :3].T @ normalize(h_rest)
        h_cur = np.einsum("tij,j->ti", W, h_local)
        h_src, weight = ref
        h_src = h_src - np.sum(h_src * d, -1, keepdims=True) * d
        weight = np.where(np.linalg.norm(h_src, axis=-1) < 1e-3, 0.0, weight)
        return axis_angle_matrix(d, _twist_angles(h_cur, h_src, weight, d)) @ W

    def place_pelvis(self, b: int, joint: str, Crot: np.ndarray) -> None:
        """Move the pelvis so the rig's hip midpoint lands on the scaled source's; in the effector mode also aim
        the spine, neck and head at the source's joints (scaled to the rig's spine length)."""
        sp, rig = self.sp, self.rig
        self.local_loc[b] = np.zeros((self.T, 3))
        self.pose_cache.clear()
        left, right = rig.index(self.bone_of["left_hip"]), rig.index(self.bone_of["right_hip"])
        hips_now = (self.pose(left)[:, :3, 3] + self.pose(right)[:, :3, 3]) / 2
        hips_src = (sp["left_hip"] + sp["right_hip"]) / 2
        self.local_loc[b] = np.einsum("tji,tj->ti", Crot, hips_src - hips_now)  # Crot^T @ delta
        self.pose_cache.clear()
        if self.options.match != "effectors":
            return
        chain = [joint]
        while chain[-1] is not None and chain[-1] != "head":
            chain.append(_segment_end(chain[-1], self.bone_of, self.rp, self.min_length))
        chain = [j for j in chain if j is not None]
        if len(chain) < 2:
            return
        pairs = list(zip(chain[:-1], chain[1:]))
        l_rig = sum(float(np.linalg.norm(self.rp[y] - self.rp[x])) for x, y in pairs)
        l_src = sum(np.linalg.norm(sp[y] - sp[x], axis=-1) for x, y in pairs)
        k = (l_rig / np.maximum(l_src, _EPS))[:, None]
        base = self.pose(b)[:, :3, 3]
        for j in chain[1:]:
            self.desired[j] = base + k * (sp[j] - sp[joint])
        if len(chain) >= 4:  # e.g. chest -> neck -> head: a two-bone chain, so the head lands exactly
            self.ik_chains[chain[-3]] = (chain[-2], chain[-1])


_FEET = {("left_ankle", "left_foot"), ("right_ankle", "right_foot")}
TOE_DOWN_M = (0.03, 0.08)  # source toe height above its lowest (5th percentile): fully planted .. fully lifted


def _toe_on_floor(
    d: np.ndarray, head: np.ndarray, toe: np.ndarray, length: float, up: np.ndarray, units: float
) -> np.ndarray:
    """Foot directions (T, 3) whose end, ``length`` from ``head``, is as high along ``up`` as the source ``toe``
    on frames where that toe is down (blended out as it lifts), keeping the direction's heading.

    d: (T, 3) unit directions aimed along the source foot; head: (T, 3) the rig's ankle; toe: (T, 3) the placed
    source toe; units: armature units per source metre (for the planted / lifted thresholds).
    """
    h_toe = toe @ up  # (T,)
    lo, hi = (m * units for m in TOE_DOWN_M)
    above = h_toe - np.percentile(h_toe, 5)
    w = 1.0 - _smoothstep((above - lo) / (hi - lo))  # 1 planted .. 0 lifted
    want = np.clip((h_toe - head @ up) / max(length, _EPS), -1.0, 1.0)  # vertical component reaching the toe
    vz = (1.0 - w) * (d @ up) + w * want  # (T,)
    flat = d - (d @ up)[:, None] * up  # (T, 3) the heading
    ok = np.linalg.norm(flat, axis=-1) > 1e-6
    out = vz[:, None] * up + np.sqrt(np.clip(1.0 - vz**2, 0.0, 1.0))[:, None] * normalize(flat)
    return np.where(ok[:, None], out, d)


LIMBS = {  # chain root -> (middle joint, effector)
    "left_shoulder": ("left_elbow", "left_wrist"),
    "right_shoulder": ("right_elbow", "right_wrist"),
    "left_hip": ("left_knee", "left_ankle"),
    "right_hip": ("right_knee", "right_ankle"),
}
SPINE_CHAIN = ("pelvis", "spine1", "spine2", "spine3", "neck", "head")


def _frame(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """Orthonormal frames (..., 3, 3): columns = primary, secondary made perpendicular, their cross product."""
    e1 = normalize(primary)
    e2 = secondary - np.sum(secondary * e1, -1, keepdims=True) * e1
    e2 = np.where(np.linalg.norm(e2, axis=-1, keepdims=True) < 1e-9, any_perpendicular(e1), normalize(e2))
    return np.stack([e1, e2, np.cross(e1, e2)], axis=-1)


def two_bone_middle(root: np.ndarray, goal: np.ndarray, upper: float, lower: float, pole: np.ndarray) -> np.ndarray:
    """Where the middle joint of a two-bone chain goes (T, 3) so its end reaches ``goal`` (or points at it when
    out of reach), bending in the plane of root -> goal and ``pole`` (a vector towards the side the joint bends)."""
    v = goal - root
    dist = np.linalg.norm(v, axis=-1)
    u = v / np.maximum(dist, _EPS)[:, None]
    reach = np.clip(dist, abs(upper - lower) + 1e-9, upper + lower)
    cos_a = np.clip((upper**2 + reach**2 - lower**2) / (2 * upper * reach), -1.0, 1.0)
    side = pole - np.sum(pole * u, -1, keepdims=True) * u
    weak = np.linalg.norm(side, axis=-1) < 1e-6
    side = np.where(weak[:, None], any_perpendicular(u), normalize(side))
    return root + upper * (cos_a[:, None] * u + np.sqrt(1 - cos_a**2)[:, None] * side)


def _twist_angles(h_cur: np.ndarray, h_src: np.ndarray, weight: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Twist (T,) about ``d`` turning the bone's reference axis ``h_cur`` onto the source's ``h_src``.

    Where the source reference is trustworthy (weight 1) it is followed; where it is not (a straight elbow or knee
    has no hinge axis), the reference keeps the direction it had the frame before (carried along as the segment
    turns), so the limb never snaps or flips; in between the two directions are blended.
    """
    h_cur = normalize(h_cur)
    valid = np.linalg.norm(h_src, axis=-1) > 1e-6
    h_src = normalize(h_src)
    if np.all(weight >= 1.0) and np.all(valid):
        return signed_angle(h_cur, h_src, d)
    T = len(d)
    theta = np.empty(T)
    confident = np.nonzero((weight > 0.5) & valid)[0]
    prev = h_src[confident[0]] if len(confident) else h_cur[0]
    for t in range(T):
        dt = d[t]
        carried = prev - np.dot(prev, dt) * dt
        n = np.linalg.norm(carried)
        carried = carried / n if n > 1e-6 else h_cur[t]
        w = float(weight[t]) if valid[t] else 0.0
        goal = w * h_src[t] + (1 - w) * carried
        n = np.linalg.norm(goal)
        goal = goal / n if n > 1e-6 else (h_src[t] if w >= 0.5 else carried)
        theta[t] = np.arctan2(np.dot(dt, np.cross(h_cur[t], goal)), np.dot(h_cur[t], goal))
        prev = goal
    return theta


def quat_continuity(q: np.ndarray) -> np.ndarray:
    """Flip signs along axis 0 so consecutive quaternions (T, ..., 4) lie in the same hemisphere (no flips)."""
    q = np.array(q, dtype=np.float64, copy=True)
    if q.shape[0] < 2:
        return q
    step = np.where(np.sum(q[1:] * q[:-1], axis=-1) < 0, -1.0, 1.0)  # (T-1, ...) flip relative to the previous
    sign = np.concatenate([np.ones_like(step[:1]), np.cumprod(step, axis=0)], axis=0)
    return q * sign[..., None]
