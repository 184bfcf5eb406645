"""Bone maps: presets, detection from bone names and hierarchy, JSON round trip, clear errors (no bpy)."""

from __future__ import annotations

import json

import pytest

from mld_core.rig import bone_maps as bm
from mld_core.rig import retarget as rt
from mld_core.motion.skeleton import JOINT_NAMES


@pytest.fixture
def name_lists(fixtures):
    return json.loads((fixtures / "rigs" / "bone_names.json").read_text())


def _rig_names(fixtures, name):
    rig = rt.RigRest.load(fixtures / "rigs" / f"{name}.json")
    return rig.names, list(rig.parents)


def test_presets_load_and_name_only_canonical_joints():
    presets = bm.load_presets()
    assert {"canonical", "rigify", "rigify_metarig", "mixamo", "bandai", "bvh_common"} <= set(presets)
    for preset in presets.values():
        assert set(preset.bones) <= set(JOINT_NAMES)
        assert set(bm.REQUIRED_JOINTS) <= set(preset.bones), preset.name


@pytest.mark.parametrize(
    "rig, preset, spot",
    [
        ("canonical", "canonical", {"left_knee": "left_knee"}),
        ("rigify_metarig", "rigify_metarig", {"neck": "spine.004", "head": "spine.006", "left_foot": "toe.L"}),
        ("rigify", "rigify", {"pelvis": "torso", "left_shoulder": "upper_arm_fk.L", "right_knee": "shin_fk.R"}),
        ("bandai_bvh", "bandai", {"spine3": "Chest", "left_collar": "Shoulder_L", "right_wrist": "Hand_R"}),
    ],
)
def test_detects_preset_of_real_rigs(fixtures, rig, preset, spot):
    names, parents = _rig_names(fixtures, rig)
    det = bm.detect_bone_map(names, parents)
    assert det.source == preset
    assert det.missing == []
    for joint, bone in spot.items():
        assert det.bone_map.joints[joint] == bone
    det.bone_map.validate(names)


def test_rigify_preset_carries_what_the_control_rig_needs(fixtures):
    names, parents = _rig_names(fixtures, "rigify")
    bmap = bm.detect_bone_map(names, parents).bone_map
    assert bmap.parent_overrides == {"upper_arm_fk.L": "shoulder.L", "upper_arm_fk.R": "shoulder.R"}
    assert bmap.pose_properties["upper_arm_parent.L"] == {"IK_FK": 1.0}
    assert bmap.pose_properties["torso"]["neck_follow"] == 1.0


@pytest.mark.parametrize(
    "rig, preset",
    [("mixamo", "mixamo"), ("mixamo_numbered", "mixamo"), ("mixamo_bvh", "bvh_common"), ("cmu_bvh", "bvh_common")],
)
def test_detects_preset_from_name_lists(name_lists, rig, preset):
    names, parents = name_lists[rig]["names"], name_lists[rig]["parents"]
    det = bm.detect_bone_map(names, parents)
    assert det.source == preset
    assert det.missing == []
    prefix = {"mixamo": "mixamorig:", "mixamo_numbered": "mixamorig1:"}.get(rig, "")
    assert det.bone_map.joints["left_shoulder"] == prefix + "LeftArm"
    assert det.bone_map.joints["left_collar"] == prefix + "LeftShoulder"
    assert det.bone_map.joints["right_knee"] == prefix + "RightLeg"


def test_common_bvh_with_and_without_intermediate_joints(name_lists):
    cmu = bm.detect_bone_map(name_lists["cmu_bvh"]["names"]).bone_map.joints
    # CMU: Hips > LowerBack > Spine > Spine1 > Neck > Neck1 > Head: Spine1 is the chest; LowerBack, Neck and
    # LHipJoint are left at rest. The neck is Neck1: Neck's head sits where the collars start, below the shoulders,
    # while SMPL's neck joint is the base of the neck between them (Neck there cost 5-8 degrees on the head).
    assert cmu["spine1"] == "Spine" and cmu["spine3"] == "Spine1" and "spine2" not in cmu
    assert cmu["neck"] == "Neck1"
    assert "LowerBack" not in cmu.values() and "Neck" not in cmu.values() and "LHipJoint" not in cmu.values()
    three = bm.detect_bone_map(name_lists["mixamo_bvh"]["names"]).bone_map.joints
    assert (three["spine1"], three["spine2"], three["spine3"]) == ("Spine", "Spine1", "Spine2")
    assert three["neck"] == "Neck"  # no Neck1: the one neck bone


def test_fuzzy_detection_without_a_preset(name_lists):
    ue = name_lists["ue_mannequin"]
    det = bm.detect_bone_map(ue["names"], ue["parents"])
    assert det.source == "auto"
    expected = {
        "pelvis": "pelvis", "spine1": "spine_01", "spine2": "spine_02", "spine3": "spine_03", "neck": "neck_01",
        "head": "head", "left_collar": "clavicle_l", "left_shoulder": "upperarm_l", "left_elbow": "lowerarm_l",
        "left_wrist": "hand_l", "right_hip": "thigh_r", "right_knee": "calf_r", "right_ankle": "foot_r",
        "right_foot": "ball_r",
    }
    for joint, bone in expected.items():
        assert det.bone_map.joints[joint] == bone, joint
    assert not any("twist" in b or b.startswith("ik_") for b in det.bone_map.joints.values())


