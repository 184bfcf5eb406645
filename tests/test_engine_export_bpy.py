"""Takes into a game engine, end to end in Blender (bpy in one subprocess): the batch exports two takes of the tiny
model (a loop and a wave) as FBX, GLB and BVH; the same takes go through the plain function with the other namings
and root motions, and through the panel's Export Takes; every file is imported back into an empty Blender and
checked: bone names, frame count, frame rate, joints following the take, the travel, the loop's seam."""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path

import pytest

from bpy_util import REPO, requires_bpy, run_bpy_script
from mld_core.rig import engine_export as ee
from mld_core.testing import tiny_model

pytestmark = [pytest.mark.bpy, requires_bpy]

SCRIPT = r"""
import sys, json
sys.path.insert(0, {repo!r})
from pathlib import Path
import numpy as np
import bpy, addon_utils
work = Path({work!r})
from blender_addon import batch
from blender_addon.scene import export_takes, key_takes, write_action
from mld_core.fileio import OutputSet
from mld_core.inputs import InputError
from mld_core.rig import engine_export as ee
from mld_core.rig.keyframes import BakedKeys, CurveKeys

out = {{"batch": batch.main(["batch.py", "--jobs", str(work / "jobs.json"), "--model", {model!r}, "--steps", "2",
                             "--out", str(work / "out" / "takes.blend"), "--export", "fbx,glb", "--export", "bvh",
                             "--root-motion", "root-bone", "--bone-names", "ue5"])}}
manifest = json.loads((work / "out" / "takes.json").read_text())
scene = bpy.context.scene
obj = bpy.data.objects["MLD_Armature"]
out["left_behind"] = [o.name for o in bpy.data.objects if o.name not in ("MLD_Armature", "MLD_Body")] + [
    a.name for a in bpy.data.actions if "mld_export" in a.name]
actions = [bpy.data.actions[t["name"]] for t in manifest["takes"]]
bone_map = key_takes.bone_map_of(obj)
runs = {{"ue5 root-bone": manifest["export"]}}
for label, (formats, motion, yaw, naming, one) in {{
        "mixamo in-place": (["fbx", "glb"], "in-place", False, "mixamo", True),
        "unity object": (["fbx"], "object", False, "unity", False),
        "canonical in-place yaw": (["glb"], "in-place", True, "canonical", True)}}.items():
    settings = ee.ExportSettings.parse(formats, motion, yaw, naming, one)
    files = ee.export_files(work / label.replace(" ", "_"), "takes", [a.name for a in actions], settings)
    with OutputSet() as outputs:
        runs[label] = export_takes.export_takes(obj, actions, files, settings, outputs, bone_map=bone_map)

# an Action that never keys the hips: refused, nothing written
frames = np.arange(1.0, 11.0)
stray = write_action.keys_to_action(obj, BakedKeys([CurveKeys('pose.bones["left_elbow"].rotation_quaternion', i,
    "left_elbow", frames, np.full(10, 1.0 if i == 0 else 0.0)) for i in range(4)], 20, 1, 10, "LINEAR"),
    "arm_only", assign=False)
try:
    with OutputSet() as outputs:
        export_takes.export_takes(obj, [stray], ee.export_files(work / "stray", "x", ["arm_only"],
                                  ee.ExportSettings()), ee.ExportSettings(), outputs, bone_map=bone_map)
except InputError as exc:
    out["no_root"] = str(exc)
out["stray_folder"] = (work / "stray").exists()

# the panel: the poll says why, then Export Takes over the ticked Actions
addon_utils.enable("blender_addon", default_set=True)
from blender_addon.ui import export_panel
scene.mld_motion.target = obj
panel = scene.mld_export
panel.folder, panel.glb, panel.root_motion, panel.bone_names = str(work / "panel"), True, "root-bone", "unity"
out["poll_untouched"] = export_panel.export_problem(bpy.context)
stray.mld_export = True
out["panel_stray"] = list(export_panel.do_export_takes(obj, [stray], panel.folder, panel))
stray.mld_export = False
for a in actions:
    a.mld_export = True
out["poll_ticked"] = export_panel.export_problem(bpy.context)
out["panel"] = sorted(bpy.ops.mld.export_takes())
out["panel_again"] = list(export_panel.do_export_takes(obj, actions, panel.folder, panel))

# what the takes play in Blender: every bone's head in world space, by its name on the armature
truth = {{}}
mw = np.asarray(obj.matrix_world)
for a in actions:
    start, pose = export_takes.sample_action(obj, a, scene)
    truth[a.name] = pose[..., :3, 3] @ mw[:3, :3].T + mw[:3, 3]
names = [b.name for b in obj.data.bones]
hips = names.index("pelvis")
fps = scene.render.fps / scene.render.fps_base
runs["unity panel"] = {{"bone_names": {{n: ee.load_namings()["unity"].bones[n] for n in names}}, "root_bone": "Root",
                        "files": [{{"path": str(work / "panel" / (a.name + ext)), "format": ext[1:], "takes": [a.name]}}
                                  for a in actions for ext in (".fbx", ".glb")]}}


def played(arm, action):
    ad = arm.animation_data or arm.animation_data_create()
    ad.action = action
    if hasattr(ad, "action_slot") and len(getattr(action, "slots", ())):
        ad.action_slot = action.slots[0]
    first, last = (int(round(v)) for v in action.frame_range)
    heads = []
    for frame in range(first, last + 1):
        bpy.context.scene.frame_set(frame)
        m = np.asarray(arm.matrix_world)
        heads.append([m[:3, :3] @ np.asarray(pb.head) + m[:3, 3] for pb in arm.pose.bones])
    return np.array(heads), [pb.name for pb in arm.pose.bones]


def reimport(path, fmt):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    for module in ("io_scene_fbx", "io_scene_gltf2", "io_anim_bvh"):
        addon_utils.enable(module, default_set=True)
    bpy.context.scene.render.fps, bpy.context.scene.render.fps_base = int(fps), 1.0  # glTF keeps seconds only
    if fmt == "fbx":
        bpy.ops.import_scene.fbx(filepath=path)
    elif fmt == "glb":
        bpy.ops.import_scene.gltf(filepath=path)
    else:
        bpy.ops.import_anim.bvh(filepath=path, global_scale=0.01, update_scene_fps=True)
    arm = [o for o in bpy.data.objects if o.type == "ARMATURE"][0]
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")  # Blender's FBX importer connects a child whose head meets its parent's
    for bone in arm.data.edit_bones:      # tail, and a connected bone ignores its location keys: engines do not
        bone.use_connect = False
    bpy.ops.object.mode_set(mode="OBJECT")
    return arm


results = []
for label, section in runs.items():
    inverse = {{new: old for old, new in section["bone_names"].items()}}
    root = section["root_bone"]
    for f in section["files"]:
        arm = reimport(f["path"], f["format"])
        actions_back = sorted(bpy.data.actions, key=lambda a: a.name)
        row = {{"run": label, "path": f["path"], "format": f["format"], "bones": sorted(b.name for b in arm.data.bones),
               "actions": [a.name for a in actions_back], "scene_fps": bpy.context.scene.render.fps /
               bpy.context.scene.render.fps_base, "takes": {{}}}}
        for take in f["takes"]:
            action = next(a for a in actions_back if a.name.split("|")[-1] == take or a.name == take
                          or len(f["takes"]) == 1)
            heads, bones = played(arm, action)
            index = [bones.index(section["bone_names"].get(n, n)) for n in names]
            got = heads[:, index]
            want = truth[take]
            t = {{"frames": len(heads), "error_cm": float(np.linalg.norm(got - want, axis=-1).max() * 100),
                 "hips_error_mm": float(np.linalg.norm(got[:, hips] - want[:, hips], axis=-1).max() * 1000)}}
            rel_got, rel_want = got - got[:, hips:hips + 1], want - want[:, hips:hips + 1]
            t["relative_error_cm"] = float(np.linalg.norm(rel_got - rel_want, axis=-1).max() * 100)
            t["hips_travel_cm"] = float(np.linalg.norm(got[-1, hips, :2] - got[0, hips, :2]) * 100)
            t["hips_sway_cm"] = float(np.ptp(got[:, hips, :2], axis=0).max() * 100)
            body = got - heads[:, [bones.index(root)]] if root else got
            t["seam_cm"] = float(np.linalg.norm(body[-1] - body[0], axis=-1).max() * 100)
            row["takes"][take] = t
        results.append(row)
out["results"] = results
out["runs"] = {{k: v for k, v in runs.items() if k != "unity panel"}}
emit(out)
"""


