"""Repairs of generated takes (mld_core.take_fixes.repair): planted feet that do not slide, locked feet, one skeleton
per take."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mld_core.checkpoint import CheckpointError, load_config
from mld_core.eval.quality import foot_skating_ratio
from mld_core.motion import skeleton as sk
from mld_core.motion.features import FOOT_CONTACT, RIC, features_to_joints, joints_to_features
from mld_core.rig.fidelity import knee_bend_deg
from mld_core.take_fixes.repair import (RepairConfig, double_support_share, features_with_bone_lengths,
                                        foot_hold_shifts, lock_feet, plant_feet, put_on_floor, repair_features,
                                        repair_rows, two_bone_ik)
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
    none = RepairConfig(bone_lengths=False, plant_feet=False, lock_feet=False)
    np.testing.assert_array_equal(repair_features(slid, none), slid)
    np.testing.assert_allclose(repair_features(slid, RepairConfig(bone_lengths=False, lock_feet=False)), plant_feet(slid))
    np.testing.assert_allclose(repair_features(slid, RepairConfig(bone_lengths=False, plant_feet=False)), lock_feet(slid))
    every = repair_features(slid)
    np.testing.assert_allclose(every, lock_feet(plant_feet(features_with_bone_lengths(slid))))


@pytest.mark.parametrize("offset_m", [0.2, -0.15])
def test_a_hovering_or_sunken_take_is_put_on_the_floor_and_nothing_else_moves(walk, offset_m):
    moved = walk.copy()
    moved[:, 3] += offset_m  # the root's height and every joint's (RIC keeps heights in world units)
    moved[:, RIC.start + 1:RIC.stop:3] += offset_m
    before, after = features_to_joints(moved), features_to_joints(put_on_floor(moved))
    assert before[..., 1].min() == pytest.approx(features_to_joints(walk)[..., 1].min() + offset_m)
    assert after[..., 1].min() == pytest.approx(0.0, abs=1e-9)  # the lowest joint over the take, on the floor
    np.testing.assert_allclose(after - before, np.broadcast_to([0.0, -before[..., 1].min(), 0.0], before.shape),
                               atol=1e-9)  # the whole take moves as one, straight up or down
    np.testing.assert_array_equal(put_on_floor(moved)[:, 67:], moved[:, 67:])  # rotations, velocities, contacts
    off = RepairConfig(bone_lengths=False, plant_feet=False, lock_feet=False)
    np.testing.assert_array_equal(repair_features(moved, off), moved)
    np.testing.assert_allclose(repair_features(moved, RepairConfig(on_floor=True)),
                               put_on_floor(repair_features(moved)))  # last, after the other repairs
    assert not RepairConfig().on_floor  # off unless a model's config turns it on


def test_pipeline_repairs_free_takes_only_when_asked(tmp_path):
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained(tiny_model(tmp_path / "m"))
    on = pipe(["a walk", "a wave"], 2.5, seed=[1, 2], num_inference_steps=2)
    off = pipe(["a walk", "a wave"], 2.5, seed=[1, 2], num_inference_steps=2, repair=False)
    assert not np.allclose(on.features, off.features)
    repaired = repair_rows(off.features, off.lengths.tolist(), pipe.config.repair)
    np.testing.assert_allclose(on.features, repaired, atol=1e-5)
    single = pipe("a wave", 2.5, seed=2, num_inference_steps=2)
    np.testing.assert_allclose(single.features[0], on.features[1], atol=1e-5)  # batch equals single runs
    pipe.config.repair = RepairConfig(bone_lengths=False, plant_feet=False, lock_feet=False)
    np.testing.assert_array_equal(pipe(["a walk", "a wave"], 2.5, seed=[1, 2], num_inference_steps=2).features,
                                  off.features)


@pytest.mark.parametrize("repair, words", [("on", "JSON object"), ({"plant_feet": "yes"}, "true or false"),
                                           ({"smooth_frames": -1}, ">= 0"), ({"feet": True}, "feet"),
                                           ({"lock_feet": 1}, "true or false"), ({"on_floor": "yes"}, "true or false"),
                                           ({"lock_release": 1.5}, "between 0 and 1"),
                                           ({"lock_min_knee_deg": 95}, "below 90"),
                                           ({"lock_max_double_support": 2}, "between 0 and 1"),
                                           ({"max_lock_shift_m": float("nan")}, ">= 0")])
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


def _knee_bend_deg(joints):
    """Each knee's bend (T, 2) in degrees: 0 = a straight leg."""
    return np.stack([knee_bend_deg(joints[:, hip], joints[:, knee], joints[:, ankle])
                     for hip, knee, ankle in ((1, 4, 7), (2, 5, 8))], axis=1)


