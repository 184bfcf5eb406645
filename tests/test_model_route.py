"""Auto (mld_core.model_route): which bundled model a prompt goes to, a call's one model, the router loading each
model once, and --model auto end to end on the bundled models (generate, shards' fingerprint, limits), plus the
add-on's side: the panel's choice, the two-model cache and a request routed on the worker (bpy-free)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mld_core.cli import main
from mld_core.condition.coverage import Coverage
from mld_core.model_route import (AUTO, MixedRoute, ModelRouter, is_auto, model_for, model_for_call, route_line,
                                  routed, verbs_to_route)
from test_bundled_models import weights  # noqa: F401 - the fixture: a default and a model trained on jumps and crawls


def _cov(prompt, verdict, known=("walk", "kick")):
    return Coverage(prompt, 0.5, verdict, [], list(known))


def test_a_prompt_goes_to_the_model_trained_on_the_verbs_the_default_has_not_learned(weights):
    assert model_for(_cov("a person jumps", "unknown")) == "verbs"
    assert model_for(_cov("a person jumps", "near")) == "verbs"
    assert model_for(_cov("a person jumps", "known")) == "default"  # what the default learned stays with it
    assert model_for(_cov("a person jumps", "unavailable")) == "default"
    assert model_for(_cov("a person kicks high", "near")) == "default"  # kick is one of the default's contents
    assert verbs_to_route(_cov("a person kicks, then jumps", "unknown")) == ["jump"]
    assert model_for(_cov("a person kicks, then jumps", "unknown")) == "verbs"
    assert model_for(_cov("a person swims", "unknown")) == "default"  # no checked verb: no model is better
    assert model_for(_cov("a person climbs a ladder", "unknown")) == "default"  # no bundled model climbs here
    assert model_for(_cov("a person crawls, then jumps", "unknown")) == "verbs"
    assert route_line(_cov("a person walks", "known")) == ""
    assert route_line(_cov("a person jumps", "unknown")) == (
        "auto: verbs makes this prompt (trained to make a jump, which the default has not learned)")


def test_a_call_goes_to_one_model(weights):
    walk, jump = _cov("a person walks", "known"), _cov("a person jumps", "unknown")
    assert model_for_call([walk, walk], one_motion=False) == "default"
    assert model_for_call([jump, jump], one_motion=False) == "verbs"
    assert model_for_call([walk, jump], one_motion=True) == "verbs"  # a sequence: the model that makes every segment
    assert routed([walk, walk]) == ("default", [])
    assert routed([walk, jump, jump], one_motion=True) == ("verbs", [route_line(jump)])  # each prompt's line once
    with pytest.raises(MixedRoute, match=r"^auto: these prompts need different models \(default: prompts 1, 3; "
                                         r"verbs: prompt 2\): generate them apart, or name one with --model$"):
        model_for_call([walk, jump, walk], one_motion=False)


def test_auto_is_a_word_unless_a_folder_is_called_so(tmp_path, monkeypatch):
    assert is_auto("auto") and is_auto(" auto ") and not is_auto("Auto") and not is_auto(None)
    assert not is_auto("v4_preview") and not is_auto(Path("auto"))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "auto").mkdir()
    assert not is_auto("auto")  # a folder of one's own wins over the word, as over a bundled name


def test_the_router_loads_each_model_once_and_routes_on_the_defaults_coverage(weights):
    loaded = []

    class Pipe:
        def __init__(self, name):
            self.name = name

        def coverage(self, prompts):
            return [_cov(p, "known" if "walk" in p else "unknown") for p in prompts]

    router = ModelRouter(lambda name: loaded.append(name) or Pipe(name))
    assert router.pipe_for(["a person walks"])[0] == "default" and loaded == ["default"]
    name, pipe = router.pipe_for(["a person jumps"])
    assert (name, pipe.name) == ("verbs", "verbs") and loaded == ["default", "verbs"]
    assert router.pipe_for(["a person jumps"])[1] is pipe and loaded == ["default", "verbs"]
    with pytest.raises(MixedRoute):
        router.pipe_for(["a person walks", "a person jumps"])


def test_the_bundled_default_sends_verb_prompts_to_the_preview_and_keeps_its_own():
    """On the real default's coverage index: what it learned stays, what the preview is trained on goes there."""
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained(None)
    prompts = {"a person jumps over a puddle": "v4_preview", "a person does a handstand": "v4_preview",
               "a person crawls on the floor": "v4_preview", "a person sits down on a chair": "v4_preview",
               "a person walks forward and waves with the right hand": "default",
               "a person does a high kick": "default",  # the default's own kick content
               "a person bends forward at the waist to bow, then stands up straight": "default",
               "a person throws both hands up in the air": "default"}
    got = {c.prompt: model_for(c) for c in pipe.coverage(list(prompts))}
    assert got == prompts


