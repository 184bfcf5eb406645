"""Where a take's travel goes when it leaves Blender for a game engine (numpy only).

A take as Blender plays it moves the hips: they carry the character's travel over the ground, and its turning.
Game engines want one of three things:

- ``object``: nothing changes; the hips carry the travel (the armature object is the character's root).
- ``in-place``: the travel is taken off the whole body and kept nowhere (the engine's own locomotion moves the
  character); with ``yaw`` the turning too. The hips keep their own sway: only the smoothed ground path goes.
- ``root-bone``: a root bone on the ground under the character carries the travel (with ``yaw`` the turning too)
  and the body hangs from it, so root and hips together put every bone exactly where it was.

The travel is the hips' ground path smoothed over about a gait cycle (a Gaussian of ``smooth_s`` seconds, 0.4),
extended past the take's ends by point reflection so that the path starts and ends on the hips (a take in place
keeps its first frame and returns to its start); a loop is extended by its own cycle instead (the cycle repeated,
moved by the loop's travel and turned by its turn), so a looped take's sway is periodic and its seam seamless.
The turning is the heading of the hips' most level axis, smoothed the same way.

Everything works on armature-space 4x4 matrices (``pose_bone.matrix`` in Blender: columns X, Y, Z, head), with
``up`` the world's up direction in armature space.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mld_core.rig.retarget import axis_angle_matrix, matrix_to_quat, normalize, quat_to_matrix

MODES = ("object", "in-place", "root-bone")
DEFAULT_SMOOTH_S = 0.4


@dataclass(frozen=True)
class RootMotion:
    """How a take's travel is exported: ``mode`` (one of :data:`MODES`), ``yaw`` (the turning goes with the
    travel), ``smooth_s`` (the Gaussian's sigma in seconds over which the hips' path is smoothed)."""

    mode: str = "object"
    yaw: bool = False
    smooth_s: float = DEFAULT_SMOOTH_S

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"root motion must be one of {', '.join(MODES)}; got {self.mode!r}")
        if not (math.isfinite(self.smooth_s) and self.smooth_s > 0):
            raise ValueError(f"the root path's smoothing must be a positive number of seconds; got {self.smooth_s}")


# --------------------------------------------------------------------------------------------------------------
# The ground: two level axes and up.


def ground_axes(up: np.ndarray) -> np.ndarray:
    """(3, 3) with columns e1, e2 (level, orthonormal) and ``up`` (normalised)."""
    up = normalize(np.asarray(up, np.float64))
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = normalize(helper - up * (helper @ up))
    return np.stack([e1, np.cross(up, e1), up], axis=1)


def level_heading(rotations: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(T,) unwrapped heading (radians about ``up``) of the bone axis that stays most level over the take.

    rotations: (T, 3, 3) armature-space rotations of one bone. The axis chosen (X, Y or Z of the bone) is the one
    whose smallest level length over the take is largest: a pelvis's left-right axis stays level through a bow,
    its forward axis does not."""
    axes = ground_axes(up)
    level = np.einsum("tij,ik->tkj", rotations, axes[:, :2])  # (T, 2 ground coords, 3 bone axes)
    best = int(np.argmax(np.linalg.norm(level, axis=1).min(axis=0)))
    return np.unwrap(np.arctan2(level[:, 1, best], level[:, 0, best]))


# --------------------------------------------------------------------------------------------------------------
# Smoothing past the ends.


