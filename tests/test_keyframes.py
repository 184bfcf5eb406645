"""Keys an animator can edit: resampling, continuity, Euler output, key reduction, foot locking (no bpy)."""

from __future__ import annotations

import numpy as np
import pytest

from mld_core.rig import bone_maps as bm
from mld_core.rig import keyframes as ke
from mld_core.rig import retarget as rt

WALK = "dataset-2_walk-turn-left_normal_027"

# Blender 5.0.1, one F-curve with AUTO_CLAMPED Bezier keys, auto_smoothing NONE (research/retarget_fidelity.py and
# tests/test_retarget_bpy.py check the model against Blender on the fly; these numbers pin it without bpy).
PIN_X = np.array([1, 4, 6, 11, 13, 20], float)
PIN_Y = np.array([0.0, 1.0, 0.5, 0.7, 2.0, 1.5])
PIN_FRAMES = np.array([2, 3.5, 5, 8, 10, 12, 15, 18.5])
PIN_VALUES = np.array([0.241553, 0.938228, 0.75, 0.511966, 0.608765, 1.38, 1.910218, 1.550978])
PIN_HANDLES = [  # (left x, left y, right x, right y) per key
    (-0.17123, 0.0, 2.17123, 0.0), (2.82877, 1.0, 4.78082, 1.0), (5.21918, 0.5, 7.95206, 0.5),
    (9.04794, 0.5, 11.78082, 0.78), (12.21918, 2.0, 15.73288, 2.0), (17.26712, 1.5, 22.73288, 1.5),
]


@pytest.fixture
def walk(fixtures):
    stored = np.load(fixtures / "rigs" / "source_takes.npz")
    return stored[f"{WALK}_joints"].astype(np.float64), stored[f"{WALK}_contacts"].astype(np.float64)


@pytest.fixture
def metarig_result(fixtures, walk):
    rig = rt.RigRest.load(fixtures / "rigs" / "rigify_metarig.json")
    bmap = bm.detect_bone_map(rig.names, rig.parents).bone_map
    return rt.retarget(walk[0], rig, bmap.joints)


def _rotations_about_z(angles):
    return np.stack([np.cos(angles / 2), 0 * angles, 0 * angles, np.sin(angles / 2)], -1)


def test_resample_covers_the_same_duration():
    pos = ke.resample_positions(40, 20, 24)
    assert len(pos) == 47  # 39 / 20 s * 24 fps + 1
    assert pos[0] == 0 and pos[-1] <= 39 and np.all(np.diff(pos) > 0)
    np.testing.assert_allclose(pos[:3], [0, 20 / 24, 40 / 24])
    np.testing.assert_array_equal(ke.resample_positions(40, 20, 20), np.arange(40))
    with pytest.raises(ValueError):
        ke.resample_positions(0, 20, 24)


def test_slerp_for_rotations_linear_for_locations():
    t = np.arange(21) / 20.0
    quats = _rotations_about_z(np.radians(170) * t)[:, None]  # (21, 1, 4): a steady turn, 8.5 degrees a frame
    pos = ke.resample_positions(21, 20, 60)
    out = ke.resample_quaternions(quats, pos)
    expected = _rotations_about_z(np.radians(170) * pos / 20)[:, None]
    np.testing.assert_allclose(out, expected, atol=1e-12)  # slerp of a steady turn is exact
    locs = np.stack([t, t**2, 0 * t], -1)
    lin = ke.resample_linear(locs, pos)
    np.testing.assert_allclose(lin[::3], locs, atol=1e-12)
    mid = lin[1]
    np.testing.assert_allclose(mid, locs[0] + (locs[1] - locs[0]) / 3)