def glb_animations(path: Path) -> dict:
    """{animation name: (keys, last key time)} read from a GLB file's JSON chunk (the times' accessor)."""
    data = path.read_bytes()
    length, kind = struct.unpack_from("<I4s", data, 12)
    assert data[:4] == b"glTF" and kind == b"JSON"
    gltf = json.loads(data[20:20 + length])
    out = {}
    for anim in gltf["animations"]:
        times = gltf["accessors"][anim["samplers"][0]["input"]]
        out[anim["name"]] = (times["count"], times["max"][0])
    return out


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    work = tmp_path_factory.mktemp("engine")
    model = tiny_model(work / "tiny")
    (work / "jobs.json").write_text(json.dumps({"jobs": [
        {"prompt": "a person walks forward", "seconds": 2, "loop": True},
        {"prompt": "a person waves", "seconds": 2}]}))
    result = run_bpy_script(SCRIPT.format(repo=str(REPO), work=str(work), model=str(model)), work, timeout=420)
    return work, result


def test_the_batch_writes_every_take_in_every_format_listed_with_hashes(exported):
    work, r = exported
    assert r["batch"] == 0 and r["left_behind"] == []  # the export's armature copy and its keys are gone
    manifest = json.loads((work / "out" / "takes.json").read_text())
    takes = [t["name"] for t in manifest["takes"]]
    assert takes == ["walks_forward_s0", "waves_s1"] and [t["loop"] for t in manifest["takes"]] == [True, False]
    section = manifest["export"]
    assert section["settings"] == {"formats": ["fbx", "glb", "bvh"], "root_motion": "root-bone", "yaw": False,
                                   "bone_names": "ue5", "one_file": False}
    files = {(f["format"], tuple(f["takes"])): f for f in section["files"]}
    assert set(files) == {(fmt, (t,)) for fmt in ("fbx", "glb", "bvh") for t in takes}
    for f in section["files"]:
        data = Path(f["path"]).read_bytes()
        assert Path(f["path"]).parent == work / "out" and Path(f["path"]).name == f"{f['takes'][0]}.{f['format']}"
        assert f["sha256"] == hashlib.sha256(data).hexdigest() and f["bytes"] == len(data)
    assert sorted(p.name for p in (work / "out").iterdir()) == sorted(
        ["takes.blend", "takes.json"] + [f"{t}.{fmt}" for t in takes for fmt in ("fbx", "glb", "bvh")])
    seam = section["takes"]["walks_forward_s0"]["seam"]
    assert seam["closed_gap_cm"] < 0.01 and seam["gap_cm"] > seam["closed_gap_cm"]
    assert "seam" not in section["takes"]["waves_s1"]
    assert section["takes"]["waves_s1"]["frames"] == 40 and section["takes"]["waves_s1"]["fps"] == 20.0


