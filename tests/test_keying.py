"""Keying a take onto a rig without bpy (mld_core.rig.keying): the options, the one road, bone map <-> panel rows, the
messages that name missing bones, the detection cache, foot contacts of a take, batch argument checks."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from mld_core.rig import bone_maps as bm
from mld_core.rig import keyframes as ke
from mld_core.rig import retarget as rt
from mld_core.rig import bone_map_rows as map_rows
from mld_core.rig import keying as rw
from mld_core.motion.skeleton import JOINT_NAMES


@pytest.fixture
def rigify_metarig(fixtures):
    return rt.RigRest.load(fixtures / "rigs" / "rigify_metarig.json")


def test_options_map_onto_bake_options():
    opts = rw.RetargetSettings(reduce=True, tolerance_deg=1.5, rotation_mode="ZXY", foot_lock=True, nla=True)
    bake = opts.bake_options(fps=24, frame_start=7)
    assert isinstance(bake, ke.BakeOptions)
    assert (bake.fps, bake.frame_start, bake.rotation_mode, bake.reduce, bake.rot_tolerance_deg, bake.foot_lock) == (
        24.0, 7.0, "ZXY", True, 1.5, True)
    assert bake.interpolation == "BEZIER" and bake.loc_tolerance == ke.BakeOptions().loc_tolerance
    assert opts.rotation_modes({"a": "XYZ"}, ["a"]) is None  # one mode for every bone
    assert opts.to_dict() == {"reduce": True, "tolerance_deg": 1.5, "rotation_mode": "ZXY", "foot_lock": True,
                              "nla": True, "match": "effectors"}
    default = rw.RetargetSettings().bake_options(30, 1)
    assert default.reduce is False and default.rotation_mode == "QUATERNION" and default.foot_lock is False


def test_keep_rigs_rotation_modes():
    keep = rw.RetargetSettings(rotation_mode="KEEP")
    assert keep.bake_options(20, 1).rotation_mode == "QUATERNION"
    current = {"Hips": "ZXY", "Spine": "QUATERNION", "Arm": "AXIS_ANGLE", "Other": "XYZ"}
    assert keep.rotation_modes(current, ["Hips", "Spine", "Arm", "Missing"]) == {
        "Hips": "ZXY", "Spine": "QUATERNION", "Arm": "QUATERNION", "Missing": "QUATERNION"}


def test_settings_from_the_panel_and_bad_values():
    panel = SimpleNamespace(reduce_keys=True, reduce_tolerance=0.25, rotation_mode="XYZ", foot_lock=False, push_nla=True)
    assert rw.RetargetSettings.from_settings(panel) == rw.RetargetSettings(True, 0.25, "XYZ", False, True)
    assert rw.RetargetSettings.from_settings(SimpleNamespace()) == rw.RetargetSettings()
    with pytest.raises(ValueError, match="rotation mode must be one of"):
        rw.RetargetSettings(rotation_mode="EULER")
    with pytest.raises(ValueError, match="tolerance"):
        rw.RetargetSettings(tolerance_deg=0)
    assert [c[0] for c in rw.ROTATION_CHOICES] == ["QUATERNION", *ke.EULER_ORDERS, "KEEP"]


@pytest.mark.parametrize(
    "canonical, opts, modes, expected",
    [
        (True, rw.RetargetSettings(), None, False),  # the canonical rig's exact path is the default
        (True, rw.RetargetSettings(nla=True), None, False),
        (True, rw.RetargetSettings(reduce=True), None, True),
        (True, rw.RetargetSettings(rotation_mode="XYZ"), None, True),
        (True, rw.RetargetSettings(foot_lock=True), None, True),
        (True, rw.RetargetSettings(rotation_mode="KEEP"), {"pelvis": "QUATERNION"}, False),
        (True, rw.RetargetSettings(rotation_mode="KEEP"), {"pelvis": "YXZ"}, True),
        (False, rw.RetargetSettings(), None, True),  # every other rig goes through its bone map
    ],
)
def test_which_rigs_go_through_keyedit(canonical, opts, modes, expected):
    assert rw.uses_keyedit(canonical, opts, modes) is expected


def test_map_rows_round_trip_keeps_extras(fixtures, rigify_metarig):
    det = bm.detect_bone_map(rigify_metarig.names, list(rigify_metarig.parents))
    rows = map_rows.map_to_rows(det.bone_map)
    assert [r.joint for r in rows] == list(JOINT_NAMES)
    assert {r.joint for r in rows if r.required} == set(bm.REQUIRED_JOINTS)
    assert all(r.bone for r in rows)
    extras = map_rows.map_extras(det.bone_map)
    back = map_rows.rows_to_map(rows, extras)
    assert back.joints == det.bone_map.joints and back.source == "rigify_metarig"
    # Rigify's generated rig: its pose properties (IK/FK switches) and parent overrides survive the panel
    rigify = rt.RigRest.load(fixtures / "rigs" / "rigify.json")
    gen = bm.detect_bone_map(rigify.names, list(rigify.parents)).bone_map
    assert gen.pose_properties and gen.parent_overrides
    back = map_rows.rows_to_map(map_rows.map_to_rows(gen), map_rows.map_extras(gen))
    assert back.pose_properties == gen.pose_properties and back.parent_overrides == gen.parent_overrides
    assert json.loads(map_rows.map_extras(gen))["format"] == map_rows.MAP_FORMAT


def test_rows_from_pairs_drop_empty_bones_and_stale_overrides():
    extras = json.dumps({"source": "user", "parent_overrides": {"Arm": "Clavicle", "Gone": "X"}, "pose_properties": {}})
    m = map_rows.rows_to_map([("pelvis", "Hips"), ("left_shoulder", "Arm"), ("left_knee", "")], extras)
    assert m.joints == {"pelvis": "Hips", "left_shoulder": "Arm"} and m.parent_overrides == {"Arm": "Clavicle"}
    assert map_rows.rows_to_map([("pelvis", "Hips")], "{broken").source == "user"  # bad extras: a plain map
    assert map_rows.map_to_rows(None)[0] == map_rows.MapRow("pelvis", "", True)
    with pytest.raises(bm.BoneMapError, match="unknown joint"):
        map_rows.rows_to_map([("tail", "Tail")])


def test_missing_required_bones_are_named(rigify_metarig):
    det = bm.detect_bone_map(rigify_metarig.names, list(rigify_metarig.parents))
    assert rw.map_problem(det.bone_map, rigify_metarig.names, "metarig") == ""
    joints = dict(det.bone_map.joints)
    del joints["left_knee"], joints["head"]
    joints["right_wrist"] = "no_such_bone"
    broken = bm.BoneMap(joints)
    problem = rw.map_problem(broken, rigify_metarig.names, "metarig")
    assert problem.startswith("'metarig': ") and "left_knee" in problem and "head" in problem
    assert "right_wrist -> 'no_such_bone'" in problem and "Retarget panel" in problem
    assert "Nothing was keyed" not in problem  # a poll message: nothing was attempted
    with pytest.raises(bm.BoneMapError) as err:
        broken.validate(rigify_metarig.names)
    message = rw.missing_message(err.value, "metarig")
    assert "left_knee" in message and "head" in message and message.endswith("Nothing was keyed.")
    # keyedit refuses the same map before computing anything
    with pytest.raises(bm.BoneMapError):
        ke.take_to_keys(np.zeros((3, 22, 3)), rigify_metarig, broken, bake_options=rw.RetargetSettings().bake_options(20, 1))


def test_detection_is_cached_per_rig(rigify_metarig):
    cache = rw.DetectionCache(size=2)
    names, parents = rigify_metarig.names, list(rigify_metarig.parents)
    first = cache.get(names, parents)
    assert cache.get(list(names), list(parents)) is first and cache.runs == 1
    renamed = [n + "_x" if n == "thigh.L" else n for n in names]
    assert cache.get(renamed, parents) is not first and cache.runs == 2
    cache.get(["a"], [-1])
    cache.get(names, parents)  # evicted (size 2): computed again
    assert cache.runs == 4


def test_canonical_rig_through_keyedit_uses_the_canonical_preset():
    rig = rt.canonical_rig()
    m = rw.canonical_map(rig.names)
    assert m.source == "canonical" and m.joints == {j: j for j in JOINT_NAMES}


def _walk(frames=40):
    """A canonical skeleton stepping in place: feet alternate between resting and lifted."""
    from mld_core.motion import skeleton as sk

    offsets = np.asarray(sk.REFERENCE_OFFSETS, dtype=np.float64)
    rest = np.zeros((22, 3))
    for j, p in enumerate(sk.PARENTS):
        rest[j] = offsets[j] + (rest[p] if p >= 0 else 0)
    rest[:, 1] -= rest[:, 1].min()
    joints = np.repeat(rest[None], frames, 0)
    t = np.arange(frames)
    lift = np.clip(np.sin(t / frames * 4 * math.pi), 0, None) * 0.5  # left foot up half the time
    for j in (sk.JOINT_NAMES.index("left_ankle"), sk.JOINT_NAMES.index("left_foot")):
        joints[:, j, 1] += lift
        joints[:, j, 2] += lift * 0.5
    return joints


def test_take_contacts_given_or_recomputed():
    joints = _walk()
    given = np.tile([1.0, 0.0, 1.0, 1.0], (39, 1))
    c = rw.take_contacts(SimpleNamespace(joints=joints, fps=20, contacts=given))
    assert c.shape == (40, 4) and np.array_equal(c[-1], given[-1])  # padded to the take's frames
    rec = rw.take_contacts(SimpleNamespace(joints=joints, fps=20))
    assert rec.shape == (40, 4)
    right = rec[:, 2] > 0.5
    left = rec[:, 0] > 0.5
    assert right.all() and 0 < left.sum() < 40  # the standing foot is in contact, the lifted one only at times
    assert rw.take_contacts(SimpleNamespace(joints=joints[:1], fps=20)) is None


def test_foot_lock_options_reach_keyedit(rigify_metarig):
    joints = _walk()
    det = bm.detect_bone_map(rigify_metarig.names, list(rigify_metarig.parents))
    take = SimpleNamespace(joints=joints, fps=20)
    opts = rw.RetargetSettings(reduce=True, foot_lock=True)
    baked, result = ke.take_to_keys(joints, rigify_metarig, det.bone_map, bake_options=opts.bake_options(24, 1),
                                    contacts=rw.take_contacts(take), fps=20)
    assert baked.fps == 24 and baked.auto_smoothing == "NONE" and baked.handle_type == "AUTO_CLAMPED"
    assert 0 < baked.stats["reduction_ratio"] < 1
    assert {c.group for c in baked.curves} == set(det.bone_map.joints.values())  # mapped bones only
    with pytest.raises(ValueError, match="contacts"):
        ke.take_to_keys(joints, rigify_metarig, det.bone_map, bake_options=opts.bake_options(24, 1), fps=20)


def test_batch_arguments_are_checked_before_any_work(tmp_path):
    from blender_addon import batch

    parser = batch.build_parser()
    addon = batch._addon_package()

    def inputs(*extra):
        return batch.retarget_inputs(parser.parse_args(["--prompt", "x", "--out", "o.blend", *extra]), addon)

    settings, bone_map = inputs("--reduce", "--tolerance", "1", "--rotation-mode", "yxz", "--foot-lock", "--nla")
    assert settings == rw.RetargetSettings(True, 1.0, "YXZ", True, True) and bone_map is None
    assert inputs()[0] == rw.RetargetSettings()
    good = tmp_path / "map.json"
    bm.BoneMap({"pelvis": "Hips", "head": "Head"}).save(good)
    assert inputs("--bone-map", str(good))[1].joints == {"pelvis": "Hips", "head": "Head"}
    (tmp_path / "bad.json").write_text("[1, 2")
    (tmp_path / "rig.txt").write_text("")
    cases = [
        (["--bone-map", str(tmp_path / "bad.json")], "not valid JSON"),
        (["--bone-map", str(tmp_path / "none.json")], "bone map not found"),
        (["--rig", str(tmp_path / "rig.txt")], "must name a .blend"),
        (["--rig", str(tmp_path / "none.blend")], "rig file not found"),
        (["--bvh-rig", str(tmp_path / "none.bvh")], "BVH rig not found"),
        (["--rig-object", "A"], "--rig-object needs --rig"),
        (["--tolerance", "-1"], "tolerance"),
        (["--armature", "A", "--bvh-rig", str(good)], "--armature"),
    ]
    for extra, words in cases:
        with pytest.raises(batch.BatchError, match=words):
            inputs(*extra)


def test_the_match_mode_reaches_the_retarget(fixtures):
    from types import SimpleNamespace

    with pytest.raises(ValueError, match="match must be one of"):
        rw.RetargetSettings(match="elbows")
    assert rw.RetargetSettings.from_settings(SimpleNamespace(match="DIRECTIONS")).match == "directions"
    stored = np.load(fixtures / "rigs" / "source_takes.npz")
    joints = stored["dataset-2_wave-right-hand_normal_026_joints"].astype(np.float64)
    rig = rt.RigRest.load(fixtures / "rigs" / "rigify_metarig.json")
    bmap = bm.detect_bone_map(rig.names, rig.parents).bone_map
    take = rw.Take(joints=joints, local_quats=None, contacts=None, fps=20.0)
    keys = {m: rw.take_keys(take, rig, bmap, rw.RetargetSettings(match=m), fps=20.0, frame_start=1.0)
            for m in rw.MATCH_IDS}
    ref = {m: ke.take_to_keys(joints, rig, bmap, retarget_options=rt.RetargetOptions(match=m),
                              bake_options=rw.RetargetSettings().bake_options(20.0, 1.0))[0] for m in rw.MATCH_IDS}
    def values(baked):
        return np.concatenate([c.values for c in baked.curves if "rotation" in c.data_path])

    for m in rw.MATCH_IDS:
        np.testing.assert_array_equal(values(keys[m]), values(ref[m]))
    assert not np.allclose(values(keys["effectors"]), values(keys["directions"]))


def test_segment_strips_follow_the_keys_at_the_scene_rate():
    from mld_core.rig.keying import segment_strips

    segments = [("walk", 0), ("wave", 50), ("bow", 90)]  # a 130-frame take at 20 fps
    assert segment_strips(segments, 130, 20, 20, 1) == [("walk", 1, 51), ("wave", 51, 91), ("bow", 91, 130)]
    assert segment_strips(segments, 130, 20, 24, 10) == [("walk", 10, 70), ("wave", 70, 118), ("bow", 118, 165)]
    assert segment_strips([("walk", 0), ("stop", 129)], 130, 20, 20, 1) == [("walk", 1, 130)]  # no empty strip


def test_the_record_picks_the_map_and_the_road(fixtures, rigify_metarig):
    canonical = rt.RigRest.load(fixtures / "rigs" / "canonical.json")
    record = rw.RigRecord(canonical, rotation_modes={n: "QUATERNION" for n in canonical.names}, fps=24.0,
                          frame_start=5)
    assert record.canonical and record.stored_map() is None
    plan = rw.plan_of(record, rw.RetargetSettings())
    assert plan.exact and plan.bone_map.source == "canonical" and (plan.fps, plan.frame_start) == (24.0, 5)
    assert not rw.plan_of(record, rw.RetargetSettings(reduce=True)).exact  # reduction: through the solve
    euler = rw.RigRecord(canonical, rotation_modes={"pelvis": "XYZ"})
    assert not rw.plan_of(euler, rw.RetargetSettings(rotation_mode="KEEP")).exact  # keeps the rig's Euler bone
    given = rw.canonical_map(canonical.names)
    assert not rw.plan_of(record, rw.RetargetSettings(), bone_map=given).exact  # a given map: through the solve
    # a foreign rig: the detected map, unless the panel stored one (its rows win)
    metarig = rw.RigRecord(rigify_metarig)
    detected = bm.detect_bone_map(rigify_metarig.names, list(rigify_metarig.parents)).bone_map
    assert not metarig.canonical and metarig.bone_map().joints == detected.joints
    rows = tuple((j, {"pelvis": "spine", "head": ""}.get(j, b)) for j, b in detected.joints.items())
    stored = rw.RigRecord(rigify_metarig, map_rows=rows, map_extras='{"source": "user"}')
    assert stored.bone_map().source == "user" and stored.bone_map().joints["pelvis"] == "spine"
    assert "head" not in stored.bone_map().joints and not rw.plan_of(stored, rw.RetargetSettings()).exact


def test_plan_keys_keys_every_take_or_names_what_is_missing(fixtures, rigify_metarig):
    joints = np.load(fixtures / "rigs" / "source_takes.npz")["dataset-2_wave-right-hand_normal_026_joints"]
    take = SimpleNamespace(joints=joints.astype(np.float64), local_quats=None, fps=20, frames=len(joints),
                           contacts=None, segments=[("wave", 0), ("bow", 30)])
    record = rw.RigRecord(rigify_metarig, fps=24.0, frame_start=1)
    settings = rw.RetargetSettings(reduce=True, nla=True)
    plan, planned = rw.plan_keys([take, take], record, settings)
    assert [p.take for p in planned] == [take, take] and plan.bone_map.source == "rigify_metarig"
    direct = rw.take_keys(rw.Take(take.joints, None, None, 20), rigify_metarig, plan.bone_map, settings, fps=24.0,
                          frame_start=1)
    assert [c.data_path for c in planned[0].keys.curves] == [c.data_path for c in direct.curves]
    np.testing.assert_array_equal(planned[1].keys.curves[3].values, direct.curves[3].values)
    props = planned[0].properties
    assert props["mld_retargeted"] == 1 and props["mld_exact"] == 0 and props["mld_bone_map"] == "rigify_metarig"
    assert props["mld_keys"] == planned[0].keys.num_keys and props["mld_scene_fps"] == 24.0
    assert planned[0].strips == rw.segment_strips(take.segments, take.frames, 20, 24.0, 1)
    no_knee = rw.RigRecord(rigify_metarig, map_rows=(("pelvis", "spine"),))
    with pytest.raises(ValueError, match="Nothing was keyed") as err:
        rw.plan_keys([take], no_knee, rw.RetargetSettings())
    assert err.value.args[0].startswith(f"{rigify_metarig.name!r}: ") and "left_knee" in err.value.args[0]