def test_fuzzy_recovers_preset_rigs_from_names_and_hierarchy(fixtures, name_lists):
    names, parents = _rig_names(fixtures, "canonical")
    fz = bm.fuzzy_bone_map(names, parents)
    assert fz.joints == {j: j for j in JOINT_NAMES}
    names, parents = _rig_names(fixtures, "bandai_bvh")
    fz = bm.fuzzy_bone_map(names, parents)
    assert fz.missing() == []
    assert fz.joints["left_shoulder"] == "UpperArm_L" and fz.joints["left_collar"] == "Shoulder_L"
    mix = name_lists["mixamo"]
    fz = bm.fuzzy_bone_map(mix["names"], mix["parents"])
    assert fz.missing() == []
    assert fz.joints["left_hip"] == "mixamorig:LeftUpLeg" and fz.joints["left_foot"] == "mixamorig:LeftToeBase"


@pytest.mark.parametrize(
    "name, side, core",
    [
        ("mixamorig:LeftUpLeg", "left", "upleg"),
        ("thigh.L", "left", "thigh"),
        ("UpperArm_R", "right", "upperarm"),
        ("calf_twist_01_l", "left", "calftwist"),
        ("Bip01 R Forearm", "right", "forearm"),
        ("Spine1", None, "spine"),
    ],
)
def test_split_name(name, side, core):
    s, c, _ = bm.split_name(name)
    assert (s, c) == (side, core)


def test_missing_required_bones_are_listed(name_lists):
    names = [n for n in name_lists["mixamo"]["names"] if "LeftLeg" not in n and "RightForeArm" not in n]
    det = bm.detect_bone_map(names)
    assert det.source == "mixamo+auto"
    assert set(det.missing) == {"left_knee", "right_elbow"}
    with pytest.raises(bm.BoneMapError) as err:
        det.bone_map.validate(names)
    assert err.value.missing == ["left_knee", "right_elbow"]
    assert "left_knee" in str(err.value) and "right_elbow" in str(err.value)
    assert "Nothing was keyed" in str(err.value)


def test_validate_names_bones_absent_from_the_rig(name_lists):
    names = name_lists["mixamo"]["names"]
    bmap = bm.detect_bone_map(names).bone_map
    bmap.joints["head"] = "mixamorig:NoSuchHead"
    with pytest.raises(bm.BoneMapError) as err:
        bmap.validate(names)
    assert err.value.absent == ["head"]
    assert "NoSuchHead" in str(err.value)


def test_json_round_trip(tmp_path, fixtures):
    names, parents = _rig_names(fixtures, "rigify")
    bmap = bm.detect_bone_map(names, parents).bone_map
    path = tmp_path / "map.json"
    bmap.save(path)
    loaded = bm.BoneMap.load(path)
    assert loaded.joints == bmap.joints
    assert loaded.parent_overrides == bmap.parent_overrides
    assert loaded.pose_properties == bmap.pose_properties
    assert loaded.source == "rigify"
    assert not (tmp_path / "map.json.tmp").exists()
    # A preset file loads as a map too (first alternative of each joint).
    preset_map = bm.BoneMap.load(bm.PRESET_DIR / "bvh_common.json")
    assert preset_map.joints["spine3"] == "Spine2"


def test_bad_json_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(bm.BoneMapError, match="not valid JSON"):
        bm.BoneMap.load(bad)
    bad.write_text(json.dumps({"bones": {"left_tail": "x"}}))
    with pytest.raises(bm.BoneMapError, match="left_tail"):
        bm.BoneMap.load(bad)
    bad.write_text(json.dumps([1, 2]))
    with pytest.raises(bm.BoneMapError, match="not a bone map"):
        bm.BoneMap.load(bad)


def test_ik_chains_resolve_against_the_rig_and_survive_json_and_rows():
    from mld_core.rig.bone_map_rows import map_extras, map_to_rows, rows_to_map

    preset = bm.load_presets()["rigify"]
    names = sorted({b for alts in preset.bones.values() for b in alts} | {"torso", "upper_arm_parent.L"}
                   | {b for c in preset.ik_controls for b in c["fk"] + c["ik"] + [c["pole"]]})
    names.remove("foot_ik.R")  # a rig without the right foot's IK control: that chain is left out
    bone_map, _ = bm.apply_preset(preset, names)
    assert len(bone_map.ik_controls) == 3
    assert {"fk": ["upper_arm_fk.L", "forearm_fk.L", "hand_fk.L"], "ik": ["upper_arm_ik.L", "hand_ik.L"],
            "pole": "upper_arm_ik_target.L"} in bone_map.ik_controls
    assert bm.BoneMap.from_dict(bone_map.to_dict()).ik_controls == bone_map.ik_controls
    assert rows_to_map(map_to_rows(bone_map), map_extras(bone_map)).ik_controls == bone_map.ik_controls
    with pytest.raises(bm.BoneMapError, match="IK chain"):
        bm.ik_chains([{"fk": ["a", "b"], "ik": ["c", "d"]}])
    for bad in ({"a": 1}, ["x"], "chains"):  # not a list of objects: a BoneMapError, no AttributeError
        with pytest.raises(bm.BoneMapError, match="IK chain"):
            bm.ik_chains(bad)
