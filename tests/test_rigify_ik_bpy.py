"""A generated Rigify rig keyed by Generate: the FK controls carry the take, the IK controls are keyed to match it and
the IK/FK switches are stored with the Action, so switching a limb to IK keeps its hand or foot where it was.
Tiny model, bpy in a subprocess (pose.rigify_generate runs headless)."""

from __future__ import annotations

import pytest

from bpy_util import addon_script, requires_bpy, run_bpy_script
from mld_core.testing import tiny_model

pytestmark = [pytest.mark.bpy, requires_bpy]

SCRIPT = r"""
import numpy as np
addon_utils.enable("rigify", default_set=True)
from blender_addon.scene import write_action
bpy.ops.object.armature_human_metarig_add()
bpy.ops.pose.rigify_generate()
rig = bpy.data.objects["rig"]
scene = bpy.context.scene
scene.render.fps = 20
s = scene.mld_motion
s.target = rig
s.prompt, s.seconds, s.steps, s.seed = "a person walks", 2.0, 2, 3
out = {{"generate": sorted(bpy.ops.mld.generate()), "error": s.last_error}}
curves = write_action.fcurves_of(rig.animation_data.action)
paths = {{fc.data_path for fc in curves}}
out["ik_keyed"] = sorted(b for b in ("hand_ik.L", "foot_ik.R", "upper_arm_ik.L", "thigh_ik.R", "thigh_ik_target.L")
                         if 'pose.bones["%s"].location' % b in paths)
switch = [fc for fc in curves if fc.data_path.endswith('["IK_FK"]')]
out["switches"] = sorted(fc.data_path for fc in switch)
ends = ["ORG-hand.L", "ORG-hand.R", "ORG-foot.L", "ORG-foot.R"]

def heads(value):
    for fc in switch:  # what the animator does: switch the limbs to IK (0) on the stored switch keys
        fc.keyframe_points[0].co[1] = value
        fc.update()
    found = []
    for f in range(scene.frame_start, scene.frame_end + 1, 5):
        scene.frame_set(f)
        found.append([list(rig.matrix_world @ rig.pose.bones[n].head) for n in ends])
    return np.array(found)

out["ik_vs_fk_mm"] = float(np.linalg.norm(heads(1.0) - heads(0.0), axis=-1).max() * 1000)
emit(out)
"""


def test_rigify_ik_controls_follow_the_fk_take(tmp_path):
    model = tiny_model(tmp_path / "tiny")
    r = run_bpy_script(addon_script(SCRIPT), tmp_path, timeout=240, MLD_MODEL_DIR=model)
    assert r["generate"] == ["FINISHED"] and r["error"] == ""
    assert r["ik_keyed"] == ["foot_ik.R", "hand_ik.L", "thigh_ik.R", "thigh_ik_target.L", "upper_arm_ik.L"]
    assert r["switches"] == ['pose.bones["thigh_parent.L"]["IK_FK"]', 'pose.bones["thigh_parent.R"]["IK_FK"]',
                             'pose.bones["upper_arm_parent.L"]["IK_FK"]', 'pose.bones["upper_arm_parent.R"]["IK_FK"]']
    assert r["ik_vs_fk_mm"] < 1.0  # hands and feet stay put when the limbs switch to IK
