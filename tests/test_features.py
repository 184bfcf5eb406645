"""Parity of the 263-d features with HumanML3D's golden sample 012314, and the round trips."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mld_core.motion import features as F
from mld_core.motion import skeleton as sk
from mld_core.motion.quaternion import qrot, yaw_quat


@pytest.fixture(scope="module")
def golden():
    d = Path(__file__).parent / "fixtures" / "humanml3d"
    return np.load(d / "new_joint_vecs_012314.npy"), np.load(d / "new_joints_012314.npy")


def test_slices_cover_263_in_order():
    groups = list(F.FEATURE_GROUPS.values())
    assert groups[0].start == 0 and groups[-1].stop == sk.FEATURE_DIM
    for a, b in zip(groups[:-1], groups[1:]):
        assert a.stop == b.start
    assert [g.stop - g.start for g in groups] == [1, 2, 1, 63, 126, 66, 4]


def test_features_to_joints_reproduces_golden_joints(golden):
    vecs, joints = golden
    rec = F.features_to_joints(vecs)
    err = np.abs(rec - joints).max()
    print(f"features_to_joints max abs error vs golden joints: {err:.2e} m")
    assert rec.shape == joints.shape and rec.dtype == np.float32
    assert err <= 1e-4


def test_joints_to_features_reproduces_golden_features(golden):
    vecs, joints = golden
    feats = F.joints_to_features(joints)
    assert feats.shape == (len(joints) - 1, sk.FEATURE_DIM) and feats.dtype == np.float32
    ref = vecs[:-1]
    for name, s in F.FEATURE_GROUPS.items():
        err = np.abs(feats[:, s] - ref[:, s])
        print(f"{name:13s} max abs error: first 80 rows {err[:80].max():.2e}, all rows {err.max():.2e}")
        # Rows near the end see a different Gaussian-smoothing window: the golden joints lack the clip's
        # last source frame.
        assert err[:80].max() <= 1e-4, name
        assert err.max() <= 2e-2, name


def test_gaussian_filter_matches_scipy():
    ndimage = pytest.importorskip("scipy.ndimage")
    x = np.random.default_rng(0).normal(size=(37, 3))
    for sigma in (1.5, 20.0):
        ref = ndimage.gaussian_filter1d(x, sigma, axis=0, mode="nearest")
        assert np.abs(F.gaussian_filter1d(x, sigma) - ref).max() < 1e-12


def test_numpy_and_torch_paths_agree(golden):
    vecs, _ = golden
    rec_np = F.features_to_joints(vecs.astype(np.float64))
    rec_t = F.features_to_joints(torch.from_numpy(vecs).double())
    assert isinstance(rec_t, torch.Tensor) and rec_t.dtype == torch.float64
    assert np.abs(rec_t.numpy() - rec_np).max() < 1e-12
    rec_t32 = F.features_to_joints(torch.from_numpy(vecs))
    assert rec_t32.dtype == torch.float32
    assert np.abs(rec_t32.numpy() - rec_np).max() < 1e-4


def test_batched_equals_per_item(golden):
    vecs, _ = golden
    rng = np.random.default_rng(1)
    batch = np.stack([vecs[:60], vecs[60:120] + 0.01 * rng.normal(size=(60, 263)).astype(np.float32)])
    out = F.features_to_joints(torch.from_numpy(batch))  # (2, 60, 22, 3)
    assert out.shape == (2, 60, 22, 3)
    for i in range(2):
        single = F.features_to_joints(torch.from_numpy(batch[i]))
        assert torch.allclose(out[i], single, atol=1e-6)


def test_torch_path_is_differentiable(golden):
    vecs, _ = golden
    x = torch.from_numpy(vecs[:20]).double().requires_grad_(True)
    F.features_to_joints(x).square().sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    assert x.grad[:, F.RIC].abs().sum() > 0 and x.grad[:, F.ROOT_ROT_VEL].abs().sum() > 0


def _turning_clip(golden_joints, turns: float) -> np.ndarray:
    """The golden clip spun about +Y through `turns` full turns (starts unrotated)."""
    t = np.linspace(0.0, 2 * np.pi * turns, len(golden_joints))
    return qrot(yaw_quat(t)[:, None], golden_joints.astype(np.float64))


@pytest.mark.parametrize("turns", [2.2, -2.2])
def test_turning_through_180_degrees_round_trips(golden, turns):
    """HumanML3D's own extraction flips feature 0's sign past +-180 degrees; ours must not."""
    _, joints = golden
    clip = _turning_clip(joints, turns)
    feats = F.joints_to_features(clip)
    rec = F.features_to_joints(feats.astype(np.float64))
    expected = F.canonical_joints(clip)[:-1]
    err = np.abs(rec - expected).max()
    print(f"turning clip ({turns:+} turns) round-trip max abs error: {err:.2e} m")
    assert err < 1e-4
    # The facing did cross +-180 degrees (with HumanML3D's arcsin this clip round-trips 9-10 cm off).
    assert abs(2 * feats[:, 0].sum()) > np.pi


def test_root_half_angle_keeps_its_sign_across_180_degrees():
    yaw = np.deg2rad(np.arange(150.0, 220.0, 5.0))  # passes +180
    root_quat = yaw_quat(-yaw)  # world -> facing frame
    half = F._root_velocity_half_angle(root_quat)[:, 0]
    assert np.allclose(half, -np.deg2rad(2.5), atol=1e-9)


def test_round_trip_on_arbitrary_placement(golden):
    """Any start position, facing and scale give the same features (canonicalisation + uniform skeleton)."""
    _, joints = golden
    moved = qrot(yaw_quat(np.array(2.0))[None, None], joints.astype(np.float64) * 1.3) + [4.0, 0.5, -2.0]
    a = F.joints_to_features(joints)
    b = F.joints_to_features(moved)
    assert np.abs(a - b).max() < 1e-4


def test_resampling_at_30_fps_gives_20_fps_rows(golden):
    _, joints = golden
    j30 = F.resample(joints.astype(np.float64), 20, 30)
    assert len(j30) == 1 + (len(joints) - 1) * 3 // 2
    assert np.abs(j30[::3] - joints[::2]).max() < 1e-6  # common instants are kept exactly
    back = F.joints_to_features(j30, fps=30)
    ref = F.joints_to_features(joints)[: len(back)]
    assert len(back) == len(joints) - 2  # 253.5 frames of 30 fps: the last half frame is dropped
    # Positions and per-frame velocities are at 20 fps again (twice-interpolated frames of this fast clip
    # differ by up to 4 cm, 1-2 mm on average).
    for s in (F.RIC, F.LOCAL_VEL):
        err = np.abs(back[:80, s] - ref[:80, s]).mean()
        assert err < 3e-3, err


@pytest.mark.parametrize(
    "bad", [np.zeros((10, 21, 3)), np.zeros((10, 22)), np.full((10, 22, 3), np.nan), np.zeros((1, 22, 3))]
)
def test_bad_joints_raise(bad):
    with pytest.raises(ValueError):
        F.joints_to_features(bad)


def test_bad_features_raise():
    with pytest.raises(ValueError, match="263"):
        F.features_to_joints(np.zeros((10, 262), np.float32))
