"""The add-on inside bpy (Blender as a Python module), each test in its own subprocess: the extension zip
installed and driven through its operators on the canonical armature, the plain-package path, and the
headless batch script end to end. Uses a tiny random model (its motions are noise, which is all these
tests need: counts, names, properties, exact joint placement, files)."""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import pytest

from bpy_util import REPO, requires_bpy, run_bpy_script, run_python

pytestmark = [pytest.mark.bpy, requires_bpy]


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    from mld_core.testing import tiny_model

    return tiny_model(tmp_path_factory.mktemp("tiny") / "tiny_model")


@pytest.fixture(scope="module")
def addon_zip(tmp_path_factory, tiny_dir):
    sys.path.insert(0, str(REPO))
    import build_addon

    return build_addon.build(tmp_path_factory.mktemp("dist"), model_dir=tiny_dir, minilm=True, validate=False, quiet=True)


INSTALLED = r"""
import importlib, sys, os
import numpy as np
import bpy

ZIP, BLEND = {zip!r}, {blend!r}
out = {{}}
bpy.ops.wm.read_factory_settings(use_empty=True)
res = bpy.ops.extensions.package_install_files(filepath=ZIP, repo="user_default", enable_on_install=True)
out["install"] = sorted(res)
pkg = "bl_ext.user_default.mld_motion"
addon = sys.modules[pkg]
import mld_core
out["vendored_core"] = os.path.realpath(mld_core.__file__).startswith(os.path.realpath(os.path.dirname(addon.__file__)))
out["prefs"] = bpy.context.preferences.addons[pkg].preferences is not None
runtime = sys.modules[pkg + ".ui.runtime"]
operators = sys.modules[pkg + ".ui.operators"]
keys = sys.modules[pkg + ".scene.write_action"]
rig = importlib.import_module(pkg + ".scene.canonical_armature")
posing = importlib.import_module("mld_core.rig.canonical_pose")

ctx = bpy.context
scene = ctx.scene
s = scene.mld_motion
out["problem_no_armature"] = operators.generate_problem(ctx)
out["poll_no_armature"] = bpy.ops.mld.generate.poll()
bpy.ops.mld.create_armature()
obj = s.target
out["bones"] = len(obj.data.bones)
out["body"] = [o.name for o in obj.children]

# an Action the user made before: it must survive
prev = bpy.data.actions.new("hand_made")
obj.animation_data_create()
obj.animation_data.action = prev

scene.render.fps = 20
s.prompt, s.seconds, s.seed, s.steps, s.variants = "a person walks forward", 2.0, 4, 3, 2
out["generate"] = sorted(bpy.ops.mld.generate())
names = s.last_actions.split(", ")
out["names"] = names
out["assigned"] = obj.animation_data.action.name
out["frame_range"] = [scene.frame_start, scene.frame_end]
acts = [bpy.data.actions[n] for n in names]
out["fcurves"] = [len(keys.fcurves_of(a)) for a in acts]
out["keys_per_curve"] = sorted({{len(fc.keyframe_points) for a in acts for fc in keys.fcurves_of(a)}})
v2 = bpy.data.actions["walks_forward_s4_v2"]
out["props"] = {{k: v2[k] for k in v2.keys() if k.startswith("mld_")}}
out["fake_users"] = [a.use_fake_user for a in acts]
out["prev_kept"] = "hand_made" in bpy.data.actions and bpy.data.actions["hand_made"].use_fake_user

# the canonical armature follows the generated joints exactly
pipe = runtime.cache().get(None, "cpu")
ref = pipe(["a person walks forward"], seconds=2.0, num_inference_steps=3, seed=int(acts[0]["mld_seed"]))
target = posing.to_blender(ref.joints[0])
heads = rig.posed_heads(obj, scene, range(scene.frame_start, scene.frame_start + len(target)))
out["max_joint_error_m"] = float(np.linalg.norm(heads - target, axis=-1).max())
out["model_loads"] = runtime.cache().loads

# another scene frame rate: keys are resampled to it
scene.render.fps = 24
s.variants = 1
bpy.ops.mld.generate()
out["frames_24"] = s.last_frames
out["frame_end_24"] = scene.frame_end
a24 = obj.animation_data.action
out["keys_24"] = sorted({{len(fc.keyframe_points) for fc in keys.fcurves_of(a24)}})

# bad input: a report, no new Action
n_before = len(bpy.data.actions)
s.prompt = "!!!"
try:
    bpy.ops.mld.generate()
    out["bad_prompt"] = "no error"
except RuntimeError as exc:
    out["bad_prompt"] = str(exc)
out["bad_prompt_panel"] = s.last_error
out["actions_unchanged"] = len(bpy.data.actions) == n_before
s.prompt = ""
out["problem_empty_prompt"] = operators.generate_problem(ctx)

# the interactive path: worker thread + main-thread timer function
s.prompt = "a person jumps"
req = operators.request_from_settings(s, None)
runtime.submit(req, runtime.Target(obj.name, obj.session_uid, scene.name, True, False))
out["busy_problem"] = operators.generate_problem(ctx)
import time
deadline = time.time() + 60
while runtime._tick() is not None and time.time() < deadline:
    time.sleep(0.02)
out["async_action"] = obj.animation_data.action.name
out["async_message"] = s.last_message

# Cancel: stops within a step, keys nothing
n_before = len(bpy.data.actions)
job = runtime.submit(req.with_(steps=500), runtime.Target(obj.name, obj.session_uid, scene.name, True, False))
while job.step_done < 2 and not job.ended:
    time.sleep(0.001)
bpy.ops.mld.cancel()
deadline = time.time() + 60
while runtime._tick() is not None and time.time() < deadline:
    time.sleep(0.02)
out["cancel_state"] = job.state
out["cancel_steps"] = job.step_done
out["cancel_message"] = s.last_message
out["cancel_no_action"] = len(bpy.data.actions) == n_before

# another rig (the canonical bones renamed): retargeted through its detected bone map
apply = sys.modules[pkg + ".scene.key_takes"]
other = rig.create_canonical_armature(ctx, name="Other", body=False)
for bone in other.data.bones:
    bone.name = "rig:" + bone.name
out["problem_other"] = apply.check_target(other)
s.target, s.prompt = other, "a person waves"
bpy.ops.mld.generate()
act = other.animation_data.action
out["other_action"] = [act.name, act["mld_retargeted"], act["mld_exact"], len(keys.fcurves_of(act))]
s.target = obj

# save, reload: keys and provenance stay
bpy.ops.wm.save_as_mainfile(filepath=BLEND)
bpy.ops.wm.open_mainfile(filepath=BLEND)
reloaded = bpy.data.actions[names[0]]
out["reloaded_fcurves"] = len(keys.fcurves_of(reloaded))
out["reloaded_keys"] = sorted({{len(fc.keyframe_points) for fc in keys.fcurves_of(reloaded)}})
out["reloaded_prompt"] = reloaded["mld_prompt"]
out["reloaded_variant2"] = names[1] in bpy.data.actions
emit(out)
"""