def test_locking_holds_the_feet_a_sliding_root_drags(walk):
    slid = _sliding(walk)
    assert foot_skating_ratio(features_to_joints(slid)) == 1.0
    locked = lock_feet(slid)
    assert foot_skating_ratio(features_to_joints(locked)) < 0.35  # from 1.0: the stance feet stay put, mostly
    changed = np.flatnonzero(np.abs(locked - slid).max(axis=0) > 1e-9)
    legs = {4 + 3 * (j - 1) + k for j in (4, 5, 7, 8, 10, 11) for k in range(3)}  # knees, ankles, toes (RIC)
    assert set(changed.tolist()) <= legs  # the root, the rest of the body and the contact channels stay
    before, after = features_to_joints(slid), features_to_joints(locked)
    assert _bone_sd_mm(after) <= _bone_sd_mm(before) + 0.01  # the legs keep their bone lengths


def test_a_held_foot_never_straightens_the_knee(walk):
    slid = _sliding(walk)
    before = _knee_bend_deg(features_to_joints(slid))
    for limit in (5.0, 20.0):
        after = _knee_bend_deg(features_to_joints(lock_feet(slid, RepairConfig(lock_min_knee_deg=limit))))
        assert (after >= np.minimum(before, limit) - 0.05).all()  # never straighter than the limit or the take
    unlimited = _knee_bend_deg(features_to_joints(lock_feet(slid, RepairConfig(lock_min_knee_deg=0.0))))
    assert (unlimited < np.minimum(before, 5.0) - 0.05).any()  # without the limit a held foot locks the knee
    strict = lock_feet(slid, RepairConfig(lock_min_knee_deg=20.0))
    assert foot_skating_ratio(features_to_joints(strict)) > foot_skating_ratio(features_to_joints(lock_feet(slid)))


def test_locking_leaves_a_take_without_plants_as_it_is(walk):
    airborne = walk.copy()
    airborne[:, FOOT_CONTACT] = 0.0
    np.testing.assert_allclose(lock_feet(airborne), airborne, atol=1e-9)


def _standing_world(frames):
    """World joints (T, 22, 3) of a figure standing with bent knees (hips 0.9 m, knees 0.5 m up, 15 cm forward)."""
    world = np.zeros((frames, 22, 3))
    for hip, knee, ankle, toe, x in ((1, 4, 7, 10, 0.1), (2, 5, 8, 11, -0.1)):
        world[:, [hip, knee, ankle, toe], 0] = x
        world[:, [hip, knee, ankle], 1] = 0.9, 0.5, 0.1
        world[:, knee, 2], world[:, toe, 2] = 0.15, 0.14
    return world


def test_held_shifts_are_capped_and_let_go_in_the_air():
    world = _standing_world(30)
    world[:, :, 0] += np.arange(30)[:, None] * 0.04  # the whole body glides 4 cm per frame along x
    world[20:, [7, 10], 1] += 0.2  # the left foot lifts off at frame 20
    contact = np.zeros((30, 4))
    contact[:20, :2] = 1.0  # the left ankle and toe are planted until then; the right foot never is
    cfg = RepairConfig(max_lock_shift_m=0.25, lock_release=0.5)
    shifts = foot_hold_shifts(world, contact, cfg)  # (T, 2, 2)
    np.testing.assert_allclose(shifts[1:5, 0, 0], -0.04 * np.arange(1, 5))  # the planted foot is held in place
    assert np.linalg.norm(shifts[19, 0]) == pytest.approx(0.25)  # up to the cap
    np.testing.assert_allclose(shifts[20:23, 0, 0], -0.25 * 0.5 ** np.arange(1, 4))  # then let go in the air
    assert np.abs(shifts[:, 1]).max() == 0.0


