"""Retargeting math on synthetic and real rest poses (numpy only, no bpy)."""

from __future__ import annotations

import numpy as np
import pytest

from mld_core.rig import bone_maps as bm
from mld_core.rig import fidelity
from mld_core.rig import retarget as rt
from mld_core.motion import skeleton as sk

CLIPS = ("dataset-2_walk-turn-left_normal_027", "dataset-2_wave-right-hand_normal_026", "dataset-1_bye_normal_001")
FIXTURE_RIGS = ("canonical", "rigify_metarig", "rigify", "bandai_bvh")
J = rt.JOINT_INDEX


@pytest.fixture
def takes(fixtures):
    stored = np.load(fixtures / "rigs" / "source_takes.npz")
    return {c: stored[f"{c}_joints"].astype(np.float64) for c in CLIPS}


@pytest.fixture
def golden(fixtures):
    return np.load(fixtures / "humanml3d" / "new_joints_012314.npy").astype(np.float64)  # (170, 22, 3)


def _fixture_rig(fixtures, name):
    rig = rt.RigRest.load(fixtures / "rigs" / f"{name}.json")
    bmap = bm.detect_bone_map(rig.names, rig.parents).bone_map
    return rig, bmap


def _rig_and_map(fixtures, rig_name):
    """(rig, joint -> bone map, parent overrides) for a fixture rig or a synthetic canonical-named one."""
    if rig_name in SYNTHETIC:
        return SYNTHETIC[rig_name], {n: n for n in rt.JOINT_NAMES}, {}
    rig, bmap = _fixture_rig(fixtures, rig_name)
    return rig, bmap.joints, bmap.parent_overrides


def _random_roll(rig: rt.RigRest, rng) -> rt.RigRest:
    """The same rig with every bone rolled by a random angle about its own Y axis (heads and tails unchanged)."""
    mats = rig.matrices.copy()
    for i in range(len(mats)):
        mats[i, :3, :3] = mats[i, :3, :3] @ rt.axis_angle_matrix(np.array([0.0, 1.0, 0.0]), rng.uniform(-np.pi, np.pi))
    return rt.RigRest(rig.names, rig.parents, mats, rig.tails, rig.object_matrix, name=rig.name)


def _posed_canonical(arm_dir_left, *, leg_spread=0.0, rolls=None, object_matrix=None, units=1.0) -> rt.RigRest:
    """A canonical-named rig whose arms point along ``arm_dir_left`` (mirrored for the right arm) at rest."""
    base = rt.canonical_rig()
    heads = base.heads.copy()
    for side, sx in (("left", 1.0), ("right", -1.0)):
        d = np.array(arm_dir_left, dtype=float) * np.array([sx, 1.0, 1.0])
        d /= np.linalg.norm(d)
        s, e, w = (J[f"{side}_{n}"] for n in ("shoulder", "elbow", "wrist"))
        upper = np.linalg.norm(heads[e] - heads[s])
        fore = np.linalg.norm(heads[w] - heads[e])
        heads[e] = heads[s] + upper * d
        heads[w] = heads[e] + fore * d
        h, k, a, f = (J[f"{side}_{n}"] for n in ("hip", "knee", "ankle", "foot"))
        tilt = np.array([sx * np.sin(leg_spread), 0.0, -np.cos(leg_spread)])
        for child, parent in ((k, h), (a, k)):
            length = np.linalg.norm(base.heads[child] - base.heads[parent])
            heads[child] = heads[parent] + length * tilt
            if child == a:
                heads[f] = heads[a] + (base.heads[f] - base.heads[a])
    tails = heads.copy()
    for j, name in enumerate(rt.JOINT_NAMES):
        child = rt.CHAIN_CHILD.get(name)
        tails[j] = heads[J[child]] if child else heads[j] + (base.tails[j] - base.heads[j])
        if np.linalg.norm(tails[j] - heads[j]) < 1e-4:
            tails[j] = heads[j] + np.array([0.0, 0.0, 0.05])
    return rt.rig_from_heads(
        list(rt.JOINT_NAMES), list(sk.PARENTS), heads * units, tails * units, rolls=rolls, object_matrix=object_matrix
    )


