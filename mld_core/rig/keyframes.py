"""Keys an animator can edit (numpy only, no bpy): resampling, sign continuity, Euler output, key reduction that
holds for the curve Blender will draw, and foot locking.

Interpolation model for key reduction: every kept key is a Bezier key with **auto-clamped** handles (Blender's
default for new keys, ``handle_left_type = handle_right_type = 'AUTO_CLAMPED'``), F-curve extrapolation constant,
and the F-curve's ``auto_smoothing = 'NONE'`` (Blender 5.0 gives new F-curves 'CONT_ACCEL' from the preferences:
whoever writes the keys must set 'NONE', see ``BakedKeys.auto_smoothing``). :func:`bezier_auto_clamped`
reproduces Blender's handle computation (``BKE_nurb_handle_calc`` for F-curves: handles at 0.3904 of the
neighbouring key interval, slope the mean of the two neighbouring secants, flat at extremes and at the first and
last key, clamped so a handle never passes a neighbour's value) and its evaluation (solving the cubic for the
frame), so the error bound checked here is the bound on what Blender plays at every scene frame (checked against
Blender 5.0.1 to float precision). ``interpolation="LINEAR"`` is available too.

Error metrics: quaternion channels (4 curves keyed together) by the rotation angle between the curve's value,
normalised as Blender does, and the original; Euler channels (3 curves) by the rotation angle too; locations by
the Euclidean distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mld_core.rig import bone_maps as bm
from mld_core.rig import retarget as rt

_EPS = 1e-12
HANDLE_FACTOR = 1.0 / 2.5614  # Blender: handle length = interval / 2.5614 for F-curve auto handles


# --------------------------------------------------------------------------------------------------------------
# Resampling and continuity.


def resample_positions(n_frames: int, fps_in: float, fps_out: float) -> np.ndarray:
    """Fractional source frame of each output frame covering the same duration (output frame k at k / fps_out)."""
    if n_frames < 1:
        raise ValueError("no frames to resample")
    if fps_in <= 0 or fps_out <= 0:
        raise ValueError("frame rates must be positive")
    duration = (n_frames - 1) / fps_in
    count = int(math.floor(duration * fps_out + 1e-6)) + 1
    return np.minimum(np.arange(count) * (fps_in / fps_out), n_frames - 1)


def resample_linear(values: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(T, ...) values linearly interpolated at fractional frames ``positions`` (N,) -> (N, ...)."""
    values = np.asarray(values, dtype=np.float64)
    lo = np.clip(np.floor(positions).astype(np.int64), 0, len(values) - 1)
    hi = np.minimum(lo + 1, len(values) - 1)
    w = (positions - lo).reshape((-1,) + (1,) * (values.ndim - 1))
    return values[lo] * (1 - w) + values[hi] * w


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Shortest-path spherical interpolation of unit quaternions (..., 4) at ``t`` (...)."""
    q0 = rt.normalize(np.asarray(q0, dtype=np.float64))
    q1 = rt.normalize(np.asarray(q1, dtype=np.float64))
    dot = np.sum(q0 * q1, -1)
    q1 = np.where(dot[..., None] < 0, -q1, q1)
    dot = np.abs(dot)
    t = np.asarray(t, dtype=np.float64)[..., None]
    theta = np.arccos(np.clip(dot, -1.0, 1.0))[..., None]
    sin = np.sin(theta)
    near = sin < 1e-6
    a = np.where(near, 1 - t, np.sin((1 - t) * theta) / np.where(near, 1, sin))
    b = np.where(near, t, np.sin(t * theta) / np.where(near, 1, sin))
    return rt.normalize(a * q0 + b * q1)


def resample_quaternions(quats: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(T, ..., 4) quaternions slerped at fractional frames ``positions`` (N,) -> (N, ..., 4), sign-continuous."""
    quats = quat_continuity(quats)
    lo = np.clip(np.floor(positions).astype(np.int64), 0, len(quats) - 1)
    hi = np.minimum(lo + 1, len(quats) - 1)
    w = (positions - lo).reshape((-1,) + (1,) * (quats.ndim - 2))
    return quat_continuity(slerp(quats[lo], quats[hi], np.broadcast_to(w, quats[lo].shape[:-1])))


