"""The canonical 22-joint skeleton constants."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mld_core.motion import skeleton as sk

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"


def test_names_parents_and_chains_agree():
    assert len(sk.JOINT_NAMES) == len(sk.PARENTS) == sk.NUM_JOINTS == 22
    assert sk.PARENTS[0] == -1 and all(0 <= p < j for j, p in enumerate(sk.PARENTS) if j)
    covered = {j for chain in sk.KINEMATIC_CHAINS for j in chain}
    assert covered == set(range(22))
    for chain in sk.KINEMATIC_CHAINS:
        for a, b in zip(chain[:-1], chain[1:]):
            assert sk.PARENTS[b] == a


def test_named_joint_indices():
    name = sk.JOINT_NAMES
    assert [name[j] for j in sk.FACE_JOINTS] == ["right_hip", "left_hip", "right_shoulder", "left_shoulder"]
    assert [name[j] for j in sk.FOOT_LEFT] == ["left_ankle", "left_foot"]
    assert [name[j] for j in sk.FOOT_RIGHT] == ["right_ankle", "right_foot"]
    assert [name[j] for j in sk.LEG_JOINTS] == ["right_knee", "right_ankle"]
    assert sk.FPS == 20 and sk.FEATURE_DIM == 263


def test_mirror_index_pairs_left_and_right_names():
    for j, m in enumerate(sk.MIRROR_INDEX):
        assert sk.MIRROR_INDEX[m] == j
        expected = sk.JOINT_NAMES[j].replace("left", "@").replace("right", "left").replace("@", "right")
        assert sk.JOINT_NAMES[m] == expected
        # Mirrored rest directions: x flips.
        assert np.array_equal(sk.RAW_OFFSETS[m], sk.RAW_OFFSETS[j] * [-1, 1, 1])


def test_reference_offsets_are_raw_directions_times_lengths():
    lengths = np.linalg.norm(sk.REFERENCE_OFFSETS, axis=1)
    assert np.allclose(lengths, sk.REFERENCE_BONE_LENGTHS)
    unit = sk.REFERENCE_OFFSETS[1:] / lengths[1:, None]
    assert np.allclose(unit, sk.RAW_OFFSETS[1:])
    assert np.all(sk.REFERENCE_BONE_LENGTHS[1:] > 0.05)


def test_reference_lengths_are_the_golden_sample_bones():
    """How REFERENCE_BONE_LENGTHS was derived: the golden joints' bone lengths, constant over frames."""
    joints = np.load(FIXTURES / "new_joints_012314.npy").astype(np.float64)
    parents = list(sk.PARENTS[1:])
    lengths = np.linalg.norm(joints[:, 1:] - joints[:, parents], axis=-1)  # (T, 21)
    assert np.ptp(lengths, axis=0).max() < 5e-6
    assert np.abs(lengths.mean(0) - sk.REFERENCE_BONE_LENGTHS[1:]).max() < 1e-7