def _synthetic_rigs():
    rng = np.random.default_rng(7)
    rolls = rng.uniform(-np.pi, np.pi, len(rt.JOINT_NAMES))
    mixamo_like = np.eye(4)  # armature space Y up in centimetres, object turned +90 deg about X and scaled 0.01
    mixamo_like[:3, :3] = rt.axis_angle_matrix(np.array([1.0, 0.0, 0.0]), np.pi / 2) * 0.01
    mixamo_like[:3, 3] = [1.5, -2.0, 0.3]
    to_y_up = rt.axis_angle_matrix(np.array([1.0, 0.0, 0.0]), -np.pi / 2)
    tpose = _posed_canonical([1, 0, 0], rolls=rolls)
    mats = tpose.matrices.copy()  # the same bones expressed in a Y-up centimetre armature space
    mats[:, :3, :3] = to_y_up @ mats[:, :3, :3]
    mats[:, :3, 3] = tpose.heads @ to_y_up.T * 100
    y_up_cm = rt.RigRest(tpose.names, tpose.parents, mats, tpose.tails @ to_y_up.T * 100, mixamo_like)
    return {
        "tpose_rolled": tpose,
        "apose_rolled": _posed_canonical([1, 0, -1], leg_spread=0.15, rolls=rolls),
        "arms_forward": _posed_canonical([0.2, -1, -0.3], rolls=rolls[::-1]),
        "tpose_y_up_cm": y_up_cm,
    }


SYNTHETIC = _synthetic_rigs()


def _segment_directions(result: rt.RetargetResult, bmap: dict) -> list[tuple[str, float]]:
    """Worst angle (deg) between each posed segment of the rig and the placed source's, per segment."""
    wj = result.world_joints()
    src = result.source_world
    heads = {j: result.rig.heads[result.rig.index(b)] for j, b in bmap.items()}
    out = []
    for joint in bmap:
        end = rt._segment_end(joint, bmap, heads, 1e-6)
        if end is None:
            continue
        a = rt.normalize(wj[end] - wj[joint])
        b = rt.normalize(src[:, J[end]] - src[:, J[joint]])
        out.append((joint, float(np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1))).max())))
    return out


@pytest.mark.parametrize("rig_name", sorted(SYNTHETIC))
def test_directions_mode_reproduces_source_directions_on_rotated_and_a_pose_rests(rig_name, takes):
    rig = SYNTHETIC[rig_name]
    bmap = {n: n for n in rt.JOINT_NAMES}
    for clip in CLIPS[:2]:
        result = rt.retarget(takes[clip], rig, bmap, rt.RetargetOptions(match="directions"))
        worst = max(err for _, err in _segment_directions(result, bmap))
        assert worst < 1e-4, (rig_name, clip, _segment_directions(result, bmap))


@pytest.mark.parametrize("rig_name", FIXTURE_RIGS)
def test_directions_mode_on_real_rest_poses(fixtures, rig_name, golden):
    rig, bmap = _fixture_rig(fixtures, rig_name)
    result = rt.retarget(golden, rig, bmap.joints, rt.RetargetOptions(match="directions"),
                         parent_overrides=bmap.parent_overrides)
    errors = _segment_directions(result, bmap.joints)
    assert max(e for _, e in errors) < 1e-4, errors


@pytest.mark.parametrize("rig_name", FIXTURE_RIGS + tuple(sorted(SYNTHETIC)))
def test_effectors_follow_the_source_continuously(fixtures, rig_name, takes, golden):
    rig, joints, overrides = _rig_and_map(fixtures, rig_name)
    for name, take in [*takes.items(), ("golden", golden)]:
        result = rt.retarget(take, rig, joints, parent_overrides=overrides)
        fid = fidelity.fidelity(result)
        assert fid["effector_err_mean"] < 0.05, (name, fid)
        for eff in ("left_wrist", "right_wrist", "head"):
            assert fid[f"{eff}_err"] < 0.05, (name, eff, fid)
        # Arms are solved as two-bone chains: the hands land exactly where the scaled source arm puts them.
        assert fid["left_wrist_err_max"] < 1e-6 and fid["right_wrist_err_max"] < 1e-6, (name, fid)
        assert fid["sink_cm"] < 1.0, (name, fid)
        assert fid["facing_err_deg"] < 1.0, (name, fid)
        assert abs(fid["turn_rig_deg"] - fid["turn_src_deg"]) < 1.0, (name, fid)
        assert fid["travel_angle_deg"] < 1.0 and abs(fid["travel_rig_m"] - fid["travel_src_m"]) < 1e-6
        # Continuous keys: no sign flips, no jumps (the golden sample whirls an arm 60-90 degrees a frame).
        dots = np.sum(result.rotations[1:] * result.rotations[:-1], -1)
        assert np.all(dots > 0), (name, "sign flip between frames")
        if name != "golden":
            step = np.degrees(2 * np.arccos(np.clip(dots, -1, 1)))
            assert step.max() < 45, (name, step.max())  # a walking knee turns up to ~30 degrees a frame


