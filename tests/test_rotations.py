"""Joint rotations from features: FK reproduces the recovered joints; twist comes from the 6D channels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mld_core.motion import features as F
from mld_core.motion import rotations as R
from mld_core.motion import skeleton as sk
from mld_core.motion.quaternion import (
    cont6d_to_matrix,
    matrix_to_cont6d,
    matrix_to_quat,
    qbetween,
    qinv,
    qmul,
    qrot,
    quat_to_matrix,
    resample_quaternions,
)

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"


@pytest.fixture(scope="module")
def golden():
    return np.load(FIXTURES / "new_joint_vecs_012314.npy"), np.load(FIXTURES / "new_joints_012314.npy")


def _axis_angle(axis, angle):
    axis = np.asarray(axis, np.float64)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    half = np.asarray(angle)[..., None] / 2
    return np.concatenate([np.cos(half), np.sin(half) * axis], axis=-1)


def test_fk_of_rotations_matches_golden_joints(golden):
    vecs, joints = golden
    rest = R.rest_offsets_from_joints(joints)  # the golden (SMPL) body's pelvis and chest shape
    quats, root = R.features_to_rotations(vecs, rest)
    assert quats.shape == (len(vecs), 22, 4) and root.shape == (len(vecs), 3)
    assert quats.dtype == root.dtype == np.float32
    assert np.allclose(np.linalg.norm(quats, axis=-1), 1.0, atol=1e-5)
    err = np.linalg.norm(R.fk(quats, root, rest) - F.features_to_joints(vecs.astype(np.float64)), axis=-1)
    print(f"golden FK error: max {err.max() * 1000:.4f} mm, mean {err.mean() * 1000:.4f} mm")
    assert err.max() < 1e-3


def _synthetic_rest_clip(frames=60, seed=0):
    """A smooth random motion of the REST_OFFSETS skeleton (whose pelvis and chest are rigid)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, frames)[:, None]
    axes = rng.normal(size=(22, 3))
    amp = rng.uniform(0.1, 0.6, size=22)
    angles = amp * np.sin(2 * np.pi * (t * rng.uniform(0.5, 1.5, size=22) + rng.uniform(size=22)))
    local = _axis_angle(np.broadcast_to(axes, (frames, 22, 3)), angles)  # (T, 22, 4)
    local[:, 0] = qmul(_axis_angle([0, 1, 0], 3.0 * t[:, 0]), local[:, 0])  # turn while moving
    root = np.concatenate([0.8 * t, 1.0 + 0.02 * np.sin(6 * t), 1.2 * t], axis=-1)
    return R.fk(local, root, sk.REST_OFFSETS)


def test_fk_of_rotations_matches_on_the_rest_skeleton():
    joints = _synthetic_rest_clip()
    feats = F.joints_to_features(joints)
    quats, root = R.features_to_rotations(feats)
    err = np.linalg.norm(R.fk(quats, root) - F.features_to_joints(feats.astype(np.float64)), axis=-1)
    print(f"synthetic REST_OFFSETS clip FK error: max {err.max() * 1000:.4f} mm")
    assert err.max() < 1e-3


def test_rest_offsets_shape_and_self_consistency():
    lengths = np.linalg.norm(sk.REST_OFFSETS, axis=1)
    assert np.allclose(lengths, sk.REFERENCE_BONE_LENGTHS, atol=1e-7)
    # Bones outside the two branches are HumanML3D's rest directions.
    same = [k for k in range(1, 22) if k not in (1, 2, 13, 14)]
    assert np.allclose(sk.REST_OFFSETS[same], sk.REFERENCE_OFFSETS[same])
    rest_pose = R.fk(np.tile([1.0, 0, 0, 0], (1, 22, 1)), np.zeros((1, 3)), sk.REST_OFFSETS)
    assert np.allclose(R.rest_offsets_from_joints(rest_pose), sk.REST_OFFSETS, atol=1e-6)
    # Hips below the pelvis, collars above spine3, mirror-symmetric up to 1e-3.
    assert sk.REST_OFFSETS[1, 1] < 0 and sk.REST_OFFSETS[13, 1] > 0
    dirs = sk.REST_DIRECTIONS
    assert np.abs(dirs[list(sk.MIRROR_INDEX)] * [-1, 1, 1] - dirs).max() < 1e-3


