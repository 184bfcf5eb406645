"""The batch with a JSON job file (a directed take, a loop, a sequence): one Action per job, each job and its
constraints' residuals in the manifest. Tiny model, bpy in a subprocess."""

from __future__ import annotations

import json

import pytest

from bpy_util import REPO, addon_script, requires_bpy, run_bpy_script, run_python
from mld_core.testing import tiny_model

pytestmark = [pytest.mark.bpy, requires_bpy]


def test_batch_runs_a_job_file(tmp_path):
    model = tiny_model(tmp_path / "tiny")
    jobs = {"jobs": [
        {"prompt": "a person waves", "seconds": 2, "seed": 7,
         "keys": {"fps": 20, "keys": [{"frame": 20, "joints": {"pelvis": [0.1, 0.9, 0.3]}}]}},
        {"prompt": "a person walks", "seconds": 2, "loop": True, "path": {"points": [[0, 0, 0], [39, 0, 1]]}},
        {"sequence": [{"prompt": "a person walks", "seconds": 2}, {"prompt": "a person bows", "seconds": 2}]},
    ]}
    (tmp_path / "jobs.json").write_text(json.dumps(jobs))
    out = tmp_path / "takes.blend"
    proc = run_python([REPO / "blender_addon" / "batch.py", "--jobs", tmp_path / "jobs.json", "--model", model,
                       "--steps", "2", "--nla", "--out", out], user_dir=tmp_path / "user", timeout=240)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    takes = json.loads(out.with_suffix(".json").read_text())["takes"]
    assert [t["job"] for t in takes] == jobs["jobs"]
    assert takes[0]["seed"] == 7 and takes[1]["seed"] == 1 and takes[2]["seed"] == 2  # a job's seed wins
    assert [c["kind"] for c in takes[0]["constraints"]] == ["PoseKeys"]
    assert [c["kind"] for c in takes[1]["constraints"]] == ["RootPath", "Loop"]
    assert "constraints" not in takes[2]  # a sequence's seam is judged on the joined take, against real motion
    (seam,) = takes[2]["seams"]
    assert seam["segment"] == 2 and seam["jerk"] > 950.0 and not seam["within_real"]  # the tiny model jerks
    assert 'warning: job 3: the seam into segment 2 ("a person bows") jerks' in proc.stderr
    assert takes[2]["frames"] == 80  # 2 s + 2 s, one motion
    # --nla: each take on its own track; the sequence's as one strip per segment, back to back, of one Action
    tracks = run_bpy_script(STRIPS.format(blend=str(out)), tmp_path)
    assert [len(t) for t in tracks] == [1, 1, 2]
    (walk, bow) = tracks[2]
    assert walk[0] == "a person walks" and bow[0] == "a person bows" and walk[1] == bow[1]
    assert walk[2:] == [1.0, 31.0, 1.0, 31.0] and bow[2:] == [31.0, 80.0, 31.0, 80.0]  # the bow's own keys: 30..79


STRIPS = r"""
import bpy
bpy.ops.wm.open_mainfile(filepath={blend!r})
arm = [o for o in bpy.data.objects if o.type == "ARMATURE"][0]
emit([[[s.name, s.action.name, s.frame_start, s.frame_end, s.action_frame_start, s.action_frame_end]
       for s in t.strips] for t in arm.animation_data.nla_tracks])
"""