@pytest.mark.parametrize("rig_name", ("canonical", "rigify_metarig", "bandai_bvh", "tpose_y_up_cm"))
def test_planted_toes_stay_on_the_floor_when_the_source_foot_changes_length(fixtures, rig_name, takes, golden):
    """Generated joints do not keep bone lengths: a source foot shorter than the rig's (and varying) must not push
    the rig's toes into the floor while they are down, and a lifted foot still points where the source's does."""
    rig, joints, overrides = _rig_and_map(fixtures, rig_name)
    lifted_checked = 0
    for take in (takes["dataset-2_walk-turn-left_normal_027"].copy(), golden.copy()):
        T = len(take)
        shrink = 0.6 + 0.15 * np.sin(np.arange(T) / 5.0)  # (T,) the foot 45-75% of its length, changing
        for side in ("left", "right"):
            ankle, toe = J[f"{side}_ankle"], J[f"{side}_foot"]
            take[:, toe] = take[:, ankle] + shrink[:, None] * (take[:, toe] - take[:, ankle])
        result = rt.retarget(take, rig, joints, parent_overrides=overrides)
        fid = fidelity.fidelity(result)
        assert fid["sink_cm"] < 0.01, fid
        assert fid["effector_err_mean"] < 0.05, fid
        wj, src = result.world_joints(), result.source_world
        units = result.scale  # world units per source metre
        for side in ("left", "right"):
            ankle, toe = f"{side}_ankle", f"{side}_foot"
            z = src[:, J[toe], 2]
            planted = z <= np.percentile(z, 5) + rt.TOE_DOWN_M[0] * units
            lifted = z > np.percentile(z, 5) + rt.TOE_DOWN_M[1] * units
            # Planted: the rig's toe exactly as high as the source's (neither sinking nor floating).
            np.testing.assert_allclose(wj[toe][planted, 2], z[planted], atol=1e-6 * units)
            # Aiming the rig's (longer) foot along the source's foot would have sunk it by more than 1 cm.
            length = np.linalg.norm(wj[toe] - wj[ankle], axis=-1)
            aimed = wj[ankle] + length[:, None] * rt.normalize(src[:, J[toe]] - src[:, J[ankle]])
            assert np.max(z[planted] - aimed[planted, 2]) > 0.01 * units
            # Lifted: the foot points along the source's foot.
            cos = np.sum(rt.normalize(wj[toe] - wj[ankle]) * rt.normalize(src[:, J[toe]] - src[:, J[ankle]]), -1)
            assert np.all(cos[lifted] > 1 - 1e-9), cos[lifted].min()
            lifted_checked += int(lifted.sum())
    assert lifted_checked > 5


@pytest.mark.parametrize("rig_name", ("canonical", "rigify_metarig", "tpose_y_up_cm"))
def test_feet_never_go_below_their_rest_height_on_standing_rigs(fixtures, rig_name, takes):
    """Generated feet dip below their own standing height now and then: on a rig whose rest stands, no ankle or
    toe goes lower than it stands at rest (the floor), and the rest of the take is untouched."""
    rig, joints, overrides = _rig_and_map(fixtures, rig_name)
    take = takes["dataset-2_walk-turn-left_normal_027"].copy()
    dip = 0.04 * np.exp(-0.5 * ((np.arange(len(take)) - 20) / 3.0) ** 2)  # (T,) a 4 cm dip around frame 20
    for name in ("left_ankle", "left_foot", "right_ankle", "right_foot"):
        take[:, J[name], 1] -= dip
    standing = rt.standing_heights(rig, joints)
    assert standing is not None
    plain = rt.retarget(take, rig, joints, rt.RetargetOptions(floor=False), parent_overrides=overrides)
    result = rt.retarget(take, rig, joints, parent_overrides=overrides)
    rest = rt._to_world(result.rig, result.rig.heads)
    wj = result.world_joints()
    below = {j: float(np.max(rest[result.rig.index(joints[j]), 2] - wj[j][:, 2])) for j in standing}
    assert max(below.values()) < 1e-6 * result.scale, below
    assert fidelity.fidelity(result)["below_rest_height_cm"] < 1e-4
    # Without the floor the dip goes through it.
    wp = plain.world_joints()
    assert max(float(np.max(rest[plain.rig.index(joints[j]), 2] - wp[j][:, 2])) for j in standing) > 0.02 * plain.scale
    # Only the feet are lifted: the hands follow the same source either way.
    for j in ("left_wrist", "right_wrist", "head"):
        np.testing.assert_allclose(wj[j], wp[j] + (wj["pelvis"] - wp["pelvis"]), atol=1e-6 * result.scale)


