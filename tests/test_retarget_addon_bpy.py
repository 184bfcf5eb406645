"""Generate onto a user's rig inside bpy (Blender as a Python module), in subprocesses: a Bandai skeleton imported
with Blender's own BVH importer, keyed by the Generate operator through its bone map (the bundled default model),
checked by what Blender plays; the Retarget panel's operators; and the batch script keying an imported BVH rig.
No number here comes from the model: the checks are bounds (fidelity, reduction) and structure."""

from __future__ import annotations

import json
import sys

import pytest

from bpy_util import REPO, addon_script, requires_bpy, run_bpy_script, run_python

pytestmark = [pytest.mark.bpy, requires_bpy]

BVH = REPO / "tests" / "fixtures" / "bandai" / "dataset-2_walk-turn-left_normal_027.bvh"

ADDON = r"""
import sys, json
import numpy as np
sys.path.insert(0, {repo!r})
sys.path.insert(0, {repo!r} + "/research")
import bpy, addon_utils
bpy.ops.wm.read_factory_settings(use_empty=True)
addon_utils.enable("blender_addon", default_set=True)
addon_utils.enable("io_anim_bvh", default_set=True)
from blender_addon.scene import key_takes as apply
from blender_addon.worker import generation
from blender_addon.scene import write_action as keys
from blender_addon.ui import operators
from mld_core.rig import fidelity
from mld_core.rig import retarget as rt
from blender_addon.ui import retarget_panel as retarget_ui
from mld_core.rig import keying as retarget_wiring
from blender_addon.scene import read_rig as rig_io
from blender_addon.ui import runtime
from blender_addon.worker.validation import validate_request
import retarget_fidelity as fid

out = {{}}
ctx = bpy.context
scene = ctx.scene
scene.render.fps = 20
s = scene.mld_motion
bpy.ops.import_anim.bvh(filepath={bvh!r}, global_scale=0.01)
obj = ctx.object
clip_action = obj.animation_data.action
out["clip_action"] = clip_action.name
s.target = obj
# seed 0 at 50 steps: a walk whose generated feet change length (its toes sank 1.2 cm before the planted-toe solve)
s.prompt, s.seconds, s.seed, s.steps = "a person walks forward", 3.0, 0, 50

# the detected map: Bandai's preset, nothing stored yet
out["problem_detected"] = operators.generate_problem(ctx)
runs = retarget_wiring.detections.runs
for _ in range(20):
    operators.generate_problem(ctx)
out["detections_for_20_polls"] = retarget_wiring.detections.runs - runs
out["detect"] = retarget_ui.do_detect(obj)
out["rows"] = len(obj.mld_retarget.rows)

# a map lacking a required bone: the poll says which, apply keys nothing
row = [r for r in obj.mld_retarget.rows if r.joint == "left_knee"][0]
knee = row.bone
row.bone = ""
out["problem_missing"] = operators.generate_problem(ctx)
out["poll_missing"] = bpy.ops.mld.generate.poll()
pipe = runtime.cache().get(None, "cpu")
request = validate_request(s.prompt, s.seconds, s.seed, s.steps, None, 1)
result = generation.generate(pipe, request)
n_actions = len(bpy.data.actions)
try:
    apply.apply_result(obj, result, scene)
    out["apply_missing"] = "no error"
except ValueError as exc:
    out["apply_missing"] = str(exc)
out["no_new_action"] = len(bpy.data.actions) == n_actions
out["action_untouched"] = obj.animation_data.action == clip_action
row.bone = knee

# save / load: a bad file changes nothing
path = {tmp!r} + "/map.json"
out["save"] = sorted(bpy.ops.mld.save_bone_map(filepath=path))
saved = json.load(open(path))
out["saved_knee"] = saved["bones"]["left_knee"]
open({tmp!r} + "/bad.json", "w").write("{{not json")
before = [(r.joint, r.bone) for r in obj.mld_retarget.rows]
out["load_bad"] = retarget_ui.do_load_map(obj, {tmp!r} + "/bad.json")
out["load_bad_unchanged"] = before == [(r.joint, r.bone) for r in obj.mld_retarget.rows]
row.bone = ""
out["load_good"] = retarget_ui.do_load_map(obj, path)
out["load_good_knee"] = [r.bone for r in obj.mld_retarget.rows if r.joint == "left_knee"][0]

# Generate (the operator, headless), reduced keys
s.reduce_keys, s.rotation_mode = True, "QUATERNION"
out["generate"] = sorted(bpy.ops.mld.generate())
out["error"] = s.last_error
act = obj.animation_data.action
out["action"] = act.name
out["clip_kept"] = clip_action.name in bpy.data.actions and clip_action.use_fake_user
bone_map = apply.bone_map_of(obj)
curves = keys.fcurves_of(act)
out["keyed_bones"] = sorted({{fc.data_path.split('"')[1] for fc in curves}})
out["mapped_bones"] = sorted(bone_map.joints.values())
out["n_bones"] = len(obj.data.bones)
out["auto_smoothing"] = sorted({{fc.auto_smoothing for fc in curves}})
out["handles"] = sorted({{h for fc in curves for k in fc.keyframe_points for h in (k.handle_left_type, k.handle_right_type)}})
out["interp"] = sorted({{k.interpolation for fc in curves for k in fc.keyframe_points}})
n_keys = sum(len(fc.keyframe_points) for fc in curves)
out["props"] = {{k: act[k] for k in ("mld_retargeted", "mld_reduction_ratio", "mld_keys", "mld_bone_map", "mld_reduce")}}
out["n_keys"] = n_keys
out["last_reduction"] = s.last_reduction
out["frame_end"] = scene.frame_end

# fidelity of what Blender plays (the same take regenerated: seeded)
take = generation.generate(pipe, request).takes[0]
rig = rig_io.read_rig(obj)
res = rt.retarget(take.joints, rig, bone_map.joints, parent_overrides=bone_map.parent_overrides, fps=take.fps)
frames = range(scene.frame_start, scene.frame_start + res.num_frames)
played = fid.blender_joint_positions(bpy, obj, dict(zip(res.joints, res.bones)), frames)
fb = fidelity.fidelity(res, target_joints=played)
out["fidelity"] = {{k: v for k, v in fb.items() if k.endswith(("_err", "_err_global")) or k in ("effector_err_mean", "sink_cm")}}

# Push to NLA: a new track with the Action (and its slot) as a strip; the active Action is left alone
s.push_nla, s.seed = True, 2
n_tracks = len(obj.animation_data.nla_tracks)
out["generate_nla"] = sorted(bpy.ops.mld.generate())
tracks = obj.animation_data.nla_tracks
strip = tracks[-1].strips[0]
out["nla"] = [len(tracks) - n_tracks, strip.action.name, s.last_actions, obj.animation_data.action.name == act.name]
out["strip_slot"] = getattr(strip, "action_slot", None) is not None and strip.action_slot == strip.action.slots[0]
out["strip_start"] = strip.frame_start

# the canonical armature: exact by default, through keyedit when Euler keys are asked for
s.push_nla, s.reduce_keys = False, False
bpy.ops.mld.create_armature()
can = s.target
bpy.ops.mld.generate()
a = can.animation_data.action
out["canonical_exact"] = [a["mld_retargeted"], a["mld_exact"], len(keys.fcurves_of(a))]
s.rotation_mode = "XYZ"
bpy.ops.mld.generate()
a = can.animation_data.action
out["canonical_euler"] = [a["mld_retargeted"], sorted({{fc.data_path.rsplit(".", 1)[1] for fc in keys.fcurves_of(a)}}),
                          sorted({{pb.rotation_mode for pb in can.pose.bones}})]

# the Retarget panel draws (with a recording layout)
sys.path.insert(0, {repo!r} + "/tests")
from recording_layout import Host, Layout
s.target = obj
retarget_ui.MLD_PT_retarget.draw(Host(), ctx)
out["drawn"] = list(Layout.calls)
emit(out)
"""