def test_extension_zip_generates_on_the_canonical_armature(tmp_path, addon_zip):
    r = run_bpy_script(INSTALLED.format(zip=str(addon_zip), blend=str(tmp_path / "saved.blend")), tmp_path, timeout=240)
    assert r["install"] == ["FINISHED"] and r["vendored_core"] and r["prefs"]
    assert "No target armature" in r["problem_no_armature"] and r["poll_no_armature"] is False
    assert r["bones"] == 22 and r["body"] == ["MLD_Body"]
    assert r["generate"] == ["FINISHED"]
    # variants are created best first (quality badges), the best one assigned
    assert sorted(r["names"]) == ["walks_forward_s4_v1", "walks_forward_s4_v2"] and r["assigned"] == r["names"][0]
    assert r["fcurves"] == [22 * 4 + 22 * 3] * 2  # quaternion + location per bone (exact mode)
    assert r["keys_per_curve"] == [40]  # 2 s at 20 fps
    assert r["frame_range"] == [1, 40]
    props = r["props"]
    assert props["mld_prompt"] == "a person walks forward" and props["mld_seed"] == 5 and props["mld_variant"] == 1
    assert props["mld_request_seed"] == 4 and props["mld_steps"] == 3 and props["mld_seconds"] == 2.0
    assert props["mld_model_id"] == "tiny-text" and props["mld_addon_version"] == "0.1.0" and props["mld_guidance"] > 0
    assert r["fake_users"] == [True, True] and r["prev_kept"]
    assert r["max_joint_error_m"] < 0.01, r["max_joint_error_m"]
    assert r["model_loads"] == 1  # loaded once, reused
    assert r["frames_24"] == 47 and r["keys_24"] == [47] and r["frame_end_24"] == 47  # 39 frames / 20 fps * 24 + 1
    assert "no words" in r["bad_prompt"] and "no words" in r["bad_prompt_panel"] and r["actions_unchanged"]
    assert r["problem_empty_prompt"] == "Type a prompt first"
    assert "running" in r["busy_problem"]
    assert r["async_action"] == "jumps_s4" and "jumps_s4" in r["async_message"]
    assert r["cancel_state"] == "cancelled" and r["cancel_steps"] < 500 and r["cancel_message"] == "Cancelled"
    assert r["cancel_no_action"]
    assert r["problem_other"] == ""  # its bone map is detected (the canonical names under a namespace)
    assert r["other_action"] == ["waves_s4", 1, 0, 22 * 4 + 3]  # rotations + root location
    assert r["reloaded_fcurves"] == 154 and r["reloaded_keys"] == [40]
    assert r["reloaded_prompt"] == "a person walks forward" and r["reloaded_variant2"]


