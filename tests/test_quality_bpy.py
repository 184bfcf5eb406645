"""Coverage and badges where a Blender user meets a take: Action custom properties, variants best first, the
panel's coverage line, badges and "What This Model Knows" (bpy in a subprocess, a tiny model with a coverage
index)."""

from __future__ import annotations

import pytest

from bpy_util import REPO, addon_script, requires_bpy, run_bpy_script
from mld_core.eval import quality

pytestmark = [pytest.mark.bpy, requires_bpy]

SCRIPT = r"""
import time
from blender_addon.ui import panels
from blender_addon.ui import quality_panel as quality_ui
from recording_layout import Host, Layout

ctx = bpy.context
s = ctx.scene.mld_motion
out = {{}}
bpy.ops.mld.create_armature()
ctx.scene.render.fps = 20
s.prompt, s.seconds, s.seed, s.steps, s.variants = "a person walks", 1.5, 2, 2, 3
out["generate"] = sorted(bpy.ops.mld.generate())
names = s.last_actions.split(", ")
out["props"] = [{{k: a[k] for k in a.keys() if k.startswith("mld_")}} for a in (bpy.data.actions[n] for n in names)]
out["assigned"] = s.target.animation_data.action.name == names[0]

# The coverage line: ask the watcher as the prompt's update callback does while the user types (a script runs in
# background mode, where the callback leaves it to the script), wait for the verdict, draw the panel.
key = quality_ui._model_key(ctx)
for text in ("a person walks", "a person juggles"):
    quality_ui.watcher().request(text, key)
    deadline = time.time() + 60
    while quality_ui.watcher().result(text, key) is None and time.time() < deadline:
        time.sleep(0.02)
    s.prompt = text
    Layout.calls.clear()
    panels.MLD_PT_generate.draw(Host(), ctx)
    out[text] = [c[1] for c in Layout.calls if c[0] == "label"]
out["check_s"] = quality_ui.watcher().seconds
Layout.calls.clear()
quality_ui.MLD_PT_known.draw(Host(), ctx)
out["known"] = [c[1] for c in Layout.calls if c[0] == "label"]

# A take on the side opposite the prompt's: a judge that always sees the other side (the tiny model's takes are noise)
# shows how the badge and the words reach the user.
from mld_core.eval import named_side
named_side.side_used = lambda ask, checks: "opposite"
s.prompt, s.variants = "a person walks and turns left", 1
out["opposite_generate"] = sorted(bpy.ops.mld.generate())
out["opposite_message"] = s.last_message
out["opposite_side"] = bpy.data.actions[s.last_actions.split(", ")[0]].get("mld_side")
Layout.calls.clear()
panels.MLD_PT_generate.draw(Host(), ctx)
out["opposite_labels"] = [c[1] for c in Layout.calls if c[0] == "label"]

# A first draw on the other side, its redraw on the named one: the take is the seed's second draw, and says why.
seen = []
named_side.side_used = lambda ask, checks: seen.append(ask) or ("opposite" if len(seen) == 1 else "named")
out["redrawn_generate"] = sorted(bpy.ops.mld.generate())
out["redrawn_message"] = s.last_message
action = bpy.data.actions[s.last_actions.split(", ")[0]]
out["redrawn_props"] = [action.get("mld_draw"), action.get("mld_side"), action.get("mld_seed")]
emit(out)
"""


@pytest.fixture(scope="module")
def tiny_with_index(tmp_path_factory):
    from mld_core.testing import tiny_model
    from test_quality import tiny_index

    model = tiny_model(tmp_path_factory.mktemp("tiny") / "tiny_model")
    tiny_index(model)
    return model


