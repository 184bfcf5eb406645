"""Draft / Final and Live Preview in the add-on: edits regenerate a Draft take onto a preview Action (the newest edit
wins), turning it off gives the armature back its Action, Keep makes an ordinary take. Tiny model, bpy in a
subprocess; bpy's timers do not run headless, so the script calls them as Blender's event loop would."""

from __future__ import annotations

import pytest

from bpy_util import REPO, addon_script, requires_bpy, run_bpy_script
from mld_core.testing import tiny_model

pytestmark = [pytest.mark.bpy, requires_bpy]

SCRIPT = r"""
import time
from blender_addon.ui import live_preview, runtime
from blender_addon.scene import take_review
ctx = bpy.context
s = ctx.scene.mld_motion
bpy.ops.mld.create_armature()
arm = s.target
s.prompt, s.seconds, s.seed, s.steps = "a person walks", 2.0, 1, 2
out = {{}}
out["final"] = sorted(bpy.ops.mld.generate())
before = arm.animation_data.action.name
out["final_draft_flag"] = bool(arm.animation_data.action["mld_draft"])
s.mode = "DRAFT"
bpy.ops.mld.generate()
draft_take = arm.animation_data.action
out["draft_take"] = [bool(draft_take["mld_draft"]), int(draft_take["mld_steps"])]
arm.animation_data.action = bpy.data.actions[before]
actions_before = len(bpy.data.actions)

def settle():
    # the event loop: the debounce timer, then the runner's timer until the newest job is keyed
    live = live_preview.live()
    time.sleep(live.debounce_s + 0.02)
    live_preview.fire()
    job = live.job
    job.wait(60)
    runtime._tick()
    return job

live_preview.live().debounce_s = 0.05
s.mode = "FINAL"
s.live_preview = True
out["keep_enabled"] = bpy.ops.mld.keep_live.poll()
for k in range(5):
    s.prompt = "a person waves %d" % k
out["waiting"] = live_preview.live().waiting
live_preview.fire()  # too early: the edits have not paused
out["early"] = live_preview.live().job is None
first = settle()
preview = arm.animation_data.action
out["preview"] = [preview.name != before, bool(preview["mld_draft"]), preview["mld_prompt"],
                  take_review.pending(arm) == [preview.name]]
runner = runtime.runner()
work = runner._work
runner._work = lambda job: time.sleep(0.5) or work(job)  # a slower model: the next edit arrives while it runs
s.seed = 5
time.sleep(0.06)
live_preview.fire()
older = live_preview.live().job
s.seed = 6
second = settle()
runner._work = work
out["newest_wins"] = [older.state, second.state, int(arm.animation_data.action["mld_seed"])]
out["seeds"] = [older.request.seed, second.request.seed]
out["one_preview_action"] = len(bpy.data.actions) - actions_before
s.live_preview = False
out["restored"] = [arm.animation_data.action.name == before, take_review.pending(arm),
                   len(bpy.data.actions) - actions_before]
s.live_preview = True
settle()
out["keep"] = sorted(bpy.ops.mld.keep_live())
kept = arm.animation_data.action
out["kept"] = [kept.name != before, bool(kept["mld_draft"]), take_review.pending(arm), s.live_preview,
               len(bpy.data.actions) - actions_before]
emit(out)
"""


def test_draft_mode_and_live_preview(tmp_path):
    model = tiny_model(tmp_path / "tiny", draft=True)
    r = run_bpy_script(addon_script(SCRIPT), tmp_path, timeout=240, MLD_MODEL_DIR=model)
    assert r["final"] == ["FINISHED"] and r["final_draft_flag"] is False
    assert r["draft_take"] == [True, 2]  # Draft mode: the model's own 2 steps, whatever Steps says
    assert r["keep_enabled"] is True and r["waiting"] is True and r["early"] is True
    assert r["preview"] == [True, True, "a person waves 4", True]  # the last edit's prompt, in Draft
    assert r["newest_wins"] == ["cancelled", "done", 6]
    assert r["one_preview_action"] == 1  # each new preview replaces the last
    assert r["restored"] == [True, [], 0]  # off: the Action it had, no preview left behind
    assert r["keep"] == ["FINISHED"]
    assert r["kept"] == [True, False, [], False, 1]  # Keep: an ordinary Final take, Live Preview off


def test_batch_draft_records_the_steps_it_ran(tmp_path):
    import json

    from bpy_util import run_python

    model = tiny_model(tmp_path / "tiny", draft=True)
    out = tmp_path / "takes.blend"
    proc = run_python([REPO / "blender_addon" / "batch.py", "--prompt", "a person walks", "--model", model,
                       "--draft", "--seconds", "2", "--out", out], user_dir=tmp_path / "user", timeout=240)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    manifest = json.loads(out.with_suffix(".json").read_text())
    assert manifest["settings"]["draft"] is True and manifest["settings"]["steps"] == 2  # not --steps' 50
    assert manifest["settings"]["draft_teacher_steps"] == 0  # the tiny model's Draft has no teacher steps
    assert manifest["settings"]["draft_teacher_guidance"] is None and manifest["settings"]["draft_text_layers"] == 2
    assert manifest["settings"]["draft_timesteps"] is None  # the tiny model's Draft spreads its steps evenly
    assert manifest["takes"][0]["steps"] == 2
