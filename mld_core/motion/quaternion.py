"""Small quaternion and 6D-rotation helpers (w, x, y, z; Hamilton product; active rotations).

Every function takes numpy arrays or torch tensors of shape (..., 4) / (..., 3) / (..., 3, 3) / (..., 6)
and returns the same kind; the torch versions are differentiable and run on any device.
"""

from __future__ import annotations

import numpy as np
import torch

_EPS = 1e-12


def _stack(parts, like):
    return torch.stack(parts, dim=-1) if isinstance(like, torch.Tensor) else np.stack(parts, axis=-1)


def _sqrt(x):
    return torch.sqrt(x) if isinstance(x, torch.Tensor) else np.sqrt(x)


def _where(cond, a, b):
    return torch.where(cond, a, b) if isinstance(cond, torch.Tensor) else np.where(cond, a, b)


def _broadcast(a, b):
    if isinstance(a, torch.Tensor):
        return tuple(torch.broadcast_shapes(a.shape[:-1], b.shape[:-1]))
    return np.broadcast_shapes(a.shape[:-1], b.shape[:-1])


def _expand(x, lead):
    if isinstance(x, torch.Tensor):
        return x.expand(*lead, x.shape[-1])
    return np.broadcast_to(x, lead + (x.shape[-1],))


def dot(a, b):
    return (a * b).sum(-1)


def cross(a, b):
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return _stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], ax + bx)


def normalize(v):
    return v / _sqrt(dot(v, v))[..., None]


def qnormalize(q):
    return normalize(q)


def qinv(q):
    """Conjugate (= inverse for unit quaternions)."""
    return _stack([q[..., 0], -q[..., 1], -q[..., 2], -q[..., 3]], q)


def qmul(q, r):
    """Hamilton product q * r (apply r first, then q)."""
    w1, x1, y1, z1 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    w2, x2, y2, z2 = r[..., 0], r[..., 1], r[..., 2], r[..., 3]
    return _stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        w1 * w2,
    )


def qrot(q, v):
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4); leading shapes broadcast."""
    lead = _broadcast(q, v)
    q, v = _expand(q, lead), _expand(v, lead)
    u = q[..., 1:]
    uv = cross(u, v)
    uuv = cross(u, uv)
    return v + 2.0 * (q[..., :1] * uv + uuv)


def turn_about_y(half_angle: np.ndarray, v: np.ndarray) -> np.ndarray:
    """qrot((cos a, 0, sin a, 0), v) for numpy half-angles a (...,) and vectors v (..., 3), leading shapes
    broadcasting: a turn by 2a about +Y written out, a few operations where qrot takes dozens (a take's facing
    rotations are all of this kind)."""
    c, s = np.cos(2.0 * half_angle), np.sin(2.0 * half_angle)
    x, z = v[..., 0], v[..., 2]
    return np.stack(np.broadcast_arrays(x * c + z * s, v[..., 1], z * c - x * s), axis=-1)


def qbetween(u, v):
    """Shortest-arc rotation taking direction u to direction v (w >= 0).

    For opposite directions it turns by 180 degrees about an axis perpendicular to u.
    """
    lead = _broadcast(u, v)
    u, v = _expand(u, lead), _expand(v, lead)
    w = _sqrt(dot(u, u) * dot(v, v)) + dot(u, v)
    axis = cross(u, v)
    q = _stack([w, axis[..., 0], axis[..., 1], axis[..., 2]], w)
    norm2 = dot(q, q)
    degenerate = norm2 < _EPS * (dot(u, u) * dot(v, v) + _EPS)
    # Fallback axis: u x X, or u x Z when u is along X.
    ex = _stack([w * 0 + 1, w * 0, w * 0], w)
    ez = _stack([w * 0, w * 0, w * 0 + 1], w)
    use_z = (u[..., 0] ** 2) > 0.9 * dot(u, u)
    perp = cross(u, _where(use_z[..., None], ez, ex))
    q_flip = _stack([w * 0, perp[..., 0], perp[..., 1], perp[..., 2]], w)
    q = _where(degenerate[..., None], q_flip, q)
    return qnormalize(q)


def qpositive(q):
    """The same rotations with w >= 0."""
    return _where((q[..., :1] < 0), -q, q)


def qfix(q):
    """Numpy: flip signs along axis 0 (time) so consecutive quaternions have a positive dot product."""
    q = np.array(q, copy=True)
    flips = np.cumsum(dot(q[1:], q[:-1]) < 0, axis=0) % 2 == 1
    q[1:][flips] *= -1
    return q


def yaw_quat(angle):
    """Rotation by `angle` radians about +Y: (..., ) -> (..., 4)."""
    half = angle * 0.5
    if isinstance(angle, torch.Tensor):
        c, s = torch.cos(half), torch.sin(half)
    else:
        c, s = np.cos(half), np.sin(half)
    return _stack([c, s * 0, s, s * 0], c)


def quat_to_matrix(q):
    """(..., 4) -> (..., 3, 3)."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    two_s = 2.0 / dot(q, q)
    rows = [
        1 - two_s * (y * y + z * z), two_s * (x * y - z * w), two_s * (x * z + y * w),
        two_s * (x * y + z * w), 1 - two_s * (x * x + z * z), two_s * (y * z - x * w),
        two_s * (x * z - y * w), two_s * (y * z + x * w), 1 - two_s * (x * x + y * y),
    ]
    return _stack(rows, w).reshape(tuple(q.shape[:-1]) + (3, 3))