def test_actions_carry_coverage_and_badges_and_the_panel_shows_them(tmp_path, tiny_with_index):
    r = run_bpy_script(addon_script(SCRIPT), tmp_path, timeout=180,
                       MLD_MODEL_DIR=tiny_with_index)
    assert r["generate"] == ["FINISHED"] and r["assigned"]
    props = r["props"]
    assert len(props) == 3 and {p["mld_seed"] for p in props} == {2, 3, 4}
    for p in props:
        assert p["mld_coverage_verdict"] == "known" and p["mld_coverage_score"] == pytest.approx(1.0, abs=1e-3)
        assert p["mld_coverage_nearest"] == "a person walks."
        assert {"mld_adherence", "mld_similarity", "mld_skating", "mld_foot_float", "mld_penetration_cm",
                "mld_jitter"} <= set(p)
        assert 0.0 <= p["mld_adherence"] <= 100.0 and 0.0 <= p["mld_skating"] <= 1.0
    scores = [quality.rank_score(quality.Badges(p["mld_adherence"], p["mld_similarity"], p["mld_skating"],
                                                p["mld_foot_float"], p["mld_penetration_cm"], p["mld_jitter"]))
              for p in props]
    assert scores == sorted(scores, reverse=True)  # variants created best first, the best one assigned
    walk, juggle = r["a person walks"], r["a person juggles"]
    assert [t for t in walk if t.startswith("Known to this model (1.00)")]
    assert [t for t in juggle if t.startswith("Not learned by this model") and "closest 'a person walks'" in t]
    assert [t for t in walk if t.startswith("Foot skating: ")] and [t for t in walk if t.startswith("Adherence: ")]
    assert "planted toes sliding (real walks: 0.2)" in walk
    assert r["known"] == ["run: runs forward", "walk: walks forward"]
    assert r["opposite_generate"] == ["FINISHED"] and r["opposite_side"] == "opposite"
    assert r["opposite_message"].endswith("; it turns right, not left as the prompt says (try another seed, or more "
                                          "variants)")
    assert "Side: opposite" in r["opposite_labels"]
    assert r["redrawn_generate"] == ["FINISHED"] and r["redrawn_props"] == [1, "named", 2]
    assert r["redrawn_message"].endswith("; draw 1 of its seed: the first did not turn left as the prompt says")
    assert len(r["check_s"]) == 2


def test_batch_manifest_records_coverage_and_badges_per_take(tmp_path, tiny_with_index):
    import json

    from bpy_util import run_python

    out = tmp_path / "takes.blend"
    args = [REPO / "blender_addon" / "batch.py", "--prompt", "a person walks", "--prompt", "a person juggles",
            "--out", out, "--model", tiny_with_index, "--steps", "2", "--seconds", "1.5"]
    proc = run_python(args, user_dir=tmp_path / "blender_user", timeout=180)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    takes = json.loads(out.with_suffix(".json").read_text())["takes"]
    assert [t["coverage"]["verdict"] for t in takes] == ["known", "unknown"]
    assert takes[1]["coverage"]["nearest"][0]["caption"] == "a person walks."
    for t in takes:
        assert set(t["badges"]) == {"adherence", "similarity", "skating", "float", "penetration_cm", "jitter", "side",
                                    "verb"}
        assert t["badges"]["side"] is None and t["badges"]["verb"] is None  # neither prompt names a side or a verb
        assert t["draw"] == 0  # nor is drawn again
        assert t["coverage_verdict"] == t["coverage"]["verdict"]  # the Action's custom properties, flattened


def test_the_batch_draws_a_take_again_unless_told_not_to(tmp_path, tiny_with_index):
    import json

    from bpy_util import run_python
    from mld_core.pipeline import MLDPipeline

    prompt = "a person walks and turns left"
    expected = MLDPipeline.from_pretrained(tiny_with_index)(prompt, 1.5, seed=0, num_inference_steps=2).draws[0]
    assert expected > 0  # the tiny model's first draw of seed 0 misses the left turn
    base = [REPO / "blender_addon" / "batch.py", "--prompt", prompt, "--model", tiny_with_index, "--steps", "2",
            "--seconds", "1.5", "--seed", "0"]
    draws = {}
    for name, extra in (("default", []), ("off", ["--side-redraws", "0"])):
        out = tmp_path / f"{name}.blend"
        proc = run_python(base + ["--out", out] + extra, user_dir=tmp_path / "blender_user", timeout=180)
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        draws[name] = json.loads(out.with_suffix(".json").read_text())["takes"][0]["draw"]
        if name == "default":
            assert f"note: line 1: draw {expected} of its seed: the first" in proc.stderr
    assert draws == {"default": expected, "off": 0}
    proc = run_python(base + ["--out", tmp_path / "bad.blend", "--side-redraws", "9"],
                      user_dir=tmp_path / "blender_user", timeout=180)
    assert proc.returncode == 2 and "--side-redraws must be between 0 and 8" in proc.stderr
    assert not (tmp_path / "bad.blend").exists()