@pytest.fixture(scope="module")
def addon_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("retarget_addon")
    return run_bpy_script(ADDON.format(repo=str(REPO), bvh=str(BVH), tmp=str(tmp)), tmp, timeout=240)


def test_bone_map_problems_are_named_and_key_nothing(addon_run):
    r = addon_run
    assert r["problem_detected"] == ""
    assert r["detections_for_20_polls"] == 0  # detection is cached, polls stay cheap
    assert r["detect"][0] == "INFO" and "'bandai'" in r["detect"][1] and r["rows"] == 22
    assert "left_knee" in r["problem_missing"] and "required" in r["problem_missing"] and r["poll_missing"] is False
    assert "left_knee" in r["apply_missing"] and "Nothing was keyed" in r["apply_missing"]
    assert r["no_new_action"] and r["action_untouched"]


def test_bone_map_save_and_load(addon_run):
    r = addon_run
    assert r["save"] == ["FINISHED"] and r["saved_knee"] == "LowerLeg_L"
    assert r["load_bad"][0] == "ERROR" and "unchanged" in r["load_bad"][1] and r["load_bad_unchanged"]
    assert r["load_good"][0] == "INFO" and r["load_good_knee"] == "LowerLeg_L"


def test_generate_keys_mapped_bones_with_reduced_bezier_keys(addon_run):
    r = addon_run
    assert r["generate"] == ["FINISHED"] and r["error"] == ""
    assert r["action"] == "walks_forward_s0" and r["clip_kept"]
    assert r["keyed_bones"] == r["mapped_bones"] and len(r["mapped_bones"]) < r["n_bones"]
    assert r["auto_smoothing"] == ["NONE"] and r["handles"] == ["AUTO_CLAMPED"] and r["interp"] == ["BEZIER"]
    props = r["props"]
    assert props["mld_retargeted"] == 1 and props["mld_bone_map"] == "file" and props["mld_reduce"] == 1
    assert props["mld_keys"] == r["n_keys"]
    unreduced = 60 * (4 * len(r["mapped_bones"]) + 3)  # 3 s at 20 fps: quaternions + the pelvis location
    assert 0 < props["mld_reduction_ratio"] < 1
    assert props["mld_reduction_ratio"] == pytest.approx(r["n_keys"] / unreduced)
    assert r["last_reduction"] == pytest.approx(props["mld_reduction_ratio"])
    assert r["frame_end"] == 60