def test_the_floor_holds_on_a_rig_whose_origin_is_at_its_hips(takes):
    """Most mocap BVH rigs rest with the root at the object origin and the feet about 0.9 m below it. The take stands
    on the origin plane like on any rig; its dipping feet must be held at their standing heights above that plane,
    not at their absolute rest heights (0.9 m lower, so the floor never held and toes went through)."""
    canonical = rt.canonical_rig()
    drop = np.eye(4)
    drop[2, 3] = -canonical.heads[canonical.index("pelvis"), 2]  # the hips at the origin, the feet below it
    rig = rt.RigRest(canonical.names, canonical.parents, drop @ canonical.matrices, canonical.tails + drop[:3, 3])
    joints = {n: n for n in canonical.names}
    take = takes["dataset-2_walk-turn-left_normal_027"].copy()
    dip = 0.04 * np.exp(-0.5 * ((np.arange(len(take)) - 20) / 3.0) ** 2)  # (T,) a 4 cm dip around frame 20
    for name in ("left_ankle", "left_foot", "right_ankle", "right_foot"):
        take[:, J[name], 1] -= dip
    standing = rt.standing_heights(rig, joints)
    assert standing is not None and all(0 <= h < 0.2 for h in standing.values())
    result = rt.retarget(take, rig, joints)
    wj = result.world_joints()
    below = max(float(np.max(standing[j] - wj[j][:, 2])) for j in standing)  # the origin plane is z = 0
    assert below < 1e-6, below
    assert fidelity.fidelity(result)["below_rest_height_cm"] < 1e-4
    plain = rt.retarget(take, rig, joints, rt.RetargetOptions(floor=False))
    assert max(float(np.max(standing[j] - plain.world_joints()[j][:, 2])) for j in standing) > 0.02


def test_walk_turn_keeps_its_direction_and_turn(fixtures, takes):
    rig, bmap = _fixture_rig(fixtures, "rigify_metarig")
    take = takes["dataset-2_walk-turn-left_normal_027"]
    result = rt.retarget(take, rig, bmap.joints)
    fid = fidelity.fidelity(result)
    assert fid["turn_src_deg"] > 60  # the clip turns left (counter-clockwise seen from above)
    assert abs(fid["turn_rig_deg"] - fid["turn_src_deg"]) < 1.0
    # Facing -Y at frame 0 (Blender's front view), as the source faces +Z.
    yaw = fidelity.facing_yaw(result.world_joints()["left_hip"], result.world_joints()["right_hip"])
    assert abs(np.degrees(yaw[0])) < 20
    turned = rt.retarget(take, rig, bmap.joints, rt.RetargetOptions(yaw_deg=90))
    yaw90 = fidelity.facing_yaw(turned.world_joints()["left_hip"], turned.world_joints()["right_hip"])
    np.testing.assert_allclose(rt.wrap_angle(yaw90 - yaw), np.radians(90), atol=1e-6)


