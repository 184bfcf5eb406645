"""Root motion and the engine export's math (numpy, no bpy): in place, on a root bone or left on the hips; loops
closed at their seam; engine bone names; the export's settings, files and their checks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mld_core.inputs import InputError
from mld_core.rig import engine_export as ee
from mld_core.rig import root_motion as rm
from mld_core.rig.bone_maps import load_presets
from mld_core.rig.retarget import RigRest, axis_angle_matrix

UP = np.array([0.0, 0.0, 1.0])
FPS = 20.0


def _turns(axis, angles) -> np.ndarray:
    angles = np.asarray(angles, np.float64)
    return axis_angle_matrix(np.broadcast_to(np.asarray(axis, np.float64), angles.shape + (3,)), angles)


def walk(seconds=4.0, speed=1.2, sway=0.03, turn_deg=0.0, frames=None) -> np.ndarray:
    """(T, 2, 4, 4) armature-space poses of hips and spine: walking forward (+Y) at ``speed`` m/s, the hips swaying
    ``sway`` m sideways at 0.9 Hz and yawing 6 degrees at 1.8 Hz, the path turning ``turn_deg`` over the take."""
    t = np.arange(frames or int(seconds * FPS) + 1) / FPS
    course = np.radians(turn_deg) * t / t[-1]
    forward = np.stack([-np.sin(course), np.cos(course), 0 * t], -1)
    side = np.stack([np.cos(course), np.sin(course), 0 * t], -1)
    path = np.cumsum(forward, 0) * speed / FPS - forward[0] * speed / FPS
    hips = np.tile(np.eye(4), (len(t), 1, 1))
    hips[:, :3, :3] = _turns(UP, course + np.radians(6) * np.sin(2 * np.pi * 1.8 * t))
    hips[:, :3, 3] = path + side * (sway * np.sin(2 * np.pi * 0.9 * t))[:, None] + [0, 0, 0.95]
    hips[:, 2, 3] += 0.02 * np.cos(2 * np.pi * 1.8 * t)
    spine = np.tile(np.eye(4), (len(t), 1, 1))
    spine[:, :3, :3] = _turns([1, 0, 0], 0.2 * np.sin(2 * np.pi * 0.9 * t))
    spine[:, 2, 3] = 0.2
    return np.stack([hips, hips @ spine], 1)


@pytest.fixture
def rig() -> RigRest:
    rest = np.tile(np.eye(4), (2, 1, 1))
    rest[0, 2, 3], rest[1, 2, 3] = 0.95, 1.15
    return RigRest(["hips", "spine"], [-1, 0], rest, rest[:, :3, 3] + [0, 0, 0.1])


def export(rig, pose, mode, yaw=False, loop=False, root_name="root"):
    out = ee.export_rig(rig, {}, root_name if mode == "root-bone" else None)
    return out, ee.export_pose(rig, out, pose, 0, UP, FPS, rm.RootMotion(mode, yaw), loop=loop)


def replay(out: ee.ExportRig, bases: np.ndarray) -> np.ndarray:
    """What Blender plays: pose = parent pose @ (parent rest^-1 @ rest) @ basis, from the rest and the keys."""
    pose = np.empty_like(bases)
    for b in out.order:
        p = out.parents[b]
        pose[:, b] = out.rest[b] @ bases[:, b] if p < 0 else \
            pose[:, p] @ np.linalg.inv(out.rest[p]) @ out.rest[b] @ bases[:, b]
    return pose


def lateral_sway(positions: np.ndarray) -> float:
    """Std of the sideways (X) position after a straight line is fitted through it: the sway of a walk along Y."""
    x = positions[:, 0]
    t = np.arange(len(x))
    return float(np.std(x - np.polyval(np.polyfit(t, x, 1), t)))


# -- the three modes ----------------------------------------------------------------------------------------------
def test_object_mode_plays_the_take_as_it_was(rig):
    pose = walk()
    out, take = export(rig, pose, "object")
    np.testing.assert_allclose(replay(out, take.bases), pose, atol=1e-12)
    assert take.report["hips_travel_cm"] == take.report["exported_hips_travel_cm"] == pytest.approx(480.0, abs=0.5)


def test_in_place_removes_the_travel_and_keeps_the_sway(rig):
    pose = walk(seconds=4.0)
    out, take = export(rig, pose, "in-place")
    played = replay(out, take.bases)
    hips = played[:, 0, :3, 3]
    assert rm.ground_travel(hips, UP) < 0.05  # the bound: under 5 cm of net travel over a 4 s walk
    assert rm.ground_travel(hips, UP) < 1e-9  # ... and here exactly none
    assert np.ptp(hips[:, 1]) < 0.10  # along the walk the hips stay within 10 cm (4.8 m before)
    assert lateral_sway(hips) > 0.85 * lateral_sway(pose[:, 0, :3, 3])  # the sway stays
    np.testing.assert_allclose(hips[:, 2], pose[:, 0, 2, 3], atol=1e-12)  # up and down untouched
    np.testing.assert_allclose(played[0], pose[0], atol=1e-12)  # the first frame as it was
    relative = np.linalg.inv(played[:, :1]) @ played  # the body relative to its hips: unchanged
    np.testing.assert_allclose(relative, np.linalg.inv(pose[:, :1]) @ pose, atol=1e-12)
    assert take.report["exported_hips_travel_cm"] == 0.0


def test_root_bone_carries_the_travel_and_gives_the_hips_back(rig):
    pose = walk()
    out, take = export(rig, pose, "root-bone")
    assert out.names == ["root", "hips", "spine"] and list(out.parents) == [-1, 0, 1]
    played = replay(out, take.bases)
    np.testing.assert_allclose(played[:, 1:], pose, atol=1e-12)  # root + hips reproduce the original exactly
    root = played[:, 0, :3, 3]
    assert np.abs(root[:, 2]).max() < 1e-12  # on the ground
    assert rm.ground_travel(root, UP) == pytest.approx(rm.ground_travel(pose[:, 0, :3, 3], UP), abs=1e-9)
    np.testing.assert_allclose(played[:, 0, :3, :3], np.eye(3)[None].repeat(len(pose), 0), atol=1e-12)  # no yaw
    sway = np.linalg.inv(played[:, 0]) @ played[:, 1]  # the hips seen from the root: the sway alone
    assert np.abs(sway[:, 1, 3]).max() < 0.10 and lateral_sway(sway[:, :3, 3]) > 0.85 * lateral_sway(pose[:, 0, :3, 3])


def test_yaw_goes_with_the_travel(rig):
    pose = walk(turn_deg=90.0)
    raw = rm.level_heading(pose[:, 0, :3, :3], UP)
    turn = np.degrees(raw[-1] - raw[0])  # the path's 90 degrees and the hips' own swing at the last frame
    assert turn == pytest.approx(95.7, abs=0.1)
    out, take = export(rig, pose, "in-place", yaw=True)
    played = replay(out, take.bases)
    heading = rm.level_heading(played[:, 0, :3, :3], UP)
    assert abs(np.degrees(heading[-1] - heading[0])) < 1.0  # the 90-degree turn is gone
    assert np.degrees(np.ptp(heading)) > 8.0  # the hips' own yaw swing (6 degrees each way) stays
    assert rm.ground_travel(played[:, 0, :3, 3], UP) < 1e-9
    _, kept = export(rig, pose, "in-place", yaw=False)
    heading = rm.level_heading(replay(out, kept.bases)[:, 0, :3, :3], UP)
    assert np.degrees(heading[-1] - heading[0]) == pytest.approx(turn, abs=1e-9)  # without yaw the turn stays
    out, rooted = export(rig, pose, "root-bone", yaw=True)
    played = replay(out, rooted.bases)
    np.testing.assert_allclose(played[:, 1:], pose, atol=1e-12)
    root_heading = rm.level_heading(played[:, 0, :3, :3], UP)
    assert np.degrees(root_heading[-1] - root_heading[0]) == pytest.approx(turn, abs=1e-6)  # the root turns
    assert rooted.report["turn_deg"] == pytest.approx(turn, abs=0.01)


def test_a_rig_with_y_up_armature_space(rig):
    """A rig whose armature space has Y up (an FBX import rotated on its object): the ground is X-Z there."""
    to_y_up = np.eye(4)
    to_y_up[:3, :3] = _turns([1, 0, 0], -np.pi / 2)
    pose = to_y_up[None, None] @ walk()
    y_rig = RigRest(rig.names, rig.parents, to_y_up[None] @ rig.matrices, rig.tails)
    out = ee.export_rig(y_rig, {}, None)
    take = ee.export_pose(y_rig, out, pose, 0, np.array([0.0, 1.0, 0.0]), FPS, rm.RootMotion("in-place"))
    hips = replay(out, take.bases)[:, 0, :3, 3]
    assert rm.ground_travel(hips, [0, 1, 0]) < 1e-9 and np.ptp(hips[:, 1]) > 0.03  # the bob (on Y here) stays


# -- loops ---------------------------------------------------------------------------------------------------------
def looped_walk(gap_deg=3.0, gap_m=0.004) -> np.ndarray:
    """A 2 s walk cycle whose last frame repeats the first one cycle on (a stride of 2.4 m), with a seam gap: the
    spine's last frame turned ``gap_deg`` and the hips' lifted ``gap_m``."""
    pose = walk(seconds=2.0)
    t = np.arange(len(pose)) / (len(pose) - 1)  # sway, yaw and bob exactly periodic over the 40 frames
    hips = pose[:, 0].copy()
    hips[:, 0, 3] = 0.03 * np.sin(2 * np.pi * t)
    hips[:, :3, :3] = _turns(UP, np.radians(6) * np.sin(4 * np.pi * t))
    hips[:, 2, 3] = 0.95 + 0.02 * np.cos(4 * np.pi * t)
    spine = np.tile(np.eye(4), (len(pose), 1, 1))
    spine[:, :3, :3] = _turns([1, 0, 0], 0.2 * np.sin(2 * np.pi * t))
    spine[:, 2, 3] = 0.2
    spine[-1, :3, :3] = spine[-1, :3, :3] @ _turns([0, 1, 0], np.radians(gap_deg))
    hips[-1, 2, 3] += gap_m
    return np.stack([hips, hips @ spine], 1)


@pytest.mark.parametrize("mode", rm.MODES)
def test_a_loop_is_closed_at_its_seam(rig, mode):
    pose = looped_walk()
    out, take = export(rig, pose, mode, loop=True)
    seam = take.report["seam"]
    assert seam["gap_cm"] == pytest.approx(0.4, abs=1e-3)  # the hips' 4 mm lift (it lifts the spine too)
    assert seam["gap_deg"] == pytest.approx(3.0, abs=1e-3) and seam["closed_gap_cm"] < 1e-6
    assert seam["closed_gap_deg"] < 1e-4 and seam["cycle_travel_cm"] == pytest.approx(240.0, abs=0.5)
    played = replay(out, take.bases)
    body = played[:, -2:] if mode != "root-bone" else np.linalg.inv(played[:, :1]) @ played[:, 1:]
    if mode == "object":  # the hips keep their travel: the pose matches relative to the root's ground point
        frames = rm.root_frames(played[:, 0], UP, FPS, yaw=False, loop=True)
        body = rm.in_root_frame(frames, played)
    np.testing.assert_allclose(body[-1], body[0], atol=1e-9)  # first and last frames match: the engine loops it
    np.testing.assert_allclose(played[0, -2:], pose[0], atol=1e-12)  # the first frame as generated
    deviation = np.linalg.norm((played[:, -2:] - pose)[..., :3, 3], axis=-1)
    if mode == "object":
        assert deviation.max() < 0.004 + 1e-9  # the gap, spread over the take, moves no joint further than its gap


@pytest.mark.parametrize("mode, yaw", [("in-place", False), ("in-place", True), ("root-bone", False),
                                       ("root-bone", True)])
def test_a_turning_loop_meets_itself_as_exported(rig, mode, yaw):
    """A loop that turns 10 degrees a cycle: with the turn exported (yaw) the root turns and the body meets itself
    relative to it; without, the turn is spread over the take so the ends face alike."""
    pose = looped_walk(gap_deg=0.0, gap_m=0.0)
    turn = _turns(UP, np.radians(10.0) * np.linspace(0, 1, len(pose)))  # the whole walk turns about its start
    bent = pose.copy()
    bent[..., :3, :3] = turn[:, None] @ pose[..., :3, :3]
    bent[..., :3, 3] = np.einsum("tij,tkj->tki", turn, pose[..., :3, 3] - pose[:1, :1, :3, 3]) + pose[:1, :1, :3, 3]
    out, take = export(rig, bent, mode, yaw=yaw, loop=True)
    assert take.report["seam"]["cycle_turn_deg"] == pytest.approx(10.0, abs=0.01)
    played = replay(out, take.bases)
    body = played if mode == "in-place" else np.linalg.inv(played[:, :1]) @ played[:, 1:]
    np.testing.assert_allclose(body[-1], body[0], atol=1e-9)
    if mode == "root-bone":
        root_turn = rm.level_heading(played[:, 0, :3, :3], UP)
        assert np.degrees(root_turn[-1] - root_turn[0]) == pytest.approx(10.0 if yaw else 0.0, abs=0.5)


def test_loop_paths_are_periodic():
    """A loop's smoothed path continues round its cycle: the path at the last frame is the first frame's, moved."""
    path = np.stack([0.03 * np.sin(np.linspace(0, 2 * np.pi, 41)), np.linspace(0, 2.4, 41)], -1)
    heading = np.zeros(41)
    smooth, _ = rm.smooth_path(path, heading, 8.0, loop=True)
    np.testing.assert_allclose(smooth[-1] - smooth[0], path[-1] - path[0], atol=1e-12)
    assert np.abs(smooth[:, 0]).max() < 0.5 * 0.03  # most of the sway is left to the hips
    turned = np.radians(np.linspace(0, 90, 41))
    circle = np.stack([np.cos(turned) - 1, np.sin(turned)], -1)
    smooth, heading = rm.smooth_path(circle, turned, 8.0, loop=True)
    assert np.degrees(heading[-1] - heading[0]) == pytest.approx(90.0, abs=1e-9)


# -- names, settings and files --------------------------------------------------------------------------------------
def test_engine_names():
    namings = ee.load_namings()
    assert list(namings)[:4] == list(ee.NAMINGS)
    mixamo = load_presets()["mixamo"]
    assert namings["mixamo"].bones == {j: names[0] for j, names in mixamo.bones.items()}  # one list of names
    assert namings["canonical"].bones == {j: j for j in load_presets()["canonical"].bones}
    ue5, unity = namings["ue5"].bones, namings["unity"].bones
    assert (ue5["pelvis"], ue5["left_hip"], ue5["right_knee"], ue5["spine3"], namings["ue5"].root) == (
        "pelvis", "thigh_l", "calf_r", "spine_05", "root")
    assert (unity["pelvis"], unity["left_shoulder"], unity["right_foot"], unity["spine3"]) == (
        "Hips", "LeftUpperArm", "RightToes", "UpperChest")
    for naming in namings.values():
        assert len(naming.bones) == 22 and len(set(naming.bones.values())) == 22, naming.name
        assert naming.root not in naming.bones.values()


def test_bone_renames_keep_unmapped_bones_and_refuse_collisions():
    bone_map = {"pelvis": "Hips_ctrl", "left_hip": "thigh.L"}
    renames, root = ee.bone_renames("ue5", bone_map, ["Hips_ctrl", "thigh.L", "prop"], root=True)
    assert renames == {"Hips_ctrl": "pelvis", "thigh.L": "thigh_l"} and root == "root"
    with pytest.raises(InputError, match=r"'thigh\.L' and 'thigh_l' would both be called 'thigh_l'"):
        ee.bone_renames("ue5", bone_map, ["Hips_ctrl", "thigh.L", "thigh_l"])
    with pytest.raises(InputError, match="'root' and the root bone would both be called 'root'"):
        ee.bone_renames("ue5", bone_map, ["Hips_ctrl", "thigh.L", "root"], root=True)


@pytest.mark.parametrize("argv, words", [
    ((["obj"],), "--export: unknown value 'obj'; use fbx, glb or bvh"),
    ((["fbx,glb", "FBX"],), "--export: fbx is named twice"),
    ((["fbx"], "sideways"), "--root-motion: unknown value 'sideways'; use object, in-place or root-bone"),
    ((["fbx"], "object", False, "maya"), "--bone-names: unknown value 'maya'; use canonical, mixamo, ue5 or unity"),
    (([" "],), "--export: name at least one format"),
])
def test_export_settings_are_checked(argv, words):
    with pytest.raises(InputError) as err:
        ee.ExportSettings.parse(*argv)
    assert words in str(err.value) and "\n" not in str(err.value)


def test_export_files_and_their_checks(tmp_path):
    settings = ee.ExportSettings.parse(["fbx", "glb,bvh"], "root-bone", True, "ue5", one_file=True)
    assert settings.to_dict() == {"formats": ["fbx", "glb", "bvh"], "root_motion": "root-bone", "yaw": True,
                                  "bone_names": "ue5", "one_file": True}
    files = ee.export_files(tmp_path, "takes", ["walk_s0", "wave/s1"], settings)
    assert [(f.format, f.path.name, f.takes) for f in files] == [
        ("fbx", "takes.fbx", ("walk_s0", "wave/s1")), ("glb", "takes.glb", ("walk_s0", "wave/s1")),
        ("bvh", "walk_s0.bvh", ("walk_s0",)), ("bvh", "wave_s1.bvh", ("wave/s1",))]
    others = {"--out": tmp_path / "takes.blend", "--manifest": tmp_path / "walk_s0.bvh"}
    with pytest.raises(InputError, match=r"--export bvh \(walk_s0\) .*walk_s0.bvh is the same file as --manifest"):
        ee.check_export_files(files, others, {})
    twins = ee.export_files(tmp_path, "takes", ["a:b", "a/b"], ee.ExportSettings(("fbx",)))
    with pytest.raises(InputError, match=r"--export fbx \(a/b\) .*a_b.fbx is the same file as --export fbx \(a:b\)"):
        ee.check_export_files(twins, {}, {})
    (tmp_path / "walk_s0.bvh").write_text("mine")
    with pytest.raises(InputError, match="exists; pass --overwrite"):
        ee.check_export_files(files, {"--out": tmp_path / "takes.blend"}, {})
    ee.check_export_files(files, {"--out": tmp_path / "takes.blend"}, {}, overwrite=True)


def test_pose_keys_play_the_bases(rig):
    out, take = export(rig, walk(seconds=2.0), "root-bone")
    keys = ee.pose_keys(out.names, take.bases, 1.0, FPS)
    assert keys.num_frames == 41 and keys.interpolation == "LINEAR" and keys.num_keys == 41 * 7 * 3
    curves = {(c.data_path, c.index): c.values for c in keys.curves}
    np.testing.assert_allclose(curves[('pose.bones["root"].location', 1)], take.bases[:, 0, 1, 3])
    quats = np.stack([curves[('pose.bones["hips"].rotation_quaternion', i)] for i in range(4)], -1)
    np.testing.assert_allclose(rm.rotation_matrices(quats), take.bases[:, 1, :3, :3], atol=1e-12)
    assert np.all(np.sum(quats[1:] * quats[:-1], -1) > 0)  # no sign flips between keys
    assert json.dumps(take.report)  # the manifest can hold it