def matrix_to_quat(m):
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions with w >= 0 (numerically stable branch)."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # 4*q_i^2 for each component, then pick the largest for the division.
    cands = [
        _stack([1 + m00 + m11 + m22, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                m[..., 1, 0] - m[..., 0, 1]], m00),
        _stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0],
                m[..., 0, 2] + m[..., 2, 0]], m00),
        _stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22,
                m[..., 1, 2] + m[..., 2, 1]], m00),
        _stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                1 - m00 - m11 + m22], m00),
    ]
    diag = _stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], m00)
    if isinstance(m, torch.Tensor):
        best = diag.argmax(-1)
        stacked = torch.stack(cands, dim=-2)  # (..., 4, 4)
        q = torch.gather(stacked, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    else:
        best = diag.argmax(-1)
        stacked = np.stack(cands, axis=-2)  # (..., 4, 4)
        q = np.take_along_axis(stacked, best[..., None, None], axis=-2)[..., 0, :]
    return qpositive(qnormalize(q))


def matrix_to_cont6d(m):
    """(..., 3, 3) -> (..., 6): first column then second column (HumanML3D's layout)."""
    if isinstance(m, torch.Tensor):
        return torch.cat([m[..., :, 0], m[..., :, 1]], dim=-1)
    return np.concatenate([m[..., :, 0], m[..., :, 1]], axis=-1)


def quat_to_cont6d(q):
    return matrix_to_cont6d(quat_to_matrix(q))


def cont6d_to_matrix(d6):
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt: x = a/|a|, z = x cross b normalised, y = z cross x."""
    x = normalize(d6[..., 0:3])
    z = normalize(cross(x, d6[..., 3:6]))
    y = cross(z, x)
    if isinstance(d6, torch.Tensor):
        return torch.stack([x, y, z], dim=-1)
    return np.stack([x, y, z], axis=-1)


def cont6d_to_quat(d6):
    return matrix_to_quat(cont6d_to_matrix(d6))


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Numpy: spherical interpolation of unit quaternions (..., 4) along the shorter arc; t (...,)."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    cos = dot(q0, q1)[..., None]
    q1 = np.where(cos < 0, -q1, q1)
    cos = np.abs(cos)
    theta = np.arccos(np.clip(cos, -1.0, 1.0))
    sin = np.sin(theta)
    small = sin < 1e-6
    safe = np.where(small, 1.0, sin)
    w0 = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(small, t, np.sin(t * theta) / safe)
    return normalize(w0 * q0 + w1 * q1)


def resampled_frames(n_in: int, fps_in: float, fps_out: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lo, hi, w), each (n_out,): the input frames either side of each output frame and the weight of ``hi``, for
    resampling ``n_in`` frames from fps_in to fps_out, keeping frame 0 and covering the same duration."""
    if fps_in <= 0 or fps_out <= 0:
        raise ValueError(f"frame rates must be positive, got {fps_in} -> {fps_out}")
    n_out = int(np.floor((n_in - 1) * fps_out / fps_in + 1e-9)) + 1
    t = np.arange(n_out) * (fps_in / fps_out)  # positions in input frames
    lo = np.clip(np.floor(t).astype(int), 0, n_in - 1)
    return lo, np.clip(lo + 1, 0, n_in - 1), t - lo


def resample_quaternions(quats: np.ndarray, root: np.ndarray, fps_in: float, fps_out: float):
    """Resample local quaternions (T, J, 4) by slerp and root positions (T, 3) linearly from fps_in to
    fps_out, keeping frame 0 and covering the same duration. Returns (quats, root) in the input dtypes."""
    quats, root = np.asarray(quats), np.asarray(root)
    lo, hi, w = resampled_frames(len(quats), fps_in, fps_out)
    n_out = len(w)
    q = slerp(quats[lo], quats[hi], np.broadcast_to(w[:, None], (n_out, quats.shape[1])))
    r = root[lo] * (1 - w[:, None]) + root[hi] * w[:, None]
    return q.astype(quats.dtype), r.astype(root.dtype)