PLAIN = r"""
import sys
sys.path.insert(0, {repo!r})
import bpy, addon_utils
bpy.ops.wm.read_factory_settings(use_empty=True)
mod = addon_utils.enable("blender_addon", default_set=True)
out = {{"enabled": mod is not None}}
out["prefs"] = bpy.context.preferences.addons["blender_addon"].preferences.bl_rna.identifier
out["ops"] = [hasattr(bpy.ops.mld, n) for n in ("generate", "cancel", "create_armature", "randomize_seed")]
out["panel"] = hasattr(bpy.types, "MLD_PT_generate")
import mld_core, os
out["core_from_repo"] = os.path.dirname(os.path.dirname(mld_core.__file__)) == {repo!r}
bpy.context.scene.mld_motion.seed = 0
seeds = set()
for _ in range(3):
    bpy.ops.mld.randomize_seed()
    seeds.add(bpy.context.scene.mld_motion.seed)
out["random_seeds"] = len(seeds)

# Draw the panel and the preferences with a recording layout: every property and operator must exist.
sys.path.insert(0, os.path.join({repo!r}, "tests"))
from recording_layout import Host, Layout

from blender_addon.ui import panels
from blender_addon.ui import runtime
from blender_addon.ui import preferences
import time
ctx = bpy.context
drawn = {{}}
panels.MLD_PT_generate.draw(Host(), ctx)
drawn["empty_scene"] = list(Layout.calls); Layout.calls.clear()
bpy.ops.mld.create_armature()
s = ctx.scene.mld_motion
s.last_error = "Length must be between 1 and 9.8 seconds, got 12 and this sentence is long enough to wrap"
panels.MLD_PT_generate.draw(Host(), ctx)
drawn["error"] = list(Layout.calls); Layout.calls.clear()
s.last_error, s.last_message, s.last_frames, s.last_seconds, s.last_actions = "", "ok", 80, 0.4, "walk_s0, walk_s0_v2"
panels.MLD_PT_generate.draw(Host(), ctx)
drawn["result"] = list(Layout.calls); Layout.calls.clear()
gate = __import__("threading").Event()
runtime._runner = runtime.JobRunner(lambda job: (job.step(3, 10), gate.wait(20)))
job = runtime._runner.submit("x")
while job.step_done < 3:
    time.sleep(0.01)
panels.MLD_PT_generate.draw(Host(), ctx)
drawn["running"] = list(Layout.calls); Layout.calls.clear()
gate.set(); job.wait(10); runtime._runner.finished()
prefs = ctx.preferences.addons["blender_addon"].preferences
preferences.MLD_AddonPreferences.draw(type("P", (), {{"layout": Layout(), "model_dir": prefs.model_dir,
    "device": prefs.device, "threads": prefs.threads, "bl_rna": prefs.bl_rna}})(), ctx)
drawn["prefs"] = list(Layout.calls)
out["drawn"] = drawn
addon_utils.disable("blender_addon", default_set=True)
out["unregistered"] = not hasattr(bpy.types.Scene, "mld_motion") and not hasattr(bpy.types, "MLD_PT_generate")
emit(out)
"""