def test_root_translation_scaled_by_leg_length(fixtures, golden):
    small = _posed_canonical([1, 0, -1])
    big = _posed_canonical([1, 0, -1], units=2.0)
    bmap = {n: n for n in rt.JOINT_NAMES}
    a = rt.retarget(golden, small, bmap)
    b = rt.retarget(golden, big, bmap)
    assert b.scale == pytest.approx(2 * a.scale)
    np.testing.assert_allclose(b.root_location, 2 * a.root_location, atol=1e-9)
    np.testing.assert_allclose(b.rotations, a.rotations, atol=1e-9)
    src = rt.leg_length({n: golden[:, J[n]] for n in rt.JOINT_NAMES})
    rig = rt.leg_length({n: small.heads[J[n]] for n in rt.JOINT_NAMES})
    assert a.scale == pytest.approx(rig / np.median(src))
    # The hips' midpoint travels as the scaled source's does.
    hips = (a.world_joints()["left_hip"] + a.world_joints()["right_hip"]) / 2
    src_hips = (golden[:, J["left_hip"]] + golden[:, J["right_hip"]]) / 2 @ rt.Y_UP_TO_Z_UP.T
    np.testing.assert_allclose(hips[:, :2] - hips[0, :2], a.scale * (src_hips[:, :2] - src_hips[0, :2]), atol=1e-9)


def test_object_transform_does_not_change_the_pose(takes):
    """A rig in centimetres, Y up, under an object turned 90 degrees and scaled 0.01 (how Mixamo FBX files arrive)
    plays the same world motion and the same pose-bone rotations as the plain Z-up metre rig."""
    plain, cm = SYNTHETIC["tpose_rolled"], SYNTHETIC["tpose_y_up_cm"]
    bmap = {n: n for n in rt.JOINT_NAMES}
    take = takes["dataset-2_walk-turn-left_normal_027"]
    a = rt.retarget(take, plain, bmap)
    b = rt.retarget(take, cm, bmap)
    np.testing.assert_allclose(b.rotations, a.rotations, atol=1e-7)
    offset = cm.object_matrix[:3, 3]
    for joint, pos in a.world_joints().items():
        np.testing.assert_allclose(b.world_joints()[joint] - offset, pos, atol=1e-7)


def test_unmapped_bones_stay_at_rest(fixtures, takes):
    rig, bmap = _fixture_rig(fixtures, "rigify_metarig")
    joints = {j: b for j, b in bmap.joints.items() if j in bm.REQUIRED_JOINTS}
    result = rt.retarget(takes["dataset-2_wave-right-hand_normal_026"], rig, joints)
    assert sorted(result.bones) == sorted(joints.values())
    rot, loc = result.full_pose()
    mapped = {rig.index(b) for b in joints.values()}
    for i in range(len(rig.names)):
        if i not in mapped:
            np.testing.assert_array_equal(rot[:, i], np.tile([1.0, 0, 0, 0], (len(rot), 1)))
            np.testing.assert_array_equal(loc[:, i], 0.0)
    # Still follows: with the spine, neck, collars and toes unmapped, hands and feet land where they should.
    fid = fidelity.fidelity(result)
    assert fid["left_wrist_err"] < 1e-6 and fid["effector_err_mean"] < 0.05, fid


def test_elbow_bends_about_one_axis(takes):
    """The upper arm's twist follows the elbow's hinge: the forearm then turns about a fixed axis of its own."""
    rig = SYNTHETIC["apose_rolled"]
    bmap = {n: n for n in rt.JOINT_NAMES}
    take = takes["dataset-2_wave-right-hand_normal_026"]
    result = rt.retarget(take, rig, bmap, rt.RetargetOptions(match="directions"))
    k = result.bones.index("right_elbow")
    q = result.rotations[:, k]
    angle = 2 * np.arccos(np.clip(np.abs(q[:, 0]), 0, 1))
    axis = rt.normalize(q[:, 1:] * np.sign(q[:, :1]))
    bent = angle > np.radians(30)
    assert bent.sum() > 5
    ref = rt.normalize(np.median(axis[bent], axis=0))
    assert np.min(np.abs(axis[bent] @ ref)) > 0.98
    # Without twist references the same motion needs a wandering axis (the test can tell the difference).
    flat = rt.retarget(take, rig, bmap, rt.RetargetOptions(match="directions", twist=False))
    qf = flat.rotations[:, k]
    axf = rt.normalize(qf[:, 1:] * np.sign(qf[:, :1]))
    reff = rt.normalize(np.median(axf[bent], axis=0))
    assert np.min(np.abs(axf[bent] @ reff)) < np.min(np.abs(axis[bent] @ ref))