def _gaussian(sigma: float) -> np.ndarray:
    radius = max(1, int(math.ceil(3.0 * sigma)))
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def _reflected(path: np.ndarray, heading: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(path (T + 2r, 2), heading (T + 2r,)) extended by point reflection through the first and last frames."""
    n = len(path)
    before = np.minimum(np.arange(radius, 0, -1), n - 1)  # frames r .. 1 mirrored to -r .. -1
    after = np.maximum(n - 1 - np.arange(1, radius + 1), 0)
    path = np.concatenate([2 * path[0] - path[before], path, 2 * path[-1] - path[after]])
    heading = np.concatenate([2 * heading[0] - heading[before], heading, 2 * heading[-1] - heading[after]])
    return path, heading


def _cycled(path: np.ndarray, heading: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """The same, extended by the loop's own cycle: the last frame repeats the first, so a cycle is ``T - 1`` frames
    and frame ``t + T - 1`` is frame ``t`` carried by the loop's motion (turned by its turn about the first frame,
    then moved onto the last)."""
    n = len(path)
    turn = heading[-1] - heading[0]
    c, s = math.cos(turn), math.sin(turn)
    cycle = np.eye(3)  # the loop's motion as a 2-D rigid transform (homogeneous)
    cycle[:2, :2] = [[c, -s], [s, c]]
    cycle[:2, 2] = path[-1] - cycle[:2, :2] @ path[0]
    index = np.arange(-radius, n + radius)
    cycles, frame = np.divmod(index, n - 1)  # index = cycles * (T - 1) + frame
    out = np.empty((len(index), 2))
    for k in np.unique(cycles):
        carry = np.linalg.matrix_power(cycle if k >= 0 else np.linalg.inv(cycle), abs(int(k)))
        rows = cycles == k
        out[rows] = path[frame[rows]] @ carry[:2, :2].T + carry[:2, 2]
    return out, heading[frame] + turn * cycles


def smooth_path(path: np.ndarray, heading: np.ndarray, sigma_frames: float, loop: bool = False
                ) -> tuple[np.ndarray, np.ndarray]:
    """The ground path (T, 2) and heading (T,) low-passed by a Gaussian of ``sigma_frames``, extended past the
    ends by point reflection (the smoothed path starts and ends on the raw one) or, for a ``loop``, by its cycle."""
    path = np.asarray(path, np.float64)
    heading = np.asarray(heading, np.float64)
    if len(path) < 3:
        return path.copy(), heading.copy()
    kernel = _gaussian(sigma_frames)
    radius = len(kernel) // 2
    ext_path, ext_heading = (_cycled if loop else _reflected)(path, heading, radius)
    smooth = np.stack([np.convolve(ext_path[:, k], kernel, mode="valid") for k in range(2)], axis=-1)  # (T, 2)
    return smooth, np.convolve(ext_heading, kernel, mode="valid")


# --------------------------------------------------------------------------------------------------------------
# Root frames and the three modes.


def root_frames(hips: np.ndarray, up: np.ndarray, fps: float, *, yaw: bool, loop: bool = False,
                smooth_s: float = DEFAULT_SMOOTH_S) -> np.ndarray:
    """(T, 4, 4) the character's root on the ground at each frame, in armature space: at the smoothed ground
    point under the hips, turned (with ``yaw``) by the smoothed heading's change since frame 0 (else not turned).

    hips: (T, 4, 4) armature-space matrices of the hips bone; fps: frames per second of the take."""
    hips = np.asarray(hips, np.float64)
    axes = ground_axes(up)
    path = hips[:, :3, 3] @ axes[:, :2]  # (T, 2) ground coordinates
    heading = level_heading(hips[:, :3, :3], up)
    path, heading = smooth_path(path, heading, smooth_s * fps, loop)
    frames = np.tile(np.eye(4), (len(hips), 1, 1))
    frames[:, :3, 3] = path @ axes[:, :2].T
    if yaw:
        frames[:, :3, :3] = axis_angle_matrix(np.broadcast_to(axes[:, 2], (len(hips), 3)), heading - heading[0])
    return frames


def in_root_frame(frames: np.ndarray, matrices: np.ndarray) -> np.ndarray:
    """(T, K, 4, 4) armature-space ``matrices`` (T, K, 4, 4) seen from the root ``frames`` (T, 4, 4)."""
    return np.linalg.inv(frames)[:, None] @ matrices


@dataclass
class RootSplit:
    """A take's top bones (no parent) after the split: ``top`` (T, K, 4, 4) armature-space matrices as exported,
    relative to ``root`` (T, 4, 4) when there is a root bone (None otherwise)."""

    top: np.ndarray
    root: np.ndarray | None


def split_root(top: np.ndarray, frames: np.ndarray, mode: str) -> RootSplit:
    """The top bones' matrices (T, K, 4, 4) as one of :data:`MODES` exports them, given the root ``frames``:
    ``object`` unchanged; ``in-place`` moved by the root's motion since frame 0 backwards (frame 0 unchanged);
    ``root-bone`` relative to the root, which carries the motion (root @ top gives back the input exactly)."""
    if mode == "object":
        return RootSplit(np.asarray(top, np.float64).copy(), None)
    local = in_root_frame(frames, np.asarray(top, np.float64))
    if mode == "in-place":
        return RootSplit(frames[0] @ local, None)
    if mode == "root-bone":
        return RootSplit(local, np.asarray(frames, np.float64).copy())
    raise ValueError(f"root motion must be one of {', '.join(MODES)}; got {mode!r}")


def ground_travel(positions: np.ndarray, up: np.ndarray) -> float:
    """Net travel over the ground (first frame to last) of ``positions`` (T, 3), in their units."""
    axes = ground_axes(up)
    step = (positions[-1] - positions[0]) @ axes[:, :2]
    return float(np.linalg.norm(step))


# --------------------------------------------------------------------------------------------------------------
# Loops: the last frame repeats the first.


def _blend_rotations(rot: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(T, K, 3, 3) rotations each turned by a growing share ``weights`` (T,) of what turns its last frame onto its
    first: frame 0 unchanged, the last equal to the first."""
    delta = np.swapaxes(rot[-1], -1, -2) @ rot[0]  # (K, 3, 3): last -> first, in the bone's own frame
    q = matrix_to_quat(delta)  # w >= 0: the short way
    angle = 2.0 * np.arctan2(np.linalg.norm(q[:, 1:], axis=-1), q[:, 0])  # (K,)
    axis = np.where(np.linalg.norm(q[:, 1:], axis=-1, keepdims=True) > 1e-12, q[:, 1:], np.array([1.0, 0, 0]))
    turn = axis_angle_matrix(np.broadcast_to(axis, rot.shape[:2] + (3,)), weights[:, None] * angle[None])
    return rot @ turn


