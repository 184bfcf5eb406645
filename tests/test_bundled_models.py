"""The models that ship with mld_core, named by folder or by name: resolution, refusals, the note that points a
prompt the model has not learned to a bundled model trained on its verbs, and the panel's choice (bpy-free)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mld_core import bundled
from mld_core.bundled import UnknownModel, bundled_models, model_folder, model_for_verbs
from mld_core.checkpoint import CheckpointError
from mld_core.cli import main
from mld_core.condition.coverage import Coverage
from mld_core.take_report import BeyondModel, check_prompts, other_model_note

REPO = Path(__file__).resolve().parents[1]


def _model(folder: Path, model_id: str, verbs=()) -> Path:
    """A folder that reads as a generation model's to mld_core.bundled (its config.json only)."""
    folder.mkdir(parents=True)
    config = {"format": "mld-core-model", "model_id": model_id}
    if verbs:
        config["verb_guide"] = {"actions": ["walk", *verbs], "scale": 8.0}
    (folder / "config.json").write_text(json.dumps(config))
    return folder


@pytest.fixture
def weights(tmp_path, monkeypatch):
    """A weights folder of its own: the default, a verb model, the evaluator (not a generation model), a stray file."""
    root = tmp_path / "weights"
    _model(root / "default", "base-v1")
    _model(root / "verbs", "verbs-v1", verbs=("jump", "crawl"))
    (root / "evaluator").mkdir()
    (root / "evaluator" / "config.json").write_text('{"feature_dim": 263}')
    (root / "notes.txt").write_text("x")
    monkeypatch.setattr(bundled, "WEIGHTS_DIR", root)
    return root


def test_bundled_models_lists_generation_models_default_first(weights):
    _model(weights / "aaa", "aaa-v1")
    assert list(bundled_models().items()) == [("default", "base-v1"), ("aaa", "aaa-v1"), ("verbs", "verbs-v1")]


def test_a_model_is_named_by_folder_or_by_bundled_name(weights, tmp_path, monkeypatch):
    assert model_folder(None) == model_folder("") == weights / "default"
    assert model_folder("verbs") == weights / "verbs"
    own = _model(tmp_path / "mine", "mine-v1")
    assert model_folder(own) == own and model_folder(str(own)) == own
    monkeypatch.chdir(tmp_path)
    (tmp_path / "verbs").mkdir()  # a folder of one's own wins over a bundled name
    assert model_folder("verbs") == Path("verbs")
    with pytest.raises(UnknownModel, match=r"^model folder not found: nope \(bundled models: default, verbs\)$"):
        model_folder("nope")
    assert model_folder("runs/nope") == Path("runs/nope")  # a path: loading it says what is wrong


def test_the_repository_bundles_the_default_and_the_v4_preview():
    found = bundled_models()
    assert list(found)[:1] == ["default"] and found["v4_preview"] == "mld-v4-preview" and "evaluator" not in found
    assert model_folder("v4_preview") == REPO / "mld_core" / "weights" / "v4_preview"
    ten = {"jump", "get_low", "on_ground", "crawl", "reach_floor", "inverted", "stand_up", "climb", "kick", "throw"}
    assert ten <= bundled.verb_labels("v4_preview") and not bundled.verb_labels("default")
    assert model_for_verbs(["jump"], found["default"]) == "v4_preview"