def test_pose_matches_blender_convention_on_a_two_bone_chain():
    # Bone a along +Y from the origin, bone b along +X from (0, 1, 0), child of a.
    rig = rt.rig_from_heads(["a", "b"], [-1, 0], np.array([[0, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 0], [1, 1, 0.0]]))
    quarter = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])  # +90 degrees about the bone's local Z
    rot = np.array([[quarter, [1.0, 0, 0, 0]]])
    loc = np.array([[[0.0, 0.0, 0.5], [0.0, 0.0, 0.0]]])
    pose = rt.fk(rig, rot, loc)
    # a's local Z is world Z, so a turns to point along -X; its head moves along its local Z by 0.5.
    np.testing.assert_allclose(pose[0, 0, :3, 3], [0, 0, 0.5], atol=1e-12)
    np.testing.assert_allclose(pose[0, 0, :3, 1], [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(pose[0, 1, :3, 3], [-1, 0, 0.5], atol=1e-12)
    np.testing.assert_allclose(pose[0, 1, :3, 1], [0, 1, 0], atol=1e-12)  # +X turned 90 degrees about Z
    np.testing.assert_allclose(rt.fk(rig)[0], rig.matrices, atol=1e-12)


def test_canonical_rig_matches_blender_edit_bones(fixtures):
    """rig_from_heads follows Blender's bone-roll convention: same rest matrices as the armature bpy built."""
    built = rt.RigRest.load(fixtures / "rigs" / "canonical.json")
    ours = rt.canonical_rig()
    for name in rt.JOINT_NAMES:
        np.testing.assert_allclose(ours.matrices[ours.index(name)], built.matrices[built.index(name)], atol=1e-5)
        assert ours.parent_name(name) == built.parent_name(name)


def test_rig_rest_round_trip(tmp_path, fixtures):
    rig, _ = _fixture_rig(fixtures, "bandai_bvh")
    rig.save(tmp_path / "rig.json")
    back = rt.RigRest.load(tmp_path / "rig.json")
    assert back.names == rig.names
    np.testing.assert_array_equal(back.parents, rig.parents)
    np.testing.assert_allclose(back.matrices, rig.matrices, atol=2e-6)
    np.testing.assert_allclose(back.object_matrix, rig.object_matrix)


def test_quaternion_helpers_round_trip():
    rng = np.random.default_rng(0)
    q = rt.normalize(rng.normal(size=(500, 4)))
    q = np.where(q[:, :1] < 0, -q, q)
    np.testing.assert_allclose(rt.matrix_to_quat(rt.quat_to_matrix(q)), q, atol=1e-9)
    a = rt.normalize(rng.normal(size=(500, 3)))
    b = rt.normalize(rng.normal(size=(500, 3)))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rt.rotation_between(a, b), a), b, atol=1e-9)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rt.rotation_between(a, -a), a), -a, atol=1e-9)


def test_bad_input_is_refused_with_a_reason(fixtures, golden):
    rig, bmap = _fixture_rig(fixtures, "rigify_metarig")
    partial = {j: b for j, b in bmap.joints.items() if j not in ("left_knee", "head")}
    with pytest.raises(rt.RetargetError, match="left_knee, head"):
        rt.retarget(golden, rig, partial)
    with pytest.raises(rt.RetargetError, match="no bones named: nope"):
        rt.retarget(golden, rig, {**bmap.joints, "head": "nope"})
    with pytest.raises(rt.RetargetError, match="shape"):
        rt.retarget(golden[:, :21], rig, bmap.joints)
    bad = golden.copy()
    bad[3, 4, 1] = np.nan
    with pytest.raises(rt.RetargetError, match="NaN"):
        rt.retarget(bad, rig, bmap.joints)
    with pytest.raises(rt.RetargetError, match="more than one joint"):
        rt.retarget(golden, rig, {**bmap.joints, "spine2": bmap.joints["spine1"]})


def test_single_frame_take(fixtures, golden):
    rig, bmap = _fixture_rig(fixtures, "bandai_bvh")
    result = rt.retarget(golden[:1], rig, bmap.joints)
    assert result.rotations.shape == (1, len(bmap.joints), 4)
    assert np.all(np.isfinite(result.root_location))