NO_TORCH = r"""
import sys
sys.modules["torch"] = None  # Blender's Python without PyTorch
sys.path.insert(0, {repo!r})
import bpy, addon_utils
bpy.ops.wm.read_factory_settings(use_empty=True)
mod = addon_utils.enable("blender_addon", default_set=True)
from blender_addon.ui import operators
from blender_addon import env
out = {{"enabled": mod is not None, "missing": env.missing_modules()}}
out["problem"] = operators.generate_problem(bpy.context)
out["poll"] = bpy.ops.mld.generate.poll()
out["create"] = sorted(bpy.ops.mld.create_armature())
out["problem_with_armature"] = operators.generate_problem(bpy.context)
emit(out)
"""


def test_registers_without_torch_and_says_how_to_get_it(tmp_path):
    r = run_bpy_script(NO_TORCH.format(repo=str(REPO)), tmp_path, timeout=120)
    assert r["enabled"] and "torch" in r["missing"]
    assert "torch" in r["problem"] and "Install dependencies" in r["problem"] and r["poll"] is False
    assert r["create"] == ["FINISHED"] and "Install dependencies" in r["problem_with_armature"]


def test_plain_package_registers_and_unregisters(tmp_path):
    r = run_bpy_script(PLAIN.format(repo=str(REPO)), tmp_path, timeout=120)
    assert r["enabled"] and r["prefs"] == "MLD_AddonPreferences"
    assert r["ops"] == [True] * 4 and r["panel"] and r["core_from_repo"]
    assert r["random_seeds"] >= 2
    assert r["unregistered"]
    drawn = {k: [tuple(c) for c in v] for k, v in r["drawn"].items()}
    assert ("operator", "mld.create_armature") in drawn["empty_scene"]
    assert ("operator", "mld.generate") in drawn["empty_scene"] and ("prop", "prompt") in drawn["empty_scene"]
    assert ("operator", "mld.randomize_seed") in drawn["empty_scene"]
    assert {"seconds", "variants", "seed", "steps", "guidance", "target", "exact", "set_frame_range"} <= {
        call[1] for call in drawn["empty_scene"] if call[0] == "prop"}
    assert ("operator", "mld.create_armature") not in drawn["error"]
    assert [c for c in drawn["error"] if c[0] == "label" and c[1].startswith("Length must be")]
    assert ("label", "80 frames in 0.40 s") in drawn["result"] and ("label", "walk_s0_v2") in drawn["result"]
    assert ("progress", "Denoising 3/10") in drawn["running"] and ("operator", "mld.cancel") in drawn["running"]
    assert ("operator", "mld.generate") not in drawn["running"]
    assert ("prop", "model_dir") in drawn["prefs"] and ("prop", "device") in drawn["prefs"]


