"""Repairs of generated takes (mld_core.motion.repair): planted feet that do not slide, one skeleton per take."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mld_core.checkpoint import CheckpointError, load_config
from mld_core.eval.quality import foot_skating_ratio
from mld_core.motion import skeleton as sk
from mld_core.motion.features import RIC, features_to_joints, joints_to_features
from mld_core.motion.repair import (RepairConfig, features_with_bone_lengths, plant_feet, repair_features,
                                    two_bone_ik)
from mld_core.testing import tiny_model

WALK = "dataset-2_walk-turn-left_normal_027"


@pytest.fixture
def walk(fixtures):
    joints = np.load(fixtures / "rigs" / "source_takes.npz")[f"{WALK}_joints"].astype(np.float64)
    return joints_to_features(joints).astype(np.float64)  # (T, 263)


def _bone_sd_mm(joints):
    parents = np.asarray(sk.PARENTS)
    lengths = np.linalg.norm(joints[:, 1:] - joints[:, parents[1:]], axis=-1)  # (T, 21)
    return float(lengths.std(axis=0).max() * 1000)


def _sliding(features, metres_per_frame=0.03):
    """The same take with its root drifting sideways: every planted foot slides."""
    out = features.copy()
    out[:, 1] += metres_per_frame
    return out


def test_planting_feet_removes_a_sliding_root(walk):
    real = foot_skating_ratio(features_to_joints(walk))
    slid = _sliding(walk)
    assert foot_skating_ratio(features_to_joints(slid)) > real + 0.2
    fixed = plant_feet(slid)
    assert foot_skating_ratio(features_to_joints(fixed)) <= real + 0.03
    changed = np.flatnonzero(np.abs(fixed - slid).max(axis=0) > 0)
    assert set(changed.tolist()) <= {1, 2}  # only the root's ground velocity moves


def test_planting_keeps_a_clean_take_on_its_path(walk):
    before, after = features_to_joints(walk), features_to_joints(plant_feet(walk))
    travelled = np.linalg.norm(before[-1, 0, [0, 2]] - before[0, 0, [0, 2]])
    assert np.linalg.norm(after[-1, 0, [0, 2]] - before[-1, 0, [0, 2]]) < 0.1 * travelled
    assert foot_skating_ratio(after) <= foot_skating_ratio(before) + 0.02


def test_a_pose_jump_is_not_taken_for_a_plant(walk):
    jumpy = walk.copy()
    jumpy[40:, RIC] += np.tile([0.3, 0.0, 0.0], 21)  # the whole pose jumps 30 cm sideways in the root frame
    step = np.abs(np.diff(features_to_joints(plant_feet(jumpy))[:, 0, 0]))
    assert step.max() < np.abs(np.diff(features_to_joints(walk)[:, 0, 0])).max() + RepairConfig().max_correction_m


def test_bone_lengths_become_the_reference_skeleton_and_toes_stay(walk):
    rng = np.random.default_rng(0)
    stretched = walk.copy()
    ric = stretched[:, RIC].reshape(len(walk), 21, 3)
    ric *= 1.0 - 0.03 * np.abs(rng.standard_normal((len(walk), 1, 1)))  # each frame shrunk by its own few per cent
    ric[:, [9, 10]] = walk[:, RIC].reshape(len(walk), 21, 3)[:, [9, 10]]  # toes where the take had them
    stretched[:, RIC] = ric.reshape(len(walk), -1)
    assert _bone_sd_mm(features_to_joints(stretched)) > 5.0
    fixed = features_with_bone_lengths(stretched)
    joints = features_to_joints(fixed)
    lengths = np.linalg.norm(joints[:, 1:] - joints[:, np.asarray(sk.PARENTS[1:])], axis=-1)
    np.testing.assert_allclose(lengths, np.broadcast_to(sk.REFERENCE_BONE_LENGTHS[1:], lengths.shape), atol=1e-6)
    toes = np.abs(joints[:, [10, 11]] - features_to_joints(stretched)[:, [10, 11]]).max()
    assert toes < 1e-6
    np.testing.assert_array_equal(np.delete(fixed, np.r_[RIC], axis=1), np.delete(stretched, np.r_[RIC], axis=1))


def test_two_bone_ik_reaches_and_keeps_lengths():
    root = np.zeros((3, 3))
    goal = np.array([[0.0, -0.7, 0.1], [0.0, -0.5, 0.3], [0.0, -2.0, 0.0]])  # the last is out of reach
    pole = np.array([[0.0, -0.4, 0.3]] * 3)
    middle, end = two_bone_ik(root, goal, pole, 0.4, 0.43)
    np.testing.assert_allclose(np.linalg.norm(middle - root, axis=1), 0.4, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(end - middle, axis=1), 0.43, atol=1e-5)
    np.testing.assert_allclose(end[:2], goal[:2], atol=1e-9)
    assert (middle[:2, 2] > 0).all()  # bends towards the pole (forward)
    np.testing.assert_allclose(end[2] / np.linalg.norm(end[2]), [0, -1, 0], atol=1e-9)


def test_repair_applies_the_switches_in_order(walk):
    slid = _sliding(walk)
    np.testing.assert_array_equal(repair_features(slid, RepairConfig(bone_lengths=False, plant_feet=False)), slid)
    np.testing.assert_allclose(repair_features(slid, RepairConfig(bone_lengths=False)), plant_feet(slid))
    both = repair_features(slid)
    np.testing.assert_allclose(both, plant_feet(features_with_bone_lengths(slid)))


def test_pipeline_repairs_free_takes_only_when_asked(tmp_path):
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained(tiny_model(tmp_path / "m"))
    on = pipe(["a walk", "a wave"], 2.5, seed=[1, 2], num_inference_steps=2)
    off = pipe(["a walk", "a wave"], 2.5, seed=[1, 2], num_inference_steps=2, repair=False)
    assert not np.allclose(on.features, off.features)
    np.testing.assert_allclose(on.features, pipe.repair_rows(off.features, off.lengths.tolist()), atol=1e-5)
    single = pipe("a wave", 2.5, seed=2, num_inference_steps=2)
    np.testing.assert_allclose(single.features[0], on.features[1], atol=1e-5)  # batch equals single runs
    pipe.config.repair = RepairConfig(bone_lengths=False, plant_feet=False)
    np.testing.assert_array_equal(pipe(["a walk", "a wave"], 2.5, seed=[1, 2], num_inference_steps=2).features,
                                  off.features)


@pytest.mark.parametrize("repair, words", [("on", "JSON object"), ({"plant_feet": "yes"}, "true or false"),
                                           ({"smooth_frames": -1}, ">= 0"), ({"feet": True}, "feet")])
def test_a_bad_repair_entry_is_a_checkpoint_error(tmp_path, repair, words):
    model = tiny_model(tmp_path / "m")
    config = json.loads((model / "config.json").read_text())
    (model / "config.json").write_text(json.dumps({**config, "repair": repair}))
    with pytest.raises(CheckpointError, match=words):
        load_config(model)


def test_planting_keeps_the_travel_the_legs_do_not_carry(walk):
    gliding = walk.copy()
    gliding[:, 4:] = walk[0, 4:]  # the pose (and its contacts) frozen: the root glides as generated
    travel = np.linalg.norm(np.diff(features_to_joints(gliding)[[0, -1], 0][:, [0, 2]], axis=0))
    assert travel > 1.0

    def kept(config):
        j = features_to_joints(plant_feet(gliding, config))
        return np.linalg.norm(np.diff(j[[0, -1], 0][:, [0, 2]], axis=0)) / travel

    assert kept(RepairConfig(min_travel_kept=0.0)) < 0.25  # planted fully, the glide (all but the capped part) stops
    assert kept(RepairConfig(min_travel_kept=0.8)) == pytest.approx(0.8, abs=0.02)