def test_what_blender_plays_follows_the_generated_take(addon_run):
    f = addon_run["fidelity"]
    assert f["effector_err_mean"] < 0.05, f  # wrists, ankles, head relative to the limb root, / limb length
    for effector in ("left_wrist", "right_wrist", "head"):  # solved to land on the scaled source
        assert f[f"{effector}_err"] < 0.05, (effector, f)
    for effector in ("left_ankle", "right_ankle"):  # placed where the scaled source's feet are, in world space
        assert f[f"{effector}_err_global"] < 0.05, (effector, f)
        assert f[f"{effector}_err"] < 0.1, (effector, f)  # the rest: the two skeletons' hip widths differ
    assert f["sink_cm"] < 1.0, f


def test_push_to_nla_and_the_canonical_rig(addon_run):
    r = addon_run
    assert r["generate_nla"] == ["FINISHED"]
    added, strip_action, last, active_unchanged = r["nla"]
    assert added == 1 and strip_action == last == "walks_forward_s2" and active_unchanged
    assert r["strip_slot"] and r["strip_start"] == 1
    assert r["canonical_exact"] == [0, 1, 22 * 7]
    retargeted, paths, modes = r["canonical_euler"]
    assert retargeted == 1 and paths == ["location", "rotation_euler"] and modes == ["XYZ"]


def test_retarget_panel_draws_the_map(addon_run):
    drawn = [tuple(c) for c in addon_run["drawn"]]
    assert ("template_list", "MLD_UL_bone_map", "rows") in drawn
    assert drawn.count(("prop_search", "bone", "bones")) == 22
    assert ("label", "left_knee *") in drawn and ("label", "spine1") in drawn
    for op in ("mld.detect_bone_map", "mld.save_bone_map", "mld.load_bone_map"):
        assert ("operator", op) in drawn
    assert {"reduce_keys", "reduce_tolerance", "rotation_mode", "foot_lock", "push_nla"} <= {
        c[1] for c in drawn if c[0] == "prop"}


CHECK = r"""
import sys
sys.path.insert(0, {repo!r})
import bpy
bpy.ops.wm.open_mainfile(filepath={blend!r})
from blender_addon.scene.write_action import fcurves_of
arm = [o for o in bpy.data.objects if o.type == "ARMATURE"][0]
acts = [a for a in bpy.data.actions if "mld_prompt" in a]
ad = arm.animation_data
emit({{
    "armature": arm.name,
    "actions": sorted(a.name for a in acts),
    "bones": sorted({{fc.data_path.split('"')[1] for a in acts for fc in fcurves_of(a)}}),
    "euler": sorted({{fc.data_path.rsplit(".", 1)[1] for a in acts for fc in fcurves_of(a)}}),
    "tracks": [t.strips[0].action.name for t in ad.nla_tracks],
    "active": ad.action.name if ad.action else None,
}})
"""