def test_loading_or_generating_from_an_unknown_model_is_one_line(tmp_path, capsys):
    from mld_core.pipeline import MLDPipeline

    with pytest.raises(CheckpointError, match="bundled models: default"):
        MLDPipeline.from_pretrained("no_such_model")
    out = tmp_path / "take.npz"
    assert main(["generate", "a person walks", "--model", "no_such_model", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.strip().startswith("error: model folder not found: no_such_model (bundled models: default")
    assert "Traceback" not in err and not out.exists()


def test_training_takes_a_bundled_name_for_init_and_vae(weights, capsys):
    from mld_core.training.cli import UsageError, _model_folder, _vae_dir

    assert _model_folder("verbs", "--init") == weights / "verbs"
    assert _model_folder(None, "--init") == weights / "default"
    with pytest.raises(UsageError, match="^--init: model folder not found: nope"):
        _model_folder("nope", "--init")
    assert _vae_dir("verbs") == str(weights / "verbs") and _vae_dir("runs/vae") == "runs/vae"
    with pytest.raises(UsageError, match="^--vae: model folder not found: nope"):
        _vae_dir("nope")
    with pytest.raises(UsageError, match="^--vae is empty"):
        _vae_dir("  ")


def test_model_for_verbs_needs_another_model_trained_on_every_verb(weights):
    assert model_for_verbs(["jump"], "base-v1") == "verbs"
    assert model_for_verbs(["jump", "crawl"], "base-v1") == "verbs"
    assert model_for_verbs(["jump", "throw"], "base-v1") is None  # not every verb
    assert model_for_verbs(["jump"], "verbs-v1") is None  # that model is the one in use
    assert model_for_verbs([], "base-v1") is None


def test_other_model_note_only_for_an_unknown_prompt_naming_the_verbs(weights):
    unknown = Coverage("a person jumps over a puddle", 0.5, "unknown")
    assert other_model_note(unknown, "base-v1") == ("the bundled model verbs is trained to make a jump "
                                                    "(--model verbs, or --model auto)")
    assert other_model_note(Coverage("a person jumps", 0.9, "known"), "base-v1") == ""
    assert other_model_note(Coverage("a person juggles", 0.4, "unknown"), "base-v1") == ""
    assert other_model_note(Coverage("a person crawls, then jumps", 0.4, "unknown"), "base-v1").endswith(
        "is trained to make a crawl and a jump (--model verbs, or --model auto)")


class _Pipe:
    model_id = "base-v1"

    def coverage(self, prompts):
        return [Coverage(p, 0.4 if "jump" in p else 0.95, "unknown" if "jump" in p else "known") for p in prompts]


def test_check_prompts_says_which_bundled_model_to_pick(weights):
    said = []
    coverages = check_prompts(_Pipe(), ["a person walks", "a person jumps"], warn=said.append)
    assert [c.verdict for c in coverages] == ["known", "unknown"]
    assert len(said) == 2 and said[0].startswith('warning: this model has not learned "a person jumps"')
    assert said[1] == "note: the bundled model verbs is trained to make a jump (--model verbs, or --model auto)"
    with pytest.raises(BeyondModel, match=r"; the bundled model verbs is trained to make a jump \(--model verbs, or "
                                          r"--model auto\) \(--strict: nothing generated\)$"):
        check_prompts(_Pipe(), ["a person jumps"], strict=True, warn=said.append)


def test_the_panel_choice_yields_to_a_folder_set_outside_the_panel(weights):
    from blender_addon.worker.model_choice import chosen_model_dir, folder_override, model_items

    assert [name for name, _, _ in model_items()] == ["auto", "default", "verbs"]
    assert model_items()[2][1] == "verbs-v1" and ", the default." in model_items()[1][2]
    # what the weights may be used for: these tiny folders record no training data, so their terms are unknown
    assert model_items()[1][2].endswith("Its weights: use as its training data's terms allow")
    assert chosen_model_dir("default") is None and chosen_model_dir(None) is None
    assert chosen_model_dir("verbs") == str(weights / "verbs")
    assert chosen_model_dir("gone") is None  # a choice saved in a .blend that is no longer bundled: the default
    assert chosen_model_dir("verbs", "/studio/model") == "/studio/model"
    assert folder_override(" /studio/model ", "/env/model") == "/studio/model"
    assert folder_override("", "/env/model") == "/env/model" and folder_override("  ", None) is None


def test_the_panel_knows_which_models_have_a_draft_and_notes_the_verb_model(tmp_path):
    from blender_addon.worker.model_choice import has_draft, model_id_of, other_model_line
    from mld_core.testing import tiny_model

    assert has_draft(None) and has_draft("v4_preview") and has_draft("auto")
    assert not has_draft(str(tiny_model(tmp_path / "no_draft")))
    assert model_id_of(None) == "mld-bandai-cpu-v3.8" and model_id_of("nope") == ""
    line = other_model_line("a person jumps over a puddle", "unknown", None, False)
    assert line == "the bundled model v4_preview is trained to make a jump (choose it, or Auto, as the panel's Model)"
    assert other_model_line("a person jumps over a puddle", "unknown", None, True).endswith(
        "(clear the Preferences' model folder, then choose it, or Auto, as the panel's Model)")
    assert other_model_line("a person jumps over a puddle", "unknown", "v4_preview", False) == ""
    assert other_model_line("a person jumps over a puddle", "near", None, False) == ""


def test_the_add_on_loads_a_bundled_model_by_name_and_caches_it_once(weights):
    from blender_addon.worker.model_cache import PipelineCache

    loaded = []
    cache = PipelineCache(loader=lambda folder, device: loaded.append(folder) or object())
    assert PipelineCache.key("verbs", "cpu") == PipelineCache.key(str(weights / "verbs"), "cpu")
    cache.get("verbs")
    cache.get(str(weights / "verbs"))
    assert len(loaded) == 1


def test_generate_on_the_default_points_an_unlearned_verb_prompt_to_the_preview(tmp_path, capsys):
    out = tmp_path / "jump.npz"
    assert main(["generate", "a person jumps over a puddle", "--steps", "3", "--seconds", "2", "--out", str(out)]) == 0
    err = capsys.readouterr().err.splitlines()
    learned = [n for n, line in enumerate(err) if line.startswith('warning: this model has not learned "a person jumps')]
    assert learned and err[learned[0] + 1] == ("note: the bundled model v4_preview is trained to make a jump "
                                               "(--model v4_preview, or --model auto)")
    assert main(["generate", "a person jumps over a puddle", "--strict", "--out", str(tmp_path / "strict.npz")]) == 2
    assert ("trained to make a jump (--model v4_preview, or --model auto) (--strict: nothing generated)"
            in capsys.readouterr().err)
    assert not (tmp_path / "strict.npz").exists()