def test_a_shorter_leg_bends_like_the_source_instead_of_snapping_straight(takes):
    """A rig whose left leg is 2% shorter (its shin 4%): the take is scaled by the mean leg length, so the short
    leg's ankle target was out of reach where the source's leg is nearly straight, and its knee locked. Its foot is
    now drawn up the leg to the source's extension: the knee bends as the source's does, feet never sink."""
    offsets = np.array(sk.REFERENCE_OFFSETS, dtype=np.float64)
    offsets[J["left_ankle"]] *= 0.96
    rig = rt.canonical_rig(offsets)
    joints = {n: n for n in rig.names}
    for clip in ("dataset-2_walk-turn-left_normal_027", "dataset-2_wave-right-hand_normal_026"):
        take = takes[clip].copy()
        stretch = take[:, J["left_ankle"]] - take[:, J["left_knee"]]
        take[:, J["left_ankle"]] += 0.05 * stretch  # a straighter source leg: the short rig leg cannot reach it
        take[:, J["left_foot"]] += 0.05 * stretch
        result = rt.retarget(take, rig, joints)
        fid = fidelity.fidelity(result)
        wj, src = result.world_joints(), result.source_world
        bend_rig = fidelity.knee_bend_deg(wj["left_hip"], wj["left_knee"], wj["left_ankle"])
        bend_src = fidelity.knee_bend_deg(src[:, J["left_hip"]], src[:, J["left_knee"]], src[:, J["left_ankle"]])
        assert np.mean(np.abs(bend_rig - bend_src)) < 1.0, (clip, np.mean(np.abs(bend_rig - bend_src)))
        assert fid["locked_knee_frac"] == 0.0 and fid["sink_cm"] < 1e-6


def iclone_like_rig(names: dict | None = None) -> rt.RigRest:
    """The canonical skeleton with iClone's trunk: a "Hip" root from which both the "pelvis" bone (carrying the
    thighs) and the spine hang. ``names``: canonical joint -> bone name (default: the joint names)."""
    base = rt.canonical_rig()
    pelvis = base.index("pelvis")
    names = ["Hip"] + [(names or {}).get(n, n) for n in base.names]
    parents = [-1] + [p + 1 if p >= 0 else 0 for p in base.parents]
    parents[1 + base.index("spine1")] = 0  # the spine beside the pelvis bone, not below it
    heads = np.concatenate([base.heads[pelvis:pelvis + 1] - [0.0, 0.0, 0.02], base.heads])
    tails = np.concatenate([base.heads[pelvis:pelvis + 1], base.tails])
    return rt.rig_from_heads(names, parents, heads, tails)


def test_a_pelvis_beside_the_spine_hands_the_root_motion_to_the_bone_both_hang_from(takes):
    """iClone rigs: Hip -> Pelvis -> thighs and Hip -> Waist -> spine. Keying the root motion on the mapped pelvis left
    the whole trunk at the origin (Blender played the head metres from the take). The bone both hang from carries it
    now; the pelvis bone between it and the thighs stays at rest."""
    rig = iclone_like_rig()
    joints = {n: n for n in rt.JOINT_NAMES}
    result = rt.retarget(takes["dataset-2_walk-turn-left_normal_027"], rig, joints)
    assert result.root_bone == "Hip" and "pelvis" not in result.bones
    fid = fidelity.fidelity(result)
    assert fid["head_err"] < 0.01 and fid["effector_err_mean"] < 0.02
    unrelated = dict(joints, pelvis="left_wrist")  # no bone both hang from that is free: a clear error
    with pytest.raises(rt.RetargetError, match="does not carry"):
        rt.check_bone_map({**unrelated, "left_wrist": "Hip"}, rig)


def test_daz_names_map_collar_and_upper_arm():
    names = ["hip", "abdomen", "chest", "neck", "head", "lCollar", "lShldr", "lForeArm", "lHand", "rCollar", "rShldr",
             "rForeArm", "rHand", "lButtock", "lThigh", "lShin", "lFoot", "rButtock", "rThigh", "rShin", "rFoot"]
    parents = [None, "hip", "abdomen", "chest", "neck", "chest", "lCollar", "lShldr", "lForeArm", "chest", "rCollar",
               "rShldr", "rForeArm", "hip", "lButtock", "lThigh", "lShin", "hip", "rButtock", "rThigh", "rShin"]
    j = bm.detect_bone_map(names, parents).bone_map.joints
    assert (j["left_collar"], j["left_shoulder"], j["left_elbow"]) == ("lCollar", "lShldr", "lForeArm")
    assert (j["pelvis"], j["left_hip"], j["right_knee"]) == ("hip", "lThigh", "rShin")
