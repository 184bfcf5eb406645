"""Rigs as users have them, keyed by the batch with --rig: a Mixamo-style FBX import (armature object rotated 90
degrees about X, scale 0.01, bones in centimetres along Y up) must be keyed standing, not lying on its side; the rig
file's frame rate and hidden collections are kept."""

from __future__ import annotations

import numpy as np
import pytest

from bpy_util import REPO, requires_bpy, run_bpy_script, run_python

pytestmark = [pytest.mark.bpy, requires_bpy]

MAKE_RIG = r"""
import math, sys
sys.path.insert(0, {repo!r})
import bpy
import numpy as np
from mld_core.rig import bone_maps, retarget as rt
from blender_addon.scene import read_rig

bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.context.scene.render.fps = 30
canonical = rt.canonical_rig()
to_y_up = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])  # Z up -> Y up (FBX), rotating -90 X
centi = np.diag([100.0, 100.0, 100.0, 1.0])
mixamo = bone_maps.load_presets()["mixamo"].bones
names = ["mixamorig:" + mixamo[j][0].split(":")[-1] for j in canonical.names]  # Mixamo's names, as imported
rig = rt.RigRest(names, canonical.parents, centi @ to_y_up @ canonical.matrices,
                 (canonical.tails @ to_y_up[:3, :3].T) * 100.0)
obj = read_rig.build_armature(rig, "mixamo_like")
obj.rotation_euler = (math.pi / 2, 0.0, 0.0)
obj.scale = (0.01, 0.01, 0.01)
rigs = bpy.data.collections.new("Rig")
bpy.context.scene.collection.children.link(rigs)
for coll in list(obj.users_collection):
    coll.objects.unlink(obj)
rigs.objects.link(obj)
widgets = bpy.data.collections.new("WGTS_mixamo_like")
bpy.context.scene.collection.children.link(widgets)
shape = bpy.data.objects.new("WGT-hand", bpy.data.meshes.new("WGT-hand"))
widgets.objects.link(shape)
bpy.context.view_layer.layer_collection.children["WGTS_mixamo_like"].exclude = True
# the world matrix a script sees before the view layer is evaluated is stale (identity here)
out = {{"stale": [list(r) for r in obj.matrix_world]}}
out["read"] = read_rig.read_rig(obj).object_matrix.round(6).tolist()
bpy.ops.wm.save_as_mainfile(filepath={rig_path!r})
emit(out)
"""

CHECK = r"""
import sys
sys.path.insert(0, {repo!r})
import bpy
import numpy as np
bpy.ops.wm.open_mainfile(filepath={blend!r})
scene = bpy.context.scene
obj = bpy.data.objects["mixamo_like"]
out = {{"fps": scene.render.fps / scene.render.fps_base, "action": obj.animation_data.action.name}}
layers = {{lc.collection.name: lc for lc in bpy.context.view_layer.layer_collection.children}}
out["widgets_excluded"] = layers["WGTS_mixamo_like"].exclude
out["rig_visible"] = not layers["Rig"].exclude
heads, pelvis, feet = [], [], []
for frame in range(scene.frame_start, scene.frame_end + 1, 5):
    scene.frame_set(frame)
    world = obj.matrix_world
    pb = obj.pose.bones
    heads.append((world @ pb["mixamorig:Head"].head)[2])
    pelvis.append((world @ pb["mixamorig:Hips"].head)[2])
    feet.append(min((world @ pb["mixamorig:LeftToeBase"].head)[2], (world @ pb["mixamorig:RightToeBase"].head)[2]))
out["head_above_pelvis_m"] = float(np.min(np.array(heads) - np.array(pelvis)))
out["lowest_toe_m"] = float(np.min(feet))
rest = obj.matrix_world @ obj.data.bones["mixamorig:LeftToeBase"].head_local
out["rest_toe_m"] = float(rest[2])  # the toe joint's height above the floor when the rig stands in its rest pose
emit(out)
"""


def test_a_rotated_centimetre_rig_is_keyed_standing_and_its_file_settings_stay(tmp_path):
    rig_path = tmp_path / "mixamo_like.blend"
    made = run_bpy_script(MAKE_RIG.format(repo=str(REPO), rig_path=str(rig_path)), tmp_path, name="make.py")
    assert made["stale"] == [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    expected = [[0.01, 0, 0, 0], [0, 0, -0.01, 0], [0, 0.01, 0, 0], [0, 0, 0, 1]]
    assert np.allclose(made["read"], expected, atol=1e-6)  # read_rig sees the rotation and the scale

    out = tmp_path / "out.blend"
    proc = run_python([REPO / "blender_addon" / "batch.py", "--prompt", "a person walks forward", "--seconds", "3",
                       "--steps", "10", "--rig", rig_path, "--out", out], user_dir=tmp_path / "user", timeout=240)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    r = run_bpy_script(CHECK.format(repo=str(REPO), blend=str(out)), tmp_path, name="check.py")
    assert r["fps"] == 30  # the rig file's frame rate (no --fps)
    assert r["widgets_excluded"] and r["rig_visible"]
    assert r["head_above_pelvis_m"] > 0.3  # standing (on its side the head is level with the pelvis)
    # on the floor, not metres below it: the lowest toe joint within 5 cm of its height in the rest pose
    assert abs(r["lowest_toe_m"] - r["rest_toe_m"]) < 0.05, (r["lowest_toe_m"], r["rest_toe_m"])