def test_quaternion_sign_continuity():
    rng = np.random.default_rng(0)
    q = _rotations_about_z(np.linspace(0, 4 * np.pi, 200))  # two full turns: w changes sign on the way
    flips = rng.random(200) < 0.5
    noisy = np.where(flips[:, None], -q, q)
    fixed = ke.quat_continuity(noisy)
    assert np.all(np.sum(fixed[1:] * fixed[:-1], -1) > 0)
    np.testing.assert_allclose(np.abs(np.sum(fixed * q, -1)), 1.0, atol=1e-12)  # same rotations
    assert np.all(np.sum(q[1:] * q[:-1], -1) > 0)  # (the unflipped input was continuous too)
    resampled = ke.resample_quaternions(noisy[:, None], ke.resample_positions(200, 20, 30))
    assert np.all(np.sum(resampled[1:] * resampled[:-1], -1) > 0)


def test_euler_convention_and_round_trip():
    def rx(a):
        return rt.axis_angle_matrix(np.array([1.0, 0, 0]), a)

    def ry(a):
        return rt.axis_angle_matrix(np.array([0, 1.0, 0]), a)

    def rz(a):
        return rt.axis_angle_matrix(np.array([0, 0, 1.0]), a)

    e = np.array([0.3, -0.5, 1.1])  # Blender: Euler((0.3, -0.5, 1.1), 'XYZ').to_matrix() = Rz Ry Rx
    np.testing.assert_allclose(ke.euler_to_matrix(e, "XYZ"), rz(1.1) @ ry(-0.5) @ rx(0.3), atol=1e-12)
    np.testing.assert_allclose(ke.euler_to_matrix(e, "ZXY"), ry(-0.5) @ rx(0.3) @ rz(1.1), atol=1e-12)
    rng = np.random.default_rng(1)
    m = rt.quat_to_matrix(rt.normalize(rng.normal(size=(300, 4))))
    for order in ke.EULER_ORDERS:
        back = ke.euler_to_matrix(ke.matrix_to_euler(m, order), order)
        np.testing.assert_allclose(back, m, atol=1e-9, err_msg=order)
        lock = rng.normal(size=(20, 3))
        lock[:, "XYZ".index(order[1])] = np.pi / 2  # gimbal lock
        ml = ke.euler_to_matrix(lock, order)
        np.testing.assert_allclose(ke.euler_to_matrix(ke.matrix_to_euler(ml, order), order), ml, atol=1e-9)


def test_euler_output_is_continuous():
    angles = np.linspace(0, 4 * np.pi, 120)  # two turns about Z, tilted about X
    tilt = rt.matrix_to_quat(rt.axis_angle_matrix(np.array([1.0, 0, 0]), 0.4))
    q = np.stack([_quat_mul(z, tilt) for z in _rotations_about_z(angles)])
    for order in ("XYZ", "ZXY", "YZX"):
        e = ke.quats_to_euler(q, order)
        assert np.abs(np.diff(e, axis=0)).max() < 0.5, order  # no 2-pi jumps, no branch switches
        np.testing.assert_allclose(ke.euler_to_matrix(e, order), rt.quat_to_matrix(q), atol=1e-9)
    e = ke.quats_to_euler(q, "XYZ")
    assert e[-1, 2] - e[0, 2] == pytest.approx(4 * np.pi, abs=1e-6)  # unwrapped


def _quat_mul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def test_bezier_model_matches_blender_numbers():
    np.testing.assert_allclose(ke.bezier_auto_clamped(PIN_X, PIN_Y, PIN_FRAMES), PIN_VALUES, atol=2e-6)
    lx, ly, rx, ry = ke.auto_clamped_handles(PIN_X, PIN_Y)
    np.testing.assert_allclose(np.stack([lx, ly[:, 0], rx, ry[:, 0]], -1), PIN_HANDLES, atol=1e-5)
    # Keys are hit exactly; outside the keys the curve is constant.
    np.testing.assert_allclose(ke.bezier_auto_clamped(PIN_X, PIN_Y, PIN_X), PIN_Y, atol=1e-12)
    np.testing.assert_allclose(ke.bezier_auto_clamped(PIN_X, PIN_Y, [-5.0, 30.0]), [0.0, 1.5])


