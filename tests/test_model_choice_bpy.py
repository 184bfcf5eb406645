"""The panel's Model: Auto and the bundled models to choose from, the choice reaching Generate's request and the coverage
check, a folder set in the Preferences winning over it, and why Draft is off for a model without one (bpy in a
subprocess; nothing is generated)."""

from __future__ import annotations

import pytest

from bpy_util import REPO, addon_script, requires_bpy, run_bpy_script

pytestmark = [pytest.mark.bpy, requires_bpy]

SCRIPT = r"""
from blender_addon.ui import operators, panels
from blender_addon.ui import quality_panel as quality_ui
from recording_layout import Host, Layout

ctx = bpy.context
s = ctx.scene.mld_motion
out = {{"start": s.model}}

def drawn():
    Layout.calls.clear()
    panels.MLD_PT_generate.draw(Host(), ctx)
    return [list(c) for c in Layout.calls]

for model in ("auto", "default", "v4_preview"):
    s.model = model
    out[model] = {{"request": operators.request_from_settings(s, None).model_dir, "key": quality_ui._model_key(ctx)[0],
                   "final": drawn(), "final_problem": operators.generate_problem(ctx)}}
    s.mode = "DRAFT"
    out[model].update(draft=drawn(), draft_problem=operators.generate_problem(ctx))
    s.mode = "FINAL"
try:
    s.model = "no_such_model"
    out["bad"] = "accepted"
except TypeError as exc:
    out["bad"] = str(exc)
emit(out)
"""


def _labels(calls):
    return [c[1] for c in calls if c[0] == "label"]


def test_the_panel_chooses_a_bundled_model_and_says_when_it_has_no_draft(tmp_path):
    r = run_bpy_script(addon_script(SCRIPT), tmp_path, timeout=120,
                       MLD_MODEL_DIR="")
    no_draft = "This model has no Draft: use Final (Live Preview needs a Draft)"
    assert r["start"] == "auto"  # a new scene starts on Auto
    assert r["auto"]["request"] == "auto" == r["auto"]["key"]  # routed per request (model_choice.pipe_for_request)
    assert no_draft not in _labels(r["auto"]["draft"]) and r["auto"]["draft_problem"] == r["default"]["draft_problem"]
    assert r["default"]["request"] is None and r["default"]["key"] is None  # the bundled default, as before
    assert ["prop", "model"] in r["default"]["final"] and no_draft not in _labels(r["default"]["draft"])
    preview = r["v4_preview"]
    assert preview["request"] == str(REPO / "mld_core" / "weights" / "v4_preview") == preview["key"]
    assert no_draft not in _labels(preview["draft"])  # the preview has its own Draft
    # Generate's poll says the armature comes next, in Draft as in Final, on every bundled model
    assert r["default"]["draft_problem"] == preview["final_problem"] == preview["draft_problem"]
    assert "no_such_model" in r["bad"]


def test_a_folder_set_outside_the_panel_wins_and_is_named(tmp_path):
    from mld_core.testing import tiny_model

    model = tiny_model(tmp_path / "studio_model")
    r = run_bpy_script(addon_script(SCRIPT), tmp_path, timeout=120,
                       MLD_MODEL_DIR=str(model))
    for choice in ("auto", "default", "v4_preview"):
        assert r[choice]["request"] == str(model) == r[choice]["key"]
        assert ["prop", "model"] not in r[choice]["final"]
        assert "Model: studio_model (set in Preferences)" in _labels(r[choice]["final"])
    assert "This model has no Draft: use Final (Live Preview needs a Draft)" in _labels(r["default"]["draft"])
    # Generate's poll says why it is off in Draft, and not in Final (the armature comes next there)
    assert r["default"]["draft_problem"] == "This model has no Draft: use Final" != r["default"]["final_problem"]


ROUTE_SCRIPT = r"""
from blender_addon.ui import quality_panel as quality_ui
from recording_layout import Layout

ctx = bpy.context
s = ctx.scene.mld_motion
out = {{}}
for model in ("auto", "default"):
    s.model = model
    for prompt in ("a person jumps over a puddle", "a person walks forward"):
        s.prompt = prompt
        key = quality_ui._model_key(ctx)
        w = quality_ui.watcher()
        with w._lock:  # the watcher's thread does this after the debounce; here at once
            w._results[(prompt, key)] = quality_ui._check(prompt, key)
        Layout.calls.clear()
        quality_ui.draw_coverage(Layout(), s, ctx)
        out[model + ": " + prompt] = [c[1] for c in Layout.calls if c[0] == "label"]
emit(out)
"""


def test_under_auto_the_panel_says_which_model_makes_the_prompt(tmp_path):
    """Auto: the line under a prompt the default has not learned that names a verb the preview is trained on says
    the preview makes it (and points to no other model); other prompts and the default's own choice are
    drawn as before."""
    r = run_bpy_script(addon_script(ROUTE_SCRIPT), tmp_path, timeout=180,
                       MLD_MODEL_DIR="")
    assert r["auto: a person jumps over a puddle"] == [
        "Auto: v4_preview makes this prompt (trained to make a jump, which the default has not learned)"]
    assert r["auto: a person walks forward"] == r["default: a person walks forward"]
    assert r["auto: a person walks forward"][0].startswith("Known to this model")
    jump = r["default: a person jumps over a puddle"]
    assert jump[0].startswith("Not learned by this model") and "choose it, or Auto, as the panel's Model" in jump[1]