def test_reimported_files_have_the_engine_names_frames_and_rate(exported):
    work, r = exported
    namings = ee.load_namings()
    for row in r["results"]:
        section = r["runs"].get(row["run"], {"settings": {"bone_names": "unity", "root_motion": "root-bone"}})
        naming = namings[section["settings"]["bone_names"]]
        root = [naming.root] if section["settings"]["root_motion"] == "root-bone" else []
        assert row["bones"] == sorted(list(naming.bones.values()) + root), row["path"]
        for take, t in row["takes"].items():
            assert t["frames"] == 40, (row["path"], take)  # 2 s at 20 fps
        if row["format"] in ("fbx", "bvh"):
            assert row["scene_fps"] == pytest.approx(20.0, abs=1e-3), row["path"]  # the importer reads the rate
        if row["format"] == "glb":
            animations = glb_animations(Path(row["path"]))
            assert sorted(animations) == sorted(row["takes"]), row["path"]  # one animation per take, named after it
            for keys, last in animations.values():
                assert keys == 40 and last == pytest.approx(39 / 20.0, abs=1e-6)
        if row["format"] == "fbx":
            assert sorted(a.split("|")[-1] for a in row["actions"]) == sorted(row["takes"]), row["path"]
        if row["format"] == "bvh":
            assert "Frame Time: 0.050000" in Path(row["path"]).read_text()
    assert {row["run"] for row in r["results"]} == {"ue5 root-bone", "mixamo in-place", "unity object",
                                                     "canonical in-place yaw", "unity panel"}


def test_reimported_joints_follow_the_take(exported):
    _, r = exported
    for row in r["results"]:
        run = row["run"]
        for take, t in row["takes"].items():
            where = (row["path"], take)
            if take == "walks_forward_s0":  # the loop: its seam closed for the engine
                if "in-place" in run:
                    assert t["seam_cm"] < 0.1, where  # first and last frames match
                if "root-bone" in run or "panel" in run:
                    assert t["seam_cm"] < 0.1, where  # ... relative to the root, which carries the travel
                continue
            if "object" in run or "root-bone" in run or "panel" in run:
                assert t["error_cm"] < 1.0, where  # every joint within 1 cm of the take
                assert t["hips_error_mm"] < 1.0, where  # root + hips give the hips back within 1 mm
            else:  # in place: the travel is gone, the body relative to its hips is the take's
                assert t["hips_travel_cm"] < 5.0, where
                assert t["hips_sway_cm"] > 0.0, where
                if "yaw" not in run:
                    assert t["relative_error_cm"] < 1.0, where
    wave = [row["takes"]["waves_s1"] for row in r["results"] if "waves_s1" in row["takes"]]
    travel = [t["hips_travel_cm"] for t in wave]
    assert max(travel) > 20.0  # the tiny model's wave travels: in place had something to take off


def test_bad_takes_and_the_panel(exported):
    work, r = exported
    assert "Action 'arm_only' has no keys on 'pelvis', the bone mapped to the hips" in r["no_root"]
    assert r["stray_folder"] is False  # nothing written
    assert r["panel_stray"][0] == "ERROR" and "'arm_only' has no keys on 'pelvis'" in r["panel_stray"][1]
    assert r["poll_untouched"] == "Tick the Actions of MLD_Armature to export in the list"
    assert r["poll_ticked"] == "" and r["panel"] == ["FINISHED"]
    assert sorted(p.name for p in (work / "panel").iterdir()) == sorted(
        f"{t}.{ext}" for t in ("walks_forward_s0", "waves_s1") for ext in ("fbx", "glb"))
    assert r["panel_again"][0] == "ERROR" and "exists; tick Replace Files" in r["panel_again"][1]