def _signals(rng, n=120):
    t = np.arange(n) / 24.0
    smooth = np.stack([np.sin(t), 0.3 * np.cos(2 * t + 1), t**2 / 10], -1)
    noisy = smooth + rng.normal(0, 0.01, smooth.shape)
    steps = np.where(t[:, None] > 2.5, 1.0, 0.0) * np.array([1.0, -2.0, 0.5])
    return {"smooth": smooth, "noisy": noisy, "steps": steps}


@pytest.mark.parametrize("interpolation", ["BEZIER", "LINEAR"])
def test_key_reduction_error_bound_holds_for_the_interpolated_curve(interpolation):
    rng = np.random.default_rng(2)
    frames = np.arange(1, 121, dtype=float)
    for name, values in _signals(rng).items():
        for tol in (1e-3, 1e-2):
            keep = ke.reduce_keys(frames, values, tol, "location", interpolation=interpolation)
            curve = ke.evaluate_curve(frames[keep], values[keep], frames, interpolation)
            err = np.linalg.norm(curve - values, axis=-1)
            assert err.max() <= tol + 1e-12, (name, tol, err.max())
            assert keep[0] == 0 and keep[-1] == len(frames) - 1
            if name == "smooth" and tol == 1e-2:
                assert len(keep) < len(frames) / 3, (tol, len(keep))
    # Constant channels need only their end keys.
    assert list(ke.reduce_keys(frames, np.ones((120, 2)), 1e-6)) == [0, 119]


def test_key_reduction_of_rotations_bounds_the_angle():
    rng = np.random.default_rng(3)
    n = 150
    axis = rt.normalize(np.cumsum(rng.normal(0, 0.05, (n, 3)), 0) + np.array([0.0, 0.0, 1.0]))
    angle = np.cumsum(np.abs(rng.normal(0.03, 0.02, n)))
    q = ke.quat_continuity(rt.matrix_to_quat(rt.axis_angle_matrix(axis, angle)))
    frames = np.arange(n, dtype=float)
    tol = np.radians(0.5)
    keep = ke.reduce_keys(frames, q, tol, "quaternion")
    approx = ke.bezier_auto_clamped(frames[keep], q[keep], frames)
    assert ke.channel_error("quaternion", approx, q).max() <= tol
    assert len(keep) < n
    e = ke.quats_to_euler(q, "XYZ")
    keep_e = ke.reduce_keys(frames, e, tol, "euler", order="XYZ")
    approx_e = ke.bezier_auto_clamped(frames[keep_e], e[keep_e], frames)
    assert ke.channel_error("euler", approx_e, e, "XYZ").max() <= tol


def test_bake_keys_only_mapped_bones_and_within_tolerance(metarig_result):
    res = metarig_result
    baked = ke.bake_keys(res, ke.BakeOptions(fps=24, frame_start=10))
    assert baked.num_frames == len(ke.resample_positions(res.num_frames, 20, 24))
    assert {c.group for c in baked.curves} == set(res.bones)
    paths = {c.data_path for c in baked.curves}
    assert paths == {f'pose.bones["{b}"].rotation_quaternion' for b in res.bones} | {
        f'pose.bones["{res.root_bone}"].location'}
    assert all(c.frames[0] == 10 and c.frames[-1] == 10 + baked.num_frames - 1 for c in baked.curves)
    assert 0.0 < baked.stats["reduction_ratio"] < 0.9
    assert baked.interpolation == "BEZIER" and baked.handle_type == "AUTO_CLAMPED" and baked.auto_smoothing == "NONE"
    # What Blender will play stays within the tolerances of the unreduced, resampled take.
    full = ke.bake_keys(res, ke.BakeOptions(fps=24, reduce=False))
    q_full, loc_full = ke.baked_pose(full, res)
    q_red, loc_red = ke.baked_pose(baked, res)
    angle = ke.channel_error("quaternion", q_red, q_full)
    assert angle.max() <= np.radians(0.5) + 1e-9
    assert np.linalg.norm(loc_red - loc_full, axis=-1).max() <= 0.002 + 1e-9