PANEL = r"""
import numpy as np
from blender_addon.ui import operators
ctx = bpy.context
s = ctx.scene.mld_motion
bpy.ops.mld.create_armature()
ctx.scene.render.fps = 20
bpy.ops.curve.primitive_bezier_curve_add(location=(0, -1.0, 0))
curve = ctx.object
curve.scale = (2.0, 2.0, 2.0)  # the handles span x -2..2 at y = -1: a 4 m arc across the character's front
s.prompt, s.seconds, s.seed, s.steps = "a person walks", 2.0, 1, 2
out = {{"free": operators.direction_of(s, 40).items}}
s.loop, s.follow_curve = True, curve
c = operators.direction_of(s, 40)
out["kinds"] = [type(i).__name__ for i in c.items]
path = c.items[1]
out["path_start_end"] = [path.points[0].tolist(), path.points[-1].tolist()]
out["path_length"] = float(np.linalg.norm(np.diff(path.points, axis=0), axis=-1).sum())
request = operators.request_from_settings(s, None)
out["request_kinds"] = [type(i).__name__ for i in request.extra["constraints"].items]
ctx.view_layer.objects.active = s.target
out["generate"] = sorted(bpy.ops.mld.generate())
emit(out)
"""


def test_panel_loop_and_follow_curve(tmp_path):
    from bpy_util import run_bpy_script

    model = tiny_model(tmp_path / "tiny")
    r = run_bpy_script(addon_script(PANEL), tmp_path, timeout=180, MLD_MODEL_DIR=model)
    assert r["free"] == []
    assert r["kinds"] == ["Loop", "RootPath"] and r["request_kinds"] == ["Loop", "RootPath"]
    start, end = r["path_start_end"]
    assert start == [0.0, 0.0] and end[0] == pytest.approx(4.0, abs=0.05) and abs(end[1]) < 0.05
    assert 4.0 < r["path_length"] < 6.0  # the arc, measured along the evaluated curve
    assert r["generate"] == ["FINISHED"]


REVIEW = r"""
ctx = bpy.context
s = ctx.scene.mld_motion
bpy.ops.mld.create_armature()
obj = s.target
mine = bpy.data.actions.new("hand_made")
obj.animation_data_create()
obj.animation_data.action = mine
s.prompt, s.seconds, s.steps, s.preview = "a person walks", 2.0, 2, True
out = {{"poll_before": bpy.ops.mld.reject_take.poll()}}
bpy.ops.mld.generate()
made = s.last_actions.split(", ")
out["playing"] = obj.animation_data.action.name
out["poll_after"] = bpy.ops.mld.reject_take.poll()
bpy.ops.mld.reject_take()
out["after_reject"] = obj.animation_data.action.name
out["made_left"] = [n for n in made if n in bpy.data.actions]
bpy.ops.mld.generate()
kept = s.last_actions.split(", ")
bpy.ops.mld.accept_take()
out["after_accept"] = obj.animation_data.action.name
out["kept"] = [n for n in kept if n in bpy.data.actions and bpy.data.actions[n].use_fake_user]
out["made"], out["kept_names"] = made, kept
out["hand_made_kept"] = "hand_made" in bpy.data.actions
emit(out)
"""


def test_preview_then_reject_or_accept(tmp_path):
    from bpy_util import run_bpy_script

    model = tiny_model(tmp_path / "tiny")
    r = run_bpy_script(addon_script(REVIEW), tmp_path, timeout=180, MLD_MODEL_DIR=model)
    assert r["poll_before"] is False and r["poll_after"] is True
    assert r["playing"] == r["made"][0]
    assert r["after_reject"] == "hand_made" and r["made_left"] == []  # what was there is back; the take is gone
    assert r["after_accept"] == r["kept_names"][0] and r["kept"] == r["kept_names"] and r["hand_made_kept"]


