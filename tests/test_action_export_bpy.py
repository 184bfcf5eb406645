"""Export Actions as Training Data: an armature's Actions, through its bone map, become a BVH folder with
captions that ``data prepare bvh`` reads. bpy in a subprocess."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bpy_util import addon_script, requires_bpy, run_bpy_script

pytestmark = [pytest.mark.bpy, requires_bpy]

EXPORT = r"""
from blender_addon.ui import retarget_panel
ctx = bpy.context
ctx.scene.render.fps = 20
bpy.ops.mld.create_armature()
obj = ctx.scene.mld_motion.target

def keyed_action(name, bone, frames):
    action = bpy.data.actions.new(name)
    obj.animation_data_create()
    obj.animation_data.action = action
    if hasattr(obj.animation_data, "action_slot") and len(action.slots):
        obj.animation_data.action_slot = action.slots[0]
    pb = obj.pose.bones[bone]
    for f in frames:
        pb.location = (0.0, 0.0, 0.05 * f)  # the bone slides along its own Z over the take
        pb.keyframe_insert("location", frame=f)
    return action

walk = keyed_action("Walk_Slow", "pelvis", range(1, 61))
walk["mld_caption"] = "a person walks slowly\nsomeone strolls"
keyed_action("Sway", "pelvis", range(1, 61))
mine = bpy.data.actions.new("nothing_keyed")
obj.animation_data.action = mine
out = {{"first": retarget_panel.do_export_actions(obj, {folder!r})}}
out["kept_action"] = obj.animation_data.action.name
out["again"] = retarget_panel.do_export_actions(obj, {folder!r})
out["none"] = retarget_panel.do_export_actions(obj, {folder2!r}, "nothing")
emit(out)
"""


def test_actions_export_and_prepare(tmp_path):
    from mld_core.cli import main

    folder, folder2 = tmp_path / "lib", tmp_path / "lib2"
    r = run_bpy_script(addon_script(EXPORT, folder=str(folder), folder2=str(folder2)), tmp_path,
                       timeout=180)
    assert r["first"][0] == "INFO" and "Exported 2 Actions" in r["first"][1]
    assert r["kept_action"] == "nothing_keyed"  # the armature's own Action is back
    assert r["again"][0] == "ERROR" and "already exists" in r["again"][1]
    assert r["none"][0] == "ERROR" and not folder2.exists()
    rows = (folder / "captions.csv").read_text().splitlines()
    assert rows == ["file,caption", "Sway.bvh,a person sway", "Walk_Slow.bvh,a person walks slowly",
                    "Walk_Slow.bvh,someone strolls"]
    assert main(["data", "prepare", "bvh", str(folder), "--captions", str(folder / "captions.csv"),
                 "--out", str(tmp_path / "out")]) == 0
    report = {f["file"]: f for f in json.loads((tmp_path / "out" / "prepare_report.json").read_text())["files"]}
    seg = report["Walk_Slow.bvh"]["segments"][0]
    assert report["Walk_Slow.bvh"]["skeleton"] == "canonical" and seg["captions"] == ["a person walks slowly",
                                                                                      "someone strolls"]
    joints = np.load(tmp_path / "out" / "new_joints" / f"{seg['id']}.npy")
    travel = np.linalg.norm(joints[-1, 0, [0, 2]] - joints[0, 0, [0, 2]])
    assert travel > 1.0  # the keyed pelvis moved ~3 m over the take; the exported take moves with it