CHECK_BLEND = r"""
import sys
sys.path.insert(0, {repo!r})
import bpy
bpy.ops.wm.open_mainfile(filepath={blend!r})
from blender_addon.scene.write_action import fcurves_of
obj = bpy.data.objects["MLD_Armature"]
acts = [a for a in bpy.data.actions if "mld_prompt" in a]
emit({{
    "actions": sorted((a.name, a["mld_prompt"], a["mld_seed"], len(fcurves_of(a)),
                       sorted({{len(fc.keyframe_points) for fc in fcurves_of(a)}})) for a in acts),
    "assigned": obj.animation_data.action.name,
    "fps": bpy.context.scene.render.fps,
    "frame_end": bpy.context.scene.frame_end,
    "preview_objects_left": [o.name for o in bpy.data.objects if o.name.startswith("MLD_Preview")],
}})
"""


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_batch_script_end_to_end(tmp_path, tiny_dir, capsys):
    prompts = tmp_path / "prompts.txt"
    prompts.write_text("# three takes\n30 a person walks forward\na person jumps\n50 a person waves\n")
    out = tmp_path / "out" / "takes.blend"
    script = REPO / "blender_addon" / "batch.py"
    user = tmp_path / "blender_user"
    args = [script, "--prompts", prompts, "--out", out, "--model", tiny_dir, "--steps", "3", "--seconds", "2",
            "--seed", "7", "--bvh-dir", tmp_path / "bvh"]
    proc = run_python(args + ["--preview", tmp_path / "out" / "takes.png"], user_dir=user, timeout=240)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    manifest = json.loads(out.with_suffix(".json").read_text())
    takes = manifest["takes"]
    assert [t["prompt"] for t in takes] == ["a person walks forward", "a person jumps", "a person waves"]
    assert [t["seed"] for t in takes] == [7, 8, 9]
    assert [t["frames"] for t in takes] == [30, 40, 50] and [t["scene_frames"] for t in takes] == [30, 40, 50]
    assert [t["name"] for t in takes] == ["walks_forward_s7", "jumps_s8", "waves_s9"]
    assert all(t["steps"] == 3 and t["time_s"] > 0 and t["model_id"] == "tiny-text" for t in takes)
    assert manifest["timing"]["load_s"] > 0 and manifest["settings"]["seconds"] == 2.0
    assert sorted(p.name for p in (tmp_path / "bvh").iterdir()) == ["jumps_s8.bvh", "walks_forward_s7.bvh", "waves_s9.bvh"]
    png = (tmp_path / "out" / "takes.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 1000
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temporary files left

    r = run_bpy_script(CHECK_BLEND.format(repo=str(REPO), blend=str(out)), tmp_path, timeout=120)
    assert [a[0] for a in r["actions"]] == ["jumps_s8", "walks_forward_s7", "waves_s9"]
    assert all(a[3] == 154 for a in r["actions"])
    assert {a[0]: a[4] for a in r["actions"]} == {"walks_forward_s7": [30], "jumps_s8": [40], "waves_s9": [50]}
    assert r["assigned"] == "walks_forward_s7" and r["fps"] == 20 and r["frame_end"] == 30
    assert r["preview_objects_left"] == []

    # existing outputs are refused without --overwrite, and left untouched (checked before any work: in-process)
    from blender_addon import batch

    before = _sha(out)
    assert batch.main(["batch.py", *map(str, args[1:])]) == 2
    err = capsys.readouterr().err
    assert "exists; pass --overwrite" in err and "Traceback" not in err
    assert _sha(out) == before

    # bad input: a message and exit code 2, nothing written
    bad = tmp_path / "bad.txt"
    bad.write_text("a person walks\n500 a person runs for far too long\n")
    cases = [
        (["--prompts", bad, "--out", tmp_path / "x.blend"], "line 2: Length must be between"),
        (["--prompts", tmp_path / "none.txt", "--out", tmp_path / "x.blend"], "prompt file not found"),
        (["--prompt", "walk", "--out", tmp_path / "x.txt"], "must name a .blend"),
        (["--prompt", "walk", "--out", tmp_path / "x.blend", "--model", tmp_path / "nomodel"], "model folder not found"),
        (["--prompt", "walk", "--out", tmp_path / "x.blend", "--model", "no_such_model"],
         "model folder not found: no_such_model (bundled models: default, v4_preview)"),
        (["--out", tmp_path / "x.blend"], "one of the arguments --prompts --prompt --jobs --merge is required"),
    ]
    for extra, words in cases:
        assert batch.main(["batch.py", *map(str, extra)]) == 2, extra
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err, (extra, err)
    # the same through a real process, for a problem found inside Blender's data
    proc = run_python([script, "--prompt", "walk", "--out", tmp_path / "x.blend", "--model", tiny_dir,
                       "--armature", "Nobody"], user_dir=user, timeout=120)
    assert proc.returncode == 2 and "no object named 'Nobody'" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "x.blend").exists()