def test_bake_keys_euler_option(metarig_result):
    res = metarig_result
    baked = ke.bake_keys(res, ke.BakeOptions(fps=30, rotation_mode="ZXY"))
    assert all(".rotation_quaternion" not in c.data_path for c in baked.curves)
    assert baked.rotation_modes == {b: "ZXY" for b in res.bones}
    for c in baked.curves:
        if c.data_path.endswith("rotation_euler"):
            assert np.abs(np.diff(c.values)).max() < np.pi / 2  # continuous
    full = ke.bake_keys(res, ke.BakeOptions(fps=30, reduce=False))
    q_full, _ = ke.baked_pose(full, res)
    q_e, _ = ke.baked_pose(baked, res)
    assert ke.channel_error("quaternion", q_e, q_full).max() <= np.radians(0.5) + 1e-9
    with pytest.raises(ValueError, match="AXIS_ANGLE"):
        ke.bake_keys(res, ke.BakeOptions(rotation_mode="AXIS_ANGLE"))


def test_foot_lock_keeps_planted_feet_still(metarig_result, walk):
    res = metarig_result
    contacts = walk[1]
    with pytest.raises(ValueError, match="contacts"):
        ke.bake_keys(res, ke.BakeOptions(fps=20, foot_lock=True))
    free = ke.bake_keys(res, ke.BakeOptions(fps=20, reduce=False))
    locked = ke.bake_keys(res, ke.BakeOptions(fps=20, reduce=False, foot_lock=True), contacts=contacts)

    def ankles(baked):
        q, loc = ke.baked_pose(baked, res)
        played = rt.RetargetResult(res.bones, res.joints, q, res.root_bone, loc, res.scale, 20.0,
                                   res.source_world, res.rig)
        return played.world_joints()

    a_free, a_lock = ankles(free), ankles(locked)
    pairs = ke.contact_pairs(contacts)
    checked = 0
    for i, side in enumerate(("left", "right")):
        runs = ke.contact_runs(pairs[:, i])
        for s, e in runs:
            if e - s < 4:
                continue
            free_drift = np.ptp(a_free[f"{side}_ankle"][s:e], axis=0).max()
            lock_drift = np.ptp(a_lock[f"{side}_ankle"][s:e], axis=0).max()
            assert lock_drift < 0.25 * free_drift, (side, s, e, lock_drift, free_drift)
            checked += 1
    assert checked >= 3
    assert ke.contact_runs(np.array([1, 1, 0, 0, 1, 0, 1, 1, 1], bool)) == [(0, 2), (4, 5), (6, 9)]
    # The rest of the body is untouched.
    for joint in ("head", "left_wrist", "pelvis"):
        np.testing.assert_allclose(a_lock[joint], a_free[joint], atol=1e-9)


def test_take_to_keys_refuses_an_incomplete_map_before_anything_is_computed(fixtures, walk):
    rig = rt.RigRest.load(fixtures / "rigs" / "bandai_bvh.json")
    bmap = bm.detect_bone_map(rig.names, rig.parents).bone_map
    baked, result = ke.take_to_keys(walk[0], rig, bmap, bake_options=ke.BakeOptions(fps=24), contacts=walk[1])
    assert {c.group for c in baked.curves} == set(bmap.joints.values())
    assert result.root_bone == "Hips"
    broken = bm.BoneMap({j: b for j, b in bmap.joints.items() if j not in ("left_wrist", "right_ankle")})
    with pytest.raises(bm.BoneMapError) as err:
        ke.take_to_keys(walk[0], rig, broken)
    assert err.value.missing == ["right_ankle", "left_wrist"]