def test_twist_comes_from_the_6d_channels(golden):
    """Twisting a bone about itself in the 6D channels leaves the joints alone but turns the rotation."""
    vecs, _ = golden
    vecs = vecs.astype(np.float64)
    knee = sk.JOINT_NAMES.index("left_knee")  # 6D of the thigh bone (hip -> knee)
    hip = sk.PARENTS[knee]
    ankle = sk.JOINT_NAMES.index("left_ankle")  # 6D of the shin, relative to the thigh
    twist = _axis_angle(sk.RAW_OFFSETS[knee], np.deg2rad(30.0))  # about the thigh's rest direction
    rot6d = vecs[:, F.ROT6D].reshape(len(vecs), 21, 6)
    thigh = qmul(matrix_to_quat(cont6d_to_matrix(rot6d[:, knee - 1])), twist[None])
    shin = qmul(qinv(twist)[None], matrix_to_quat(cont6d_to_matrix(rot6d[:, ankle - 1])))  # shin unchanged
    twisted = vecs.copy()
    for k, q in ((knee, thigh), (ankle, shin)):
        twisted[:, F.ROT6D.start + 6 * (k - 1) : F.ROT6D.start + 6 * k] = matrix_to_cont6d(quat_to_matrix(q))

    q0, _ = R.features_to_rotations(vecs)
    q1, _ = R.features_to_rotations(twisted)
    w0, w1 = R.world_rotations(q0.astype(np.float64)), R.world_rotations(q1.astype(np.float64))
    delta = qmul(qinv(w0[:, hip]), w1[:, hip])  # in the hip's frame: a turn about the rest thigh
    assert np.allclose(R.rotation_angle_deg(delta), 30.0, atol=0.05)
    axis = delta[:, 1:] / np.linalg.norm(delta[:, 1:], axis=-1, keepdims=True)
    assert np.allclose(np.abs(axis @ sk.REST_DIRECTIONS[knee]), 1.0, atol=1e-4)
    # Other joints are untouched.
    others = [j for j in range(22) if j != hip]
    assert np.abs(w0[:, others] - w1[:, others]).max() < 1e-5


def test_single_child_rotations_follow_humanml3d_bones(golden):
    """On consistent data no swing correction is needed: joint j's world rotation is the 6D bone's."""
    vecs, _ = golden
    quats, _ = R.features_to_rotations(vecs)
    world = R.world_rotations(quats.astype(np.float64))
    bones = R.hml_bone_rotations(vecs)
    for j, kids in enumerate(R.CHILDREN):
        if len(kids) == 1:
            c = kids[0]
            expected = qmul(bones[:, c], qbetween(sk.REST_DIRECTIONS[c], sk.RAW_OFFSETS[c])[None])
            assert R.rotation_angle_deg(qmul(qinv(expected), world[:, j])).max() < 0.01, j


def test_fk_numpy_and_torch_agree(golden):
    vecs, _ = golden
    quats, root = R.features_to_rotations(vecs[:30])
    a = R.fk(quats, root)
    b = R.fk(torch.from_numpy(quats).double(), torch.from_numpy(root).double())
    assert isinstance(b, torch.Tensor) and b.shape == (30, 22, 3)
    assert np.abs(b.numpy() - a).max() < 1e-6


def test_identity_rotations_give_the_rest_pose():
    pose = R.fk(np.tile([1.0, 0, 0, 0], (22, 1)), np.array([0.0, 1.0, 0.0]))  # (22, 3)
    for j, p in enumerate(sk.PARENTS):
        if p >= 0:
            assert np.allclose(pose[j] - pose[p], sk.REST_OFFSETS[j])


def test_quaternions_are_continuous_in_time(golden):
    vecs, _ = golden
    quats, _ = R.features_to_rotations(vecs)
    assert ((quats[1:] * quats[:-1]).sum(-1) > 0).all()


def test_bad_features_raise():
    with pytest.raises(ValueError, match="263"):
        R.features_to_rotations(np.zeros((10, 22, 3)))


def test_resample_quaternions_keeps_frames_and_duration(golden):
    vecs, _ = golden
    quats, root = R.features_to_rotations(vecs)
    q30, r30 = resample_quaternions(quats, root, 20, 30)
    assert len(q30) == 1 + (len(quats) - 1) * 3 // 2 and q30.dtype == np.float32
    assert np.allclose(q30[::3], quats[::2], atol=1e-6) and np.allclose(r30[::3], root[::2], atol=1e-6)
    assert np.allclose(np.linalg.norm(q30, axis=-1), 1.0, atol=1e-5)
    # Halfway frames lie halfway: the angle to each neighbour is the same.
    mid = q30[1]  # 30 fps frame 1 = 20 fps frame 0.667
    a = R.rotation_angle_deg(qmul(qinv(quats[0].astype(np.float64)), mid.astype(np.float64)))
    b = R.rotation_angle_deg(qmul(qinv(quats[0].astype(np.float64)), quats[1].astype(np.float64)))
    assert np.allclose(a, 2 / 3 * b, atol=0.05)


def test_turning_about_y_equals_rotating_by_its_quaternion():
    from mld_core.motion.quaternion import qrot, turn_about_y

    rng = np.random.default_rng(0)
    half = rng.uniform(-4.0, 4.0, (5, 7))
    v = rng.normal(size=(5, 7, 3))
    q = np.stack([np.cos(half), np.zeros_like(half), np.sin(half), np.zeros_like(half)], axis=-1)
    np.testing.assert_allclose(turn_about_y(half, v), qrot(q, v), atol=1e-12)
    many = rng.normal(size=(5, 7, 4, 3))  # one angle for several vectors, as a take's joints per frame
    np.testing.assert_allclose(turn_about_y(half[..., None], many), qrot(q[..., None, :], many), atol=1e-12)
    quarter = turn_about_y(np.array(np.pi / 4), np.array([1.0, 2.0, 0.0]))  # +X turns to -Z by 90 degrees
    np.testing.assert_allclose(quarter, [0.0, 2.0, -1.0], atol=1e-12)