ARMATURE_KEYS = r"""
import math
import numpy as np
from blender_addon.ui import operators
ctx = bpy.context
scene = ctx.scene
scene.render.fps = 20
s = scene.mld_motion
bpy.ops.mld.create_armature()
obj = s.target
obj.location = (1.0, 2.0, 0.0)
pb = obj.pose.bones["left_shoulder"]
pb.rotation_mode = "QUATERNION"
pb.keyframe_insert("rotation_quaternion", frame=1)
pb.rotation_quaternion = (math.cos(0.6), 0.0, math.sin(0.6), 0.0)
pb.keyframe_insert("rotation_quaternion", frame=31)
pb.keyframe_insert("rotation_quaternion", frame=200)  # beyond the take: not used
scene.frame_set(31)
wrist = list(obj.matrix_world @ obj.pose.bones["left_shoulder"].head)
s.prompt, s.seconds, s.steps, s.use_armature_keys = "a person waves", 2.0, 2, True
c = operators.direction_of(s, 40, obj)
keys = c.items[0]
out = {{"frames": sorted(keys.targets), "joints": sorted(keys.targets[30]),
       "shoulder": keys.targets[30]["left_shoulder"], "expected": [wrist[0] - 1.0, wrist[2], -(wrist[1] - 2.0)],
       "frame_restored": scene.frame_current}}
s.keys_selected_only = True
for pb in obj.pose.bones:
    if hasattr(pb, "select"):
        pb.select = False
    else:
        pb.bone.select = False
try:
    operators.direction_of(s, 40, obj)
    out["none_selected"] = "no error"
except ValueError as exc:
    out["none_selected"] = str(exc)
emit(out)
"""


def test_use_keys_on_the_armature(tmp_path):
    from bpy_util import run_bpy_script

    r = run_bpy_script(addon_script(ARMATURE_KEYS), tmp_path, timeout=120)
    assert r["frames"] == [0, 30]  # scene frames 1 and 31 (frame 200 is past the 2 s take)
    assert r["joints"] == ["left_shoulder"]  # only the keyed bone's joint
    assert r["shoulder"] == pytest.approx(r["expected"], abs=1e-5)  # relative to the armature, model axes
    assert r["frame_restored"] == 31
    assert "no keys in the take's frame range" in r["none_selected"]


def test_typing_a_prompt_raises_nothing(tmp_path):
    """The prompt's update callback (the coverage line) runs without an error on stderr."""
    script = tmp_path / "type.py"
    script.write_text(addon_script("bpy.context.scene.mld_motion.prompt = 'a person jumps'\nprint('typed')\n"))
    proc = run_python([script], user_dir=tmp_path / "user", timeout=120)
    assert proc.returncode == 0 and "typed" in proc.stdout
    assert "Traceback" not in proc.stderr and "Error" not in proc.stderr, proc.stderr[-2000:]


SEQUENCE = r"""
ctx = bpy.context
ctx.scene.render.fps = 20
s = ctx.scene.mld_motion
bpy.ops.mld.create_armature()
s.steps = 2
s.prompt, s.seconds = "a person walks", 2.0
bpy.ops.mld.sequence_edit(action="ADD")
s.prompt, s.seconds = "a person bows", 3.0
bpy.ops.mld.sequence_edit(action="ADD")
bpy.ops.mld.sequence_edit(action="UP")  # the bow first
out = {{"rows": [(r.prompt, r.seconds) for r in s.sequence]}}
out["generate"] = sorted(bpy.ops.mld.generate())
out["frames"], out["actions"], out["message"] = s.last_frames, s.last_actions, s.last_message
s.sequence[1].prompt = "!!!"
try:
    out["bad"] = sorted(bpy.ops.mld.generate())
except RuntimeError as exc:  # an operator's ERROR report, as a script sees it
    out["bad"] = str(exc)
out["error"] = s.last_error
emit(out)
"""


def test_panel_sequence_makes_one_take(tmp_path):
    from bpy_util import run_bpy_script

    r = run_bpy_script(addon_script(SEQUENCE), tmp_path, timeout=180, MLD_MODEL_DIR=tiny_model(tmp_path / "t"))
    assert r["rows"] == [["a person bows", 3.0], ["a person walks", 2.0]]
    assert r["generate"] == ["FINISHED"] and r["frames"] == 100 and "," not in r["actions"]  # 3 s + 2 s, one Action
    assert 'the seam into segment 2 ("a person walks") jerks' in r["message"]  # the tiny model's seam is rough
    assert "Sequence segment 2" in r["bad"] and "Sequence segment 2" in r["error"]