def test_the_batch_draws_a_take_again_for_its_verb_when_told_to(tmp_path, tiny_with_index):
    """--verb-redraws N: the take the batch keys is the pipeline's, and the batch says why it is a later draw (or
    that no draw showed the verb); the side's note is not given for it."""
    import json

    from bpy_util import run_python
    from mld_core.pipeline import MLDPipeline

    prompt = "a person jumps over a puddle"
    out = MLDPipeline.from_pretrained(tiny_with_index)(prompt, 1.5, seed=0, num_inference_steps=2, verb_redraws=2)
    assert out.redrawn_for[0] in ("verb", "verb missed")  # the tiny model's first draw of seed 0 shows no jump
    words = "an earlier one did not show a jump" if out.redrawn_for[0] == "verb" else "no draw of its seed showed"
    blend = tmp_path / "jump.blend"
    proc = run_python([REPO / "blender_addon" / "batch.py", "--prompt", prompt, "--model", tiny_with_index, "--steps",
                       "2", "--seconds", "1.5", "--seed", "0", "--verb-redraws", "2", "--out", blend],
                      user_dir=tmp_path / "blender_user", timeout=180)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert json.loads(blend.with_suffix(".json").read_text())["takes"][0]["draw"] == out.draws[0]
    assert words in proc.stderr and "turn" not in proc.stderr
    # without redraws the first draw is keyed, and its verb badge says what it does not show
    proc = run_python([REPO / "blender_addon" / "batch.py", "--prompt", prompt, "--model", tiny_with_index, "--steps",
                       "2", "--seconds", "1.5", "--seed", "0", "--verb-redraws", "0", "--out", tmp_path / "no.blend"],
                      user_dir=tmp_path / "blender_user", timeout=180)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "warning: line 1: it does not show a jump as the prompt says (try another seed" in proc.stderr
    # the tiny model has not learned the prompt, and the bundled v4 preview is trained on its verb
    assert ("note: line 1: the bundled model v4_preview is trained to make a jump (--model v4_preview, or --model "
            "auto)") in proc.stderr


def test_the_batch_with_model_auto_makes_each_line_by_its_model(tmp_path):
    """--model auto: each line by the bundled model that makes it, said per line; each take records its model."""
    import json

    from bpy_util import run_python

    jobs = tmp_path / "prompts.txt"
    jobs.write_text("a person jumps over a puddle\na person walks forward\n")
    blend = tmp_path / "auto.blend"
    proc = run_python([REPO / "blender_addon" / "batch.py", "--prompts", jobs, "--model", "auto", "--steps", "2",
                       "--seconds", "2", "--side-redraws", "0", "--verb-redraws", "0", "--out", blend],
                      user_dir=tmp_path / "blender_user", timeout=240)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    manifest = json.loads(blend.with_suffix(".json").read_text())
    assert manifest["model_id"] == "auto" and manifest["model_dir"] == "auto"
    assert [t["model_id"] for t in manifest["takes"]] == ["mld-v4-preview", "mld-bandai-cpu-v3.8"]
    assert "note: line 1: auto: v4_preview makes this prompt (trained to make a jump" in proc.stderr
    assert "line 2: auto" not in proc.stderr and "--model auto)" not in proc.stderr