def close_loop(matrices: np.ndarray) -> np.ndarray:
    """A looped take's last frame made equal to its first, the difference spread evenly over the take.

    matrices: (T, B, 4, 4) every bone seen from the root (armature-space poses in the root's frame), so each joint
    moves by at most its own gap at the seam. Frame 0 is unchanged, frame T-1 becomes frame 0."""
    m = np.array(matrices, np.float64, copy=True)
    weights = np.linspace(0.0, 1.0, len(m))
    if m.shape[1]:
        m[..., :3, :3] = _blend_rotations(m[..., :3, :3], weights)
        m[..., :3, 3] += weights[:, None, None] * (m[0, :, :3, 3] - m[-1, :, :3, 3])[None]
    return m


def seam_gap(heads: np.ndarray, rotations: np.ndarray) -> tuple[float, float]:
    """(largest head distance, largest rotation angle in degrees) between a take's last and first frames.

    heads: (T, B, 3); rotations: (T, B, 3, 3), both in the frame the seam is judged in."""
    if not heads.shape[1]:
        return 0.0, 0.0
    distance = float(np.linalg.norm(heads[-1] - heads[0], axis=-1).max())
    q = matrix_to_quat(np.swapaxes(rotations[-1], -1, -2) @ rotations[0])  # (B, 4): the angle from its quaternion,
    angle = 2.0 * np.arctan2(np.linalg.norm(q[:, 1:], axis=-1), np.abs(q[:, 0]))  # not arccos (exact near 0)
    return distance, float(np.degrees(angle).max())


def quaternions(rotations: np.ndarray) -> np.ndarray:
    """(T, ..., 3, 3) -> (T, ..., 4) w-first, sign-continuous along time (keys without 360-degree flips)."""
    from mld_core.rig.retarget import quat_continuity

    return quat_continuity(matrix_to_quat(rotations))


def rotation_matrices(quats: np.ndarray) -> np.ndarray:
    return quat_to_matrix(quats)