def test_generate_with_model_auto_uses_the_model_the_prompt_goes_to(tmp_path, capsys):
    jump, walk = tmp_path / "jump.npz", tmp_path / "walk.npz"
    args = ["--steps", "3", "--seconds", "2", "--side-redraws", "0", "--verb-redraws", "0"]
    assert main(["generate", "a person jumps over a puddle", "--model", "auto", "--out", str(jump), *args]) == 0
    assert "auto: v4_preview makes this prompt (trained to make a jump" in capsys.readouterr().err
    assert main(["generate", "a person walks forward", "--model", "auto", "--out", str(walk), *args]) == 0
    assert "auto:" not in capsys.readouterr().err
    assert str(np.load(jump)["model_id"]) == "mld-v4-preview"
    assert str(np.load(walk)["model_id"]) == "mld-bandai-cpu-v3.8"
    prompts = tmp_path / "prompts.txt"
    prompts.write_text("a person jumps over a puddle\na person walks forward\n")
    mixed = tmp_path / "mixed.npz"
    assert main(["generate", "--prompts", str(prompts), "--model", "auto", "--out", str(mixed), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: auto: these prompts need different models (v4_preview: prompt 1; default: prompt 2): "
                   "generate them apart, or name one with --model"]
    assert not mixed.exists()


def test_auto_has_the_defaults_limits_and_a_fingerprint_of_every_bundled_model():
    from mld_core import inputs, shards

    assert inputs.model_limits(AUTO) == inputs.model_limits(None)
    auto = shards.model_fingerprint(AUTO)
    assert auto == shards.model_fingerprint("auto") and auto not in (shards.model_fingerprint(None),
                                                                     shards.model_fingerprint("v4_preview"))


def test_the_panel_offers_auto_first_and_routes_a_request_on_the_worker(weights):
    from blender_addon.worker import model_choice
    from blender_addon.worker.model_cache import PipelineCache

    assert [name for name, _, _ in model_choice.model_items()] == ["auto", "default", "verbs"]
    assert model_choice.chosen_model_dir("auto") == "auto" and model_choice.chosen_model_dir("auto", "/m") == "/m"
    assert model_choice.other_model_line("a person jumps", "unknown", "auto", False) == ""  # Auto goes there itself
    assert model_choice.auto_line("a person jumps", "unknown", ("walk",)) == (
        "Auto: verbs makes this prompt (trained to make a jump, which the default has not learned)")
    assert model_choice.auto_line("a person kicks", "near", ("kick",)) == ""
    assert model_choice.auto_line("a person jumps", "unavailable", ()) == ""

    loaded = []

    class Pipe:
        def __init__(self, folder):
            self.folder, self.draft_denoiser = folder, object() if folder is None else None

        def coverage(self, prompts):
            return [_cov(p, "known" if "walk" in p else "unknown") for p in prompts]

    cache = PipelineCache(loader=lambda folder, device: loaded.append(folder) or Pipe(folder))

    def request(prompt, draft=False, extra=None, model_dir="auto"):
        return SimpleNamespace(prompt=prompt, model_dir=model_dir, device="cpu", threads=0, draft=draft,
                               extra=extra or {})

    assert model_choice.pipe_for_request(cache, request("a person walks")).folder is None
    assert model_choice.pipe_for_request(cache, request("a person jumps")).folder == "verbs"
    sequence = {"sequence": [("a person walks", 2.0), ("a person jumps", 2.0)]}
    assert model_choice.pipe_for_request(cache, request("a person walks", extra=sequence)).folder == "verbs"
    assert loaded == [None, "verbs"]  # both kept: Auto moves between them without loading again
    assert model_choice.route_request(cache, request("a person jumps"))[1] == [
        "auto: verbs makes this prompt (trained to make a jump, which the default has not learned)"]
    assert model_choice.route_request(cache, request("a person walks"))[1] == []
    with pytest.raises(ValueError, match="^Auto chose verbs for this prompt and it has no Draft: use Final$"):
        model_choice.pipe_for_request(cache, request("a person jumps", draft=True))
    assert model_choice.pipe_for_request(cache, request("a person jumps", model_dir="verbs")).folder == "verbs"


def test_the_model_cache_keeps_the_two_used_last():
    from blender_addon.worker.model_cache import PipelineCache

    loaded = []
    cache = PipelineCache(loader=lambda folder, device: loaded.append(folder) or object())
    a, b = cache.get("/a"), cache.get("/b")
    assert cache.get("/a") is a and cache.get("/b") is b and loaded == ["/a", "/b"]
    cache.get("/c")  # drops /a, used longest ago
    assert cache.get("/b") is b and loaded == ["/a", "/b", "/c"]
    cache.get("/a")
    assert loaded == ["/a", "/b", "/c", "/a"]