def test_a_foot_still_on_the_floor_keeps_its_hold():
    world = _standing_world(30)
    world[:, :, 0] += np.arange(30)[:, None] * 0.04
    contact = np.zeros((30, 4))
    contact[:5, :2] = 1.0  # the left foot is planted for 5 frames, then its contact goes off while it stays down
    shifts = foot_hold_shifts(world, contact, RepairConfig())  # (T, 2, 2)
    np.testing.assert_allclose(shifts[4:, 0, 0], -0.16)  # no let-go on the floor: that would slide it


def test_a_take_that_shuffles_without_lifting_its_feet_is_not_locked(walk):
    slid = _sliding(walk)
    joints = features_to_joints(slid)
    shuffled = slid.copy()
    shuffled[:, FOOT_CONTACT] = 1.0  # every foot joint in contact all the time: only the low ones count as planted
    share = double_support_share(joints, shuffled[:, FOOT_CONTACT])
    assert share > double_support_share(joints, slid[:, FOOT_CONTACT])
    np.testing.assert_array_equal(lock_feet(shuffled, RepairConfig(lock_max_double_support=share - 0.01)), shuffled)
    assert np.abs(lock_feet(shuffled, RepairConfig(lock_max_double_support=share)) - shuffled).max() > 0.01


def test_a_shuffling_segment_is_not_held_but_a_stepping_one_is(walk):
    slid = _sliding(walk)
    n, spans = len(slid) // 2, [(0, len(slid) // 2), (len(slid) // 2, len(slid))]
    mixed = slid.copy()
    mixed[n:, FOOT_CONTACT] = 1.0  # the second segment shuffles: every low foot joint in contact
    joints = features_to_joints(mixed)
    cfg = RepairConfig(lock_max_double_support=0.5)
    assert double_support_share(joints[:n], mixed[:n, FOOT_CONTACT]) <= 0.5
    assert double_support_share(joints[n:], mixed[n:, FOOT_CONTACT]) > 0.5
    split = lock_feet(mixed, cfg, spans)
    assert np.abs(split[:n] - mixed[:n]).max() > 0.01  # the stepping segment is held
    unplanted = mixed.copy()
    unplanted[n:, FOOT_CONTACT] = 0.0  # the same take with no plant at all in the second segment
    np.testing.assert_allclose(split[:, RIC], lock_feet(unplanted, cfg, spans)[:, RIC])  # no new hold there
    step = np.linalg.norm(np.diff(features_to_joints(split)[:, [7, 8, 10, 11]], axis=0), axis=-1).max()
    assert step < 0.3  # no foot jumps where the segments meet: a hold carried into the shuffle is not dropped


def test_held_shifts_stop_where_the_leg_would_straighten():
    world = _standing_world(30)
    world[:, :, 0] += np.arange(30)[:, None] * 0.04
    contact = np.zeros((30, 4))
    contact[:, :2] = 1.0
    cfg = RepairConfig(max_lock_shift_m=1.0, lock_min_knee_deg=20.0)
    shifts = foot_hold_shifts(world, contact, cfg)  # (T, 2, 2)
    thigh, shin = np.hypot(0.4, 0.15), np.hypot(0.4, 0.15)
    reach = np.sqrt(thigh ** 2 + shin ** 2 + 2 * thigh * shin * np.cos(np.radians(20.0)))
    held_ankle = world[:, 7] + np.stack([shifts[:, 0, 0], np.zeros(30), shifts[:, 0, 1]], axis=1)
    distance = np.linalg.norm(held_ankle - world[:, 1], axis=-1)  # (T,) hip to the held ankle
    assert distance.max() == pytest.approx(reach, abs=1e-9)  # held up to the reach, not beyond
    assert np.linalg.norm(shifts[-1, 0]) == pytest.approx(np.sqrt(reach ** 2 - 0.8 ** 2), abs=1e-9)