def quat_continuity(q: np.ndarray) -> np.ndarray:
    """Flip quaternion signs along axis 0 so neighbours lie in the same hemisphere: no 360-degree flips."""
    return rt.quat_continuity(q)


# --------------------------------------------------------------------------------------------------------------
# Euler angles (Blender's convention: order "XYZ" applies X first, R = Rz @ Ry @ Rx).

EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


def _axis_rot(axis: int, angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros(np.shape(angle) + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    m[..., axis, axis] = 1
    m[..., i, i] = c
    m[..., j, j] = c
    m[..., i, j] = -s
    m[..., j, i] = s
    return m


def euler_to_matrix(euler: np.ndarray, order: str = "XYZ") -> np.ndarray:
    """(..., 3) angles (radians, per axis X, Y, Z as Blender stores them) -> (..., 3, 3)."""
    euler = np.asarray(euler, dtype=np.float64)
    m = np.broadcast_to(np.eye(3), euler.shape[:-1] + (3, 3))
    for ch in order:  # first letter applied first: R = R_last @ ... @ R_first
        a = "XYZ".index(ch)
        m = _axis_rot(a, euler[..., a]) @ m
    return m


def matrix_to_euler(m: np.ndarray, order: str = "XYZ") -> np.ndarray:
    """(..., 3, 3) -> (..., 3) angles in (-pi, pi] (per axis X, Y, Z), one of the two solutions."""
    if order not in EULER_ORDERS:
        raise ValueError(f"unknown Euler order {order!r}")
    m = np.asarray(m, dtype=np.float64)
    i, j, k = ("XYZ".index(c) for c in order)  # R = R_k(c) R_j(b) R_i(a)
    parity = 1.0 if (j - i) % 3 == 1 else -1.0
    # For R = Rk Rj Ri: m[k, i] = -parity * sin(b) ...
    sb = -parity * m[..., k, i]
    b = np.arcsin(np.clip(sb, -1.0, 1.0))
    cb = np.cos(b)
    a = np.arctan2(parity * m[..., k, j], m[..., k, k])
    c = np.arctan2(parity * m[..., j, i], m[..., i, i])
    gimbal = cb < 1e-9
    if np.any(gimbal):  # lock: put everything in the first angle
        a_g = np.arctan2(-parity * m[..., j, k], m[..., j, j])
        a = np.where(gimbal, a_g, a)
        c = np.where(gimbal, 0.0, c)
    out = np.empty(m.shape[:-2] + (3,))
    out[..., i], out[..., j], out[..., k] = a, b, c
    return out


def euler_continuity(euler: np.ndarray, order: str = "XYZ") -> np.ndarray:
    """Along axis 0, pick for each frame the equivalent Euler triple (2-pi wraps and the alternate solution)
    closest to the previous frame's, like Blender's ``Euler.make_compatible``: curves without jumps."""
    e = np.array(euler, dtype=np.float64, copy=True)
    i, j, k = ("XYZ".index(c) for c in order)
    for t in range(1, e.shape[0]):
        prev = e[t - 1]
        cur = e[t]
        alt = cur.copy()
        alt[..., i] += np.pi
        alt[..., j] = np.pi - alt[..., j]
        alt[..., k] += np.pi
        best = []
        for cand in (cur, alt):
            cand = prev + rt.wrap_angle(cand - prev)
            best.append(cand)
        d0 = np.sum((best[0] - prev) ** 2, -1)
        d1 = np.sum((best[1] - prev) ** 2, -1)
        e[t] = np.where((d1 < d0)[..., None], best[1], best[0])
    return e


def quats_to_euler(quats: np.ndarray, order: str = "XYZ") -> np.ndarray:
    """(T, ..., 4) quaternions -> (T, ..., 3) continuous Euler angles (radians)."""
    return euler_continuity(matrix_to_euler(rt.quat_to_matrix(quats), order), order)


# --------------------------------------------------------------------------------------------------------------
# Blender's auto-clamped Bezier F-curves.


def auto_clamped_handles(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Handles of keys (x (K,), y (K, C)) as Blender computes them for AUTO_CLAMPED F-curve keys.

    Returns (left_x (K,), left_y (K, C), right_x (K,), right_y (K, C)).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    K = len(x)
    lx, rx = x.copy(), x.copy()
    ly, ry = y.copy(), y.copy()
    if K < 2:
        return lx, ly, rx, ry
    # Neighbours; the first and last keys mirror their only neighbour (prev = 2 * cur - next).
    px = np.concatenate([[2 * x[0] - x[1]], x[:-1]])
    py = np.concatenate([2 * y[:1] - y[1:2], y[:-1]])
    nx = np.concatenate([x[1:], [2 * x[-1] - x[-2]]])
    ny = np.concatenate([y[1:], 2 * y[-1:] - y[-2:-1]])
    len_a = x - px  # F-curves measure the intervals along x only
    len_b = nx - x
    len_a = np.where(len_a == 0, 1.0, len_a)
    len_b = np.where(len_b == 0, 1.0, len_b)
    tx = (nx - x) / len_b + (x - px) / len_a  # = 2
    ty = (ny - y) / len_b[:, None] + (y - py) / len_a[:, None]  # sum of the two secant slopes
    length = tx * 2.5614
    la = np.minimum(len_a, 5.0 * len_b)
    lb = np.minimum(len_b, 5.0 * la)
    fa = la / length
    fb = lb / length
    lx = x - tx * fa
    rx = x + tx * fb
    ly = y - ty * fa[:, None]
    ry = y + ty * fb[:, None]
    # Clamping (HD_AUTO_ANIM) for keys with both neighbours.
    inner = np.zeros(K, dtype=bool)
    inner[1:-1] = True
    yd1 = py - y
    yd2 = ny - y
    extreme = ((yd1 <= 0) & (yd2 <= 0)) | ((yd1 >= 0) & (yd2 >= 0))
    ly_new = np.where(extreme, y, ly)
    ry_new = np.where(extreme, y, ry)
    left_v = extreme.copy()
    right_v = extreme.copy()
    rising = yd1 <= 0  # previous key below (or level with) this one
    clamp_l = ~extreme & np.where(rising, py > ly, py < ly)
    clamp_r = ~extreme & np.where(rising, ny < ry, ny > ry)
    ly_new = np.where(clamp_l, py, ly_new)
    ry_new = np.where(clamp_r, ny, ry_new)
    left_v |= clamp_l
    right_v |= clamp_r
    # Keep the handles aligned: the violated side decides the slope (left first, as Blender does).
    h1x = (lx - x)[:, None]
    h2x = (x - rx)[:, None]
    ry_al = np.where(left_v, y + (y - ly_new) / h1x * h2x, ry_new)
    ly_al = np.where(~left_v & right_v, y + (y - ry_new) / h2x * h1x, ly_new)
    ly = np.where(inner[:, None], ly_al, ly)
    ry = np.where(inner[:, None], ry_al, ry)
    # First and last keys: flat handles (auto handles with constant extrapolation).
    ly[0], ry[0] = y[0], y[0]
    ly[-1], ry[-1] = y[-1], y[-1]
    return lx, ly, rx, ry


def _bezier_param(x0, x1, x2, x3, f):
    """Parameter u in [0, 1] of the cubic Bezier x(u) (control points x0..x3, monotonic) where x(u) = f."""
    lo = np.zeros_like(f)
    hi = np.ones_like(f)
    u = np.clip((f - x0) / np.maximum(x3 - x0, _EPS), 0.0, 1.0)
    for _ in range(12):  # Newton, guarded by bisection bounds
        a = 1 - u
        xu = a**3 * x0 + 3 * a * a * u * x1 + 3 * a * u * u * x2 + u**3 * x3
        dx = 3 * a * a * (x1 - x0) + 6 * a * u * (x2 - x1) + 3 * u * u * (x3 - x2)
        lo = np.where(xu < f, u, lo)
        hi = np.where(xu > f, u, hi)
        ok = np.abs(dx) > _EPS
        u_new = u - np.where(ok, (xu - f) / np.where(ok, dx, 1.0), 0.0)
        bad = (u_new < lo) | (u_new > hi)
        u = np.where(xu == f, u, np.where(bad, (lo + hi) / 2, u_new))
        if np.max(np.abs(xu - f), initial=0.0) < 1e-10:
            break
    return u


def bezier_auto_clamped(key_x: np.ndarray, key_y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Evaluate the auto-clamped Bezier F-curve through keys (key_x (K,), key_y (K, C)) at frames x (N,) -> (N, C).

    Outside the keys the curve is constant (Blender's default extrapolation).
    """
    key_x = np.asarray(key_x, dtype=np.float64)
    key_y = np.asarray(key_y, dtype=np.float64)
    squeeze = key_y.ndim == 1
    if squeeze:
        key_y = key_y[:, None]
    x = np.asarray(x, dtype=np.float64)
    if len(key_x) == 1:
        out = np.broadcast_to(key_y[0], (len(x), key_y.shape[1])).copy()
        return out[:, 0] if squeeze else out
    lx, ly, rx, ry = auto_clamped_handles(key_x, key_y)
    seg = np.clip(np.searchsorted(key_x, x, side="right") - 1, 0, len(key_x) - 2)
    x0, x3 = key_x[seg], key_x[seg + 1]
    x1, x2 = rx[seg], lx[seg + 1]
    # Blender shortens handles that would overlap within a segment (BKE_fcurve_correct_bezpart).
    h1 = x1 - x0
    h2 = x3 - x2
    total = h1 + h2
    fac = np.where(total > (x3 - x0), (x3 - x0) / np.maximum(total, _EPS), 1.0)
    x1 = x0 + h1 * fac
    x2 = x3 - h2 * fac
    y0, y3 = key_y[seg], key_y[seg + 1]
    y1 = y0 + (ry[seg] - y0) * fac[:, None]
    y2 = y3 - (y3 - ly[seg + 1]) * fac[:, None]
    f = np.clip(x, key_x[0], key_x[-1])
    u = _bezier_param(x0, x1, x2, x3, f)[:, None]
    a = 1 - u
    out = a**3 * y0 + 3 * a * a * u * y1 + 3 * a * u * u * y2 + u**3 * y3
    exact = np.isclose(f[:, None], x0[:, None], rtol=0, atol=1e-9)
    out = np.where(exact, y0, out)
    return out[:, 0] if squeeze else out


def linear_curve(key_x: np.ndarray, key_y: np.ndarray, x: np.ndarray) -> np.ndarray:
    key_y = np.asarray(key_y, dtype=np.float64)
    if key_y.ndim == 1:
        return np.interp(x, key_x, key_y)
    return np.stack([np.interp(x, key_x, key_y[:, c]) for c in range(key_y.shape[1])], -1)


def evaluate_curve(key_x, key_y, x, interpolation: str = "BEZIER") -> np.ndarray:
    if interpolation == "BEZIER":
        return bezier_auto_clamped(key_x, key_y, x)
    if interpolation == "LINEAR":
        return linear_curve(key_x, key_y, x)
    raise ValueError(f"unknown interpolation {interpolation!r} (BEZIER or LINEAR)")


# --------------------------------------------------------------------------------------------------------------
# Key reduction.


def channel_error(kind: str, approx: np.ndarray, exact: np.ndarray, order: str = "XYZ") -> np.ndarray:
    """Per-frame error (N,) of a channel group: 'quaternion' / 'euler' -> radians, 'location' -> distance,
    'scalar' -> max abs difference."""
    if kind == "quaternion":
        a = rt.normalize(approx)
        b = rt.normalize(exact)
        return 2 * np.arccos(np.clip(np.abs(np.sum(a * b, -1)), 0.0, 1.0))
    if kind == "euler":
        ma = euler_to_matrix(approx, order)
        mb = euler_to_matrix(exact, order)
        cos = (np.trace(np.swapaxes(ma, -1, -2) @ mb, axis1=-2, axis2=-1) - 1) / 2
        return np.arccos(np.clip(cos, -1.0, 1.0))
    if kind == "location":
        return np.linalg.norm(approx - exact, axis=-1)
    if kind == "scalar":
        return np.max(np.abs(approx - exact), axis=-1)
    raise ValueError(f"unknown channel kind {kind!r}")


def reduce_keys(
    frames: np.ndarray,
    values: np.ndarray,
    tolerance: float,
    kind: str = "scalar",
    *,
    interpolation: str = "BEZIER",
    order: str = "XYZ",
) -> np.ndarray:
    """Indices of the keys to keep so the curve through them stays within ``tolerance`` of ``values`` at every
    frame in ``frames`` (N,), the channels of ``values`` (N, C) keyed together.

    Greedy: start from the first and last frame, add the frame of largest error until the bound holds (it always
    ends: with every frame keyed the curve passes through all values). The error is measured on the curve Blender
    evaluates (``interpolation`` BEZIER = auto-clamped handles, or LINEAR) with :func:`channel_error`.
    """
    frames = np.asarray(frames, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]
    n = len(frames)
    if n <= 2:
        return np.arange(n)
    keep = np.zeros(n, dtype=bool)
    keep[[0, n - 1]] = True
    # Constant channel group: two keys (or one) are enough.
    while True:
        idx = np.nonzero(keep)[0]
        approx = evaluate_curve(frames[idx], values[idx], frames, interpolation)
        err = channel_error(kind, approx, values, order)
        err[idx] = 0.0
        worst = int(np.argmax(err))
        if err[worst] <= tolerance:
            return idx
        # Add the worst frame of every segment that breaks the bound (fewer passes over the curve).
        seg = np.searchsorted(idx, np.arange(n), side="right") - 1
        bad = err > tolerance
        order_idx = np.lexsort((-err, seg))
        first_in_seg = np.ones(n, dtype=bool)
        first_in_seg[1:] = seg[order_idx][1:] != seg[order_idx][:-1]
        picks = order_idx[first_in_seg & bad[order_idx]]
        keep[picks] = True


# --------------------------------------------------------------------------------------------------------------
# Baking a retargeted take into F-curve keys.


@dataclass
class CurveKeys:
    """The keys of one F-curve: ``pose.bones["<bone>"].<prop>`` index ``index``, in action group ``group``."""

    data_path: str
    index: int
    group: str
    frames: np.ndarray  # (K,) scene frames
    values: np.ndarray  # (K,)


@dataclass
class BakedKeys:
    """Everything to key: curves, the interpolation and handle type to set on every key, and statistics."""

    curves: list[CurveKeys]
    fps: float
    frame_start: float
    num_frames: int
    interpolation: str = "BEZIER"
    handle_type: str | None = "AUTO_CLAMPED"  # None: leave the handles Blender gives new keys
    rotation_mode: str = "QUATERNION"
    stats: dict = field(default_factory=dict)
    auto_smoothing: str | None = "NONE"  # fcurve.auto_smoothing to set (Blender 5.0 gives new curves CONT_ACCEL); None: keep
    euler_orders: dict = field(default_factory=dict)  # bone -> Euler order, for bones keyed with Euler curves
    rotation_modes: dict = field(default_factory=dict)  # bone -> rotation mode to set on the pose bone

    @property
    def num_keys(self) -> int:
        return int(sum(len(c.frames) for c in self.curves))


@dataclass
class BakeOptions:
    """fps: scene frame rate (frames per second; fps / fps_base in Blender); frame_start: first scene frame.
    rotation_mode: "QUATERNION" or an Euler order ("XYZ", ...) for the rotation curves.
    reduce: keep only the keys needed to stay within rot_tolerance_deg (rotations) and loc_tolerance (locations,
    world units, e.g. metres) at every scene frame; interpolation: "BEZIER" (auto-clamped handles) or "LINEAR".
    foot_lock: keep feet in contact in place (needs contacts); lock_blend_s: ease in/out time of a lock.
    """

    fps: float = 24.0
    frame_start: float = 1.0
    rotation_mode: str = "QUATERNION"
    reduce: bool = True
    rot_tolerance_deg: float = 0.5
    loc_tolerance: float = 0.002
    interpolation: str = "BEZIER"
    foot_lock: bool = False
    lock_blend_s: float = 0.1


def bake_keys(
    result: "rt.RetargetResult",
    options: BakeOptions | None = None,
    contacts: np.ndarray | None = None,
    rotation_modes: dict[str, str] | None = None,
) -> BakedKeys:
    """F-curve keys for a retargeted take at the scene's frame rate (only mapped bones get keys).

    contacts: (T, 2) or (T, 4) foot contact flags at the source rate (left, right) or HumanML3D's (left ankle,
    left toe, right ankle, right toe), needed for ``foot_lock``. rotation_modes: per-bone override of
    ``options.rotation_mode`` (e.g. keep a bone's existing Euler order).
    """
    options = options or BakeOptions()
    if options.interpolation not in ("BEZIER", "LINEAR"):
        raise ValueError("interpolation must be BEZIER or LINEAR")
    positions = resample_positions(result.num_frames, result.fps, options.fps)
    quats = resample_quaternions(result.rotations, positions)  # (N, K, 4)
    root_loc = resample_linear(result.root_location, positions)  # (N, 3)
    if options.foot_lock:
        if contacts is None:
            raise ValueError("foot locking needs the take's foot contacts")
        c = contact_pairs(contacts)
        c = c[np.clip(np.round(positions).astype(np.int64), 0, len(c) - 1)]
        quats, root_loc = foot_lock(result, quats, root_loc, c, fps=options.fps, blend_s=options.lock_blend_s)
    N = len(positions)
    frames = options.frame_start + np.arange(N, dtype=np.float64)
    curves: list[CurveKeys] = []
    euler_orders: dict[str, str] = {}
    bone_modes: dict[str, str] = {}
    kept = 0
    total = 0
    rot_tol = math.radians(options.rot_tolerance_deg)
    loc_tol = options.loc_tolerance / max(result.rig.world_scale(), _EPS)  # world units -> armature units

    def add(bone: str, prop: str, vals: np.ndarray, kind: str, tol: float, order: str = "XYZ") -> None:
        nonlocal kept, total
        if options.reduce:
            idx = reduce_keys(frames, vals, tol, kind, interpolation=options.interpolation, order=order)
        else:
            idx = np.arange(N)
        kept += len(idx) * vals.shape[1]
        total += N * vals.shape[1]
        for i in range(vals.shape[1]):
            curves.append(CurveKeys(f'pose.bones["{bone}"].{prop}', i, bone, frames[idx], vals[idx, i]))

    for k, bone in enumerate(result.bones):
        mode = (rotation_modes or {}).get(bone, options.rotation_mode)
        bone_modes[bone] = mode
        if bone == result.root_bone:
            add(bone, "location", root_loc, "location", loc_tol)
        if mode == "QUATERNION":
            add(bone, "rotation_quaternion", quat_continuity(quats[:, k]), "quaternion", rot_tol)
        elif mode in EULER_ORDERS:
            euler_orders[bone] = mode
            add(bone, "rotation_euler", quats_to_euler(quats[:, k], mode), "euler", rot_tol, mode)
        else:
            raise ValueError(
                f"bone {bone!r}: rotation mode {mode!r} cannot be keyed (use QUATERNION or an Euler order)"
            )
    stats = {
        "keys": kept,
        "keys_unreduced": total,
        "reduction_ratio": kept / max(total, 1),
        "frames": N,
        "fps": options.fps,
    }
    return BakedKeys(
        curves, options.fps, options.frame_start, N, options.interpolation,
        "AUTO_CLAMPED" if options.interpolation == "BEZIER" else "VECTOR",
        options.rotation_mode, stats, euler_orders=euler_orders, rotation_modes=bone_modes,
    )


def evaluate_baked(baked: BakedKeys, frames: np.ndarray | None = None) -> dict[tuple[str, int], np.ndarray]:
    """What Blender plays: every curve of ``baked`` evaluated at ``frames`` (default: every scene frame)."""
    if frames is None:
        frames = baked.frame_start + np.arange(baked.num_frames, dtype=np.float64)
    return {
        (c.data_path, c.index): evaluate_curve(c.frames, c.values, frames, baked.interpolation)
        for c in baked.curves
    }


# --------------------------------------------------------------------------------------------------------------
# Foot locking.


def contact_pairs(contacts: np.ndarray) -> np.ndarray:
    """(T, 2) bool (left, right) from (T, 2) or HumanML3D's (T, 4) (left ankle, left toe, right ankle, right toe)
    contact channels (> 0.5 is contact): a foot is planted when its ankle is."""
    c = np.asarray(contacts, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] not in (2, 4):
        raise ValueError(f"contacts must have shape (T, 2) or (T, 4), got {c.shape}")
    if c.shape[1] == 4:
        c = c[:, [0, 2]]
    return c > 0.5


def contact_runs(contact: np.ndarray) -> list[tuple[int, int]]:
    """The runs [start, end) of consecutive True values in a (T,) bool array."""
    c = np.concatenate([[False], np.asarray(contact, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(c.astype(np.int8)))
    return [(int(s), int(e)) for s, e in zip(edges[::2], edges[1::2])]


def foot_lock(
    result: "rt.RetargetResult",
    quats: np.ndarray,
    root_loc: np.ndarray,
    contacts: np.ndarray,
    *,
    fps: float,
    blend_s: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Keep each foot in place while it is in contact, solving the leg (thigh + shin) as a two-bone chain.

    quats (N, K, 4) / root_loc (N, 3): the take's mapped-bone rotations and pelvis location at the output rate;
    contacts (N, 2) bool (left, right). During a contact run the ankle is held at its mean position over the run;
    it eases in and out over ``blend_s`` seconds around the run (as far as the leg reaches). The foot keeps its
    world orientation. Returns new (quats, root_loc) (root_loc unchanged).
    """
    rig = result.rig
    quats = np.array(quats, dtype=np.float64, copy=True)
    bone_of = dict(zip(result.joints, result.bones))
    col = {b: k for k, b in enumerate(result.bones)}
    blend = max(1, int(round(blend_s * fps)))
    for side_i, side in enumerate(("left", "right")):
        contact = np.asarray(contacts[:, side_i], dtype=bool)
        if not contact.any():
            continue
        leg = tuple(rig.index(bone_of[f"{side}_{j}"]) for j in ("hip", "knee", "ankle"))
        rot, loc = _full_pose(result, quats, root_loc)
        pose = rt.fk(rig, rot, loc)  # (N, B, 4, 4)
        target, weight = _locked_ankle(pose[:, leg[2], :3, 3], contact, blend)
        frames = np.nonzero(weight > 0)[0]
        if not len(frames):
            continue
        for bone_i, m in _leg_to_target(rig, pose[frames], leg, target[frames]).items():
            name = rig.names[bone_i]
            if name in col:
                quats[frames, col[name]] = rt.matrix_to_quat(m)
    return rt.quat_continuity(quats), root_loc


def _locked_ankle(a_pos: np.ndarray, contact: np.ndarray, blend: int) -> tuple[np.ndarray, np.ndarray]:
    """Where the ankle should be ((N, 3)) and how much of the lock applies ((N,), 0..1): the mean position of each
    contact run, eased in and out over ``blend`` frames around it (smoothstep)."""
    N = len(a_pos)
    target = a_pos.copy()
    weight = np.zeros(N)
    for s, e in contact_runs(contact):
        lock = a_pos[s:e].mean(axis=0)
        for t in range(max(0, s - blend), min(N, e + blend)):
            if t < s:
                w = (t - (s - blend) + 1) / (blend + 1)
            elif t >= e:
                w = ((e + blend) - t) / (blend + 1)
            else:
                w = 1.0
            w = w * w * (3 - 2 * w)
            if w > weight[t]:
                weight[t] = w
                target[t] = (1 - w) * a_pos[t] + w * lock
    return target, weight


def _leg_to_target(rig: "rt.RigRest", pose: np.ndarray, leg: tuple[int, int, int], goal: np.ndarray) -> dict:
    """New local rotations (bone index -> (F, 3, 3)) of thigh, shin and foot so the ankle reaches ``goal`` (two-bone
    IK in armature space; the foot keeps its world orientation). ``pose``: (F, B, 4, 4) posed matrices."""
    ih, ik, ia = leg
    H, K, A = pose[:, ih, :3, 3], pose[:, ik, :3, 3], pose[:, ia, :3, 3]
    upper = float(np.linalg.norm(rig.heads[ik] - rig.heads[ih]))
    lower = float(np.linalg.norm(rig.heads[ia] - rig.heads[ik]))
    K_new = rt.two_bone_middle(H, goal, upper, lower, K - (H + A) / 2)
    # Rotate the thigh so the knee moves to K_new, then the shin so the ankle reaches the goal.
    R_thigh = rt.rotation_between(K - H, K_new - H)
    A_after = H + np.einsum("tij,tj->ti", R_thigh, A - H)
    R_shin = rt.rotation_between(A_after - K_new, goal - K_new)
    new_thigh_w = R_thigh @ pose[:, ih, :3, :3]
    new_shin_w = R_shin @ R_thigh @ pose[:, ik, :3, :3]
    rest = rig.matrices[:, :3, :3]
    new_local = {}
    # Bones between thigh and shin (or shin and foot), if any, are unmapped and rigid: the shin is carried by the
    # thigh as if it were its parent, and the foot by the shin.
    for bone_i, new_w, parent_w, parent_i in (
        (ih, new_thigh_w, None, rig.parents[ih]),
        (ik, new_shin_w, new_thigh_w, ih),
        (ia, pose[:, ia, :3, :3], new_shin_w, ik),
    ):
        if parent_w is None:
            parent_w = pose[:, parent_i, :3, :3] if parent_i >= 0 else np.eye(3)
        prest = rest[parent_i] if parent_i >= 0 else np.eye(3)
        carried = parent_w @ prest.T @ rest[bone_i]
        new_local[bone_i] = np.swapaxes(carried, -1, -2) @ new_w
    return new_local


def _full_pose(result: "rt.RetargetResult", quats: np.ndarray, root_loc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rig = result.rig
    N, B = quats.shape[0], len(rig.names)
    rot = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (N, B, 1))
    loc = np.zeros((N, B, 3))
    for k, name in enumerate(result.bones):
        rot[:, rig.index(name)] = quats[:, k]
    loc[:, rig.index(result.root_bone)] = root_loc
    return rot, loc


def baked_pose(baked: BakedKeys, result: "rt.RetargetResult") -> tuple[np.ndarray, np.ndarray]:
    """The pose Blender will play from ``baked``: (N, K, 4) quaternions of ``result.bones`` and the root bone's
    (N, 3) location at every scene frame (Euler curves converted back to quaternions)."""
    values = evaluate_baked(baked)
    N = baked.num_frames
    quats = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (N, len(result.bones), 1))
    loc = np.zeros((N, 3))
    for k, bone in enumerate(result.bones):
        base = f'pose.bones["{bone}"]'
        if (f"{base}.rotation_quaternion", 0) in values:
            quats[:, k] = np.stack([values[(f"{base}.rotation_quaternion", i)] for i in range(4)], -1)
        elif (f"{base}.rotation_euler", 0) in values:
            e = np.stack([values[(f"{base}.rotation_euler", i)] for i in range(3)], -1)
            quats[:, k] = rt.matrix_to_quat(euler_to_matrix(e, baked.euler_orders.get(bone, "XYZ")))
    if (f'pose.bones["{result.root_bone}"].location', 0) in values:
        loc = np.stack([values[(f'pose.bones["{result.root_bone}"].location', i)] for i in range(3)], -1)
    return quats, loc


def take_to_keys(
    joints: np.ndarray,
    rig: "rt.RigRest",
    bone_map,
    *,
    retarget_options: "rt.RetargetOptions | None" = None,
    bake_options: BakeOptions | None = None,
    contacts: np.ndarray | None = None,
    rotation_modes: dict[str, str] | None = None,
    fps: float = 20.0,
) -> tuple[BakedKeys, "rt.RetargetResult"]:
    """One call from a generated take to the keys to write: check the map, retarget, resample, lock, reduce.

    joints: (T, 22, 3) metres, Y up, at ``fps``; rig: the armature's rest (``rig_io.read_rig``); bone_map: a
    ``bone_maps.BoneMap`` (or a plain joint -> bone dict). Raises ``bone_maps.BoneMapError`` (listing what is
    missing) before anything is computed when the map does not fit the rig, so the caller keys nothing.
    """
    if not isinstance(bone_map, bm.BoneMap):
        bone_map = bm.BoneMap(dict(bone_map))
    bone_map.validate(rig.names)
    result = rt.retarget(joints, rig, bone_map.joints, retarget_options,
                         parent_overrides=bone_map.parent_overrides, fps=fps)
    baked = bake_keys(result, bake_options, contacts=contacts, rotation_modes=rotation_modes)
    return baked, result
