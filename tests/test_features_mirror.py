"""Left/right mirroring of joints, features and captions; HumanML3D's normalisation statistics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mld_core.motion import features as F
from mld_core.motion import skeleton as sk

FIXTURES = Path(__file__).parent / "fixtures" / "humanml3d"


@pytest.fixture(scope="module")
def golden():
    return np.load(FIXTURES / "new_joint_vecs_012314.npy"), np.load(FIXTURES / "new_joints_012314.npy")


def test_mirror_joints_twice_is_identity(golden):
    _, joints = golden
    assert np.array_equal(F.mirror_joints(F.mirror_joints(joints)), joints)
    t = torch.from_numpy(joints)
    assert torch.equal(F.mirror_joints(F.mirror_joints(t)), t)


def test_mirror_joints_swaps_sides_and_negates_x(golden):
    _, joints = golden
    m = F.mirror_joints(joints)
    left_wrist, right_wrist = sk.JOINT_NAMES.index("left_wrist"), sk.JOINT_NAMES.index("right_wrist")
    assert np.allclose(m[:, left_wrist], joints[:, right_wrist] * [-1, 1, 1])
    assert np.allclose(m[:, 0], joints[:, 0] * [-1, 1, 1])
    assert torch.allclose(F.mirror_joints(torch.from_numpy(joints)), torch.from_numpy(m))


def test_mirror_features_matches_mirrored_joints(golden):
    vecs, _ = golden
    assert np.array_equal(F.mirror_features(F.mirror_features(vecs)), vecs)
    rec = F.features_to_joints(F.mirror_features(vecs.astype(np.float64)))
    expected = F.mirror_joints(F.features_to_joints(vecs.astype(np.float64)))
    assert np.abs(rec - expected).max() < 1e-9
    t = F.mirror_features(torch.from_numpy(vecs))
    assert np.allclose(t.numpy(), F.mirror_features(vecs))


def test_features_of_mirrored_joints_swap_left_and_right_channels(golden):
    """Re-extracting mirrored joints swaps the sides; the asymmetric reference skeleton (its left and
    right bones differ by up to 9 mm) keeps it from being exact."""
    _, joints = golden
    feats = F.joints_to_features(joints)
    mirrored = F.joints_to_features(F.mirror_joints(joints))
    expected = F.mirror_features(feats)
    # Contacts: left of the mirror = right of the original.
    contacts, expected_contacts = mirrored[:, F.FOOT_CONTACT], expected[:, F.FOOT_CONTACT]
    assert (contacts == expected_contacts).mean() > 0.98
    assert not np.array_equal(contacts, feats[:, F.FOOT_CONTACT])  # the sides really were swapped
    for s in (F.RIC, F.ROT6D, F.LOCAL_VEL, F.ROOT_ROT_VEL):
        assert np.abs(mirrored[:, s] - expected[:, s]).mean() < 6e-3
    # The left wrist of the mirror moves like the right wrist of the original (not like the left one).
    lw = F.RIC.start + 3 * (sk.JOINT_NAMES.index("left_wrist") - 1)
    rw = F.RIC.start + 3 * (sk.JOINT_NAMES.index("right_wrist") - 1)
    same_side = np.abs(mirrored[:, lw + 1] - feats[:, lw + 1]).mean()
    other_side = np.abs(mirrored[:, lw + 1] - feats[:, rw + 1]).mean()
    assert other_side < 0.2 * same_side


@pytest.mark.parametrize(
    "text, expected",
    [
        ("a person waves the left hand", "a person waves the right hand"),
        ("Right foot kicks, then LEFT foot", "Left foot kicks, then RIGHT foot"),
        ("turns clockwise then counterclockwise", "turns counterclockwise then clockwise"),
        ("spins counter-clockwise", "spins clockwise"),
        ("Anticlockwise circle", "Clockwise circle"),
        ("steps leftward, then rightwards", "steps rightward, then leftwards"),
        ("left-handed throw", "right-handed throw"),
        ("a bright light; copyright", "a bright light; copyright"),  # whole words only
        # "left", the past of "leave", is not a side
        ("he left the room waving his right hand", "he left the room waving his left hand"),
        ("she has left, then someone turns left", "she has left, then someone turns right"),
        ("a man came and left", "a man came and left"),
        ("a person raises the left hand and left leg", "a person raises the right hand and right leg"),
        ("", ""),
    ],
)
def test_mirror_text(text, expected):
    assert F.mirror_text(text) == expected
    assert F.mirror_text(F.mirror_text(expected)) == expected


def test_mean_std_groups_and_semantics():
    rng = np.random.default_rng(0)
    clips = [rng.normal(size=(n, 263)) * rng.uniform(0.1, 2.0, size=263) + 3.0 for n in (5, 17, 40)]
    mean, std = F.mean_std(clips)
    data = np.concatenate(clips)
    assert mean.shape == std.shape == (263,) and mean.dtype == std.dtype == np.float32
    assert np.allclose(mean, data.mean(0), atol=1e-5)
    per_dim = data.std(0)
    for s in F.FEATURE_GROUPS.values():
        assert np.allclose(std[s], per_dim[s].mean(), atol=1e-5)  # one value per group
    # Same as one concatenated clip.
    mean2, std2 = F.mean_std([data])
    assert np.array_equal(mean, mean2) and np.array_equal(std, std2)


def test_golden_std_has_the_group_structure(golden):
    """HumanML3D's released Std is constant within each of the 7 groups, as mean_std produces."""
    std = np.load(FIXTURES / "Std.npy")
    assert std.shape == (263,)
    for s in F.FEATURE_GROUPS.values():
        assert np.ptp(std[s]) < 1e-7
    mean, ours = F.mean_std([golden[0]])
    for s in F.FEATURE_GROUPS.values():
        assert np.ptp(ours[s]) < 1e-7


def test_mean_std_rejects_empty_and_constant_groups_are_safe():
    with pytest.raises(ValueError):
        F.mean_std([])
    _, std = F.mean_std([np.ones((4, 263))])
    assert (std > 0).all()