def test_batch_keys_an_imported_bvh_rig(tmp_path, capsys):
    out = tmp_path / "rig.blend"
    script = REPO / "blender_addon" / "batch.py"
    args = [script, "--prompt", "a person waves", "--out", out, "--steps", "5", "--seconds", "2",
            "--bvh-rig", BVH, "--bvh-scale", "0.01", "--reduce", "--rotation-mode", "zxy", "--nla", "--foot-lock"]
    proc = run_python(args, user_dir=tmp_path / "blender_user", timeout=240)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    manifest = json.loads(out.with_suffix(".json").read_text())
    assert manifest["rig"]["bone_map"] == "bandai" and manifest["settings"]["retarget"]["rotation_mode"] == "ZXY"
    take = manifest["takes"][0]
    assert take["retargeted"] and 0 < take["reduction_ratio"] < 1
    r = run_bpy_script(CHECK.format(repo=str(REPO), blend=str(out)), tmp_path, timeout=120)
    assert r["actions"] == ["waves_s0"] and r["tracks"] == ["waves_s0"]
    assert r["active"] is None  # the imported clip is kept but not assigned; the take plays from the NLA
    assert r["euler"] == ["location", "rotation_euler"] and "Hips" in r["bones"] and len(r["bones"]) < 40

    # bad input: exit code 2, one line, nothing written (checked in-process, before any model work)
    sys.path.insert(0, str(REPO))
    from blender_addon import batch

    bad_map = tmp_path / "bad_map.json"
    bad_map.write_text('{"bones": {"elbow_of_doom": "x"}}')
    cases = [
        (["--bvh-rig", tmp_path / "none.bvh"], "BVH rig not found"),
        (["--rig", tmp_path / "none.blend"], "rig file not found"),
        (["--rig-object", "Armature"], "--rig-object needs --rig"),
        (["--bone-map", bad_map], "unknown joint names"),
        (["--rotation-mode", "QXZ"], "rotation mode must be one of"),
    ]
    for extra, words in cases:
        target = tmp_path / "x.blend"
        assert batch.main(["batch.py", "--prompt", "walk", "--out", str(target), *map(str, extra)]) == 2, extra
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err, (extra, err)
        assert not target.exists()
    # a map lacking required bones, found once the rig is in the scene: exit 2, no file
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"bones": {"pelvis": "Hips", "head": "Head"}}))
    proc = run_python([script, "--prompt", "walk", "--out", tmp_path / "y.blend", "--bvh-rig", BVH,
                       "--bone-map", partial], user_dir=tmp_path / "blender_user", timeout=120)
    assert proc.returncode == 2 and "left_knee" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert not (tmp_path / "y.blend").exists()


POSED_LINK = r"""
import numpy as np
from blender_addon.scene import read_rig as rig_io, write_action
from mld_core.rig import bone_maps
from test_retarget import iclone_like_rig
mixamo = bone_maps.load_presets()["mixamo"].bones
names = {{j: "mixamorig:" + mixamo[j][0].split(":")[-1] for j in mixamo}}  # the mixamo preset finds its Hips
from mld_core.rig import retarget as rt
rig = iclone_like_rig(names)
rig = rt.rig_from_heads(["placement"] + list(rig.names), [-1] + [p + 1 for p in rig.parents],  # a top control
                        np.concatenate([[[0.0, 0.0, 0.0]], rig.heads]), np.concatenate([[[0.0, 0.0, 0.2]], rig.tails]))
obj = rig_io.build_armature(rig, "iclone_like")
link = obj.pose.bones["mixamorig:Hips"]  # between the root (Hip) and the thighs: not keyed
link.rotation_quaternion = (0.9, 0.3, 0.1, 0.0)  # what a BVH import's motion leaves on it
obj.pose.bones["placement"].location = (0.5, 0.0, 0.0)  # above every keyed bone: where the user put the character
s = bpy.context.scene.mld_motion
s.target = obj
s.prompt, s.seconds, s.steps = "a person walks", 2.0, 2
out = {{"generate": sorted(bpy.ops.mld.generate()), "error": s.last_error}}
act = obj.animation_data.action
keyed = {{}}
for fc in write_action.fcurves_of(act):
    keyed.setdefault(fc.data_path.split('"')[1], set()).add(fc.data_path.split(".")[-1])
out["root_location"] = "location" in keyed.get("Hip", set())
out["link_keys"] = sorted(keyed.get("mixamorig:Hips", set()))
bpy.context.scene.frame_set(bpy.context.scene.frame_start + 5)
out["link_at_rest"] = bool(np.allclose(np.array(link.matrix_basis), np.eye(4), atol=1e-6))
out["placement"] = [sorted(keyed.get("placement", set())), list(obj.pose.bones["placement"].location)]
emit(out)
"""


def test_a_posed_link_between_keyed_bones_is_keyed_at_rest(tmp_path):
    from mld_core.testing import tiny_model

    model = tiny_model(tmp_path / "tiny")
    r = run_bpy_script(addon_script(POSED_LINK), tmp_path, timeout=180, MLD_MODEL_DIR=model)
    assert r["generate"] == ["FINISHED"] and r["error"] == ""
    assert r["root_location"]  # the bone the pelvis and the spine hang from carries the root motion
    assert r["link_keys"] == ["location", "rotation_quaternion", "scale"] and r["link_at_rest"]
    assert r["placement"] == [[], [0.5, 0.0, 0.0]]  # a control above the keyed bones keeps the user's placement
