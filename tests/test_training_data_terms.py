"""Whose terms a model's weights carry (mld_core.data.terms): data folders record them, every training stage and
tool that puts weights into a model folder adds what it read, and the card, the add-on's notice and the panel's
model choice say it."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from mld_core.checkpoint import CheckpointError, ModelConfig, load_config
from mld_core.cli import main
from mld_core.data import terms
from mld_core.testing import tiny_model
from test_training import TINY_DEN, TINY_VAE, _write_folder

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
sys.path.insert(0, str(REPO))


def test_one_source_that_forbids_makes_the_whole_non_commercial_and_an_unknown_one_unknown():
    assert terms.commercial_use([terms.CMU]) is True
    assert terms.commercial_use([terms.CMU, terms.KIT]) is None
    assert terms.commercial_use([terms.CMU, terms.KIT, terms.BANDAI]) is False
    # one name twice: the more restrictive entry wins, in the first one's place
    loose = {**terms.CMU, "commercial": True}
    strict = {**terms.CMU, "licence": "withdrawn", "commercial": False}
    assert terms.union([loose, terms.KIT], [strict]) == [strict, terms.KIT]
    assert terms.union([strict], [loose]) == [strict]
    assert terms.use_label([terms.BANDAI, terms.CMU]) == "non-commercial (CC BY-NC 4.0)"
    assert terms.use_label([terms.CMU]) == "may be used in commercial products"
    assert "not recorded" in terms.licence_summary([terms.CMU, terms.unrecorded("x")])


@pytest.mark.parametrize("bad", [[], "CMU", [{"name": "x", "licence": "y"}], [{"name": "", "licence": "y",
                                                                                 "commercial": True}],
                                 [{"name": "x", "licence": "y", "commercial": "yes"}],
                                 [{"name": "x", "licence": "y", "commercial": 1}],
                                 [{"name": "x", "licence": " ", "commercial": True}]])
def test_malformed_records_are_refused_in_one_line(bad, tmp_path):
    with pytest.raises(ValueError):
        terms.checked(bad)
    model = tiny_model(tmp_path / "m")
    config = json.loads((model / "config.json").read_text())
    (model / "config.json").write_text(json.dumps({**config, "training_data": bad}))
    with pytest.raises(CheckpointError) as info:
        load_config(model)
    assert "\n" not in str(info.value)


def test_a_folder_or_model_without_records_is_of_unknown_terms(tmp_path):
    assert terms.of_folder(tmp_path) == [terms.unrecorded(f"data folder {tmp_path.name}")]
    (tmp_path / terms.TERMS_FILE).write_text("{not json")
    assert terms.commercial_use(terms.of_folder(tmp_path)) is None
    config = ModelConfig(model_id="old")
    assert terms.of_model(config) == [terms.unrecorded("model old")]
    terms.add_to(config, [terms.CMU])
    assert config.training_data == [terms.unrecorded("model old"), terms.CMU]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A CMU-only tiny folder, a VAE and a denoiser trained on it."""
    root = tmp_path_factory.mktemp("terms")
    data = _write_folder(root / "cmu_only")
    terms.write(data, [terms.CMU])
    (root / "vae.json").write_text(json.dumps(TINY_VAE))
    assert main(["train", "vae", "--data", str(data), "--out", str(root / "vae"), "--steps", "10", "--threads", "1",
                 "--config", str(root / "vae.json")]) == 0
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(root / "vae"), "--out", str(root / "den"),
                 "--steps", "10", "--threads", "1", "--config", json.dumps(TINY_DEN)]) == 0
    return root


def test_runs_on_commercial_data_alone_say_so_and_one_step_from_bandai_weights_does_not(runs, tmp_path):
    assert load_config(runs / "vae").training_data == [terms.CMU]
    assert load_config(runs / "den").training_data == [terms.CMU]
    # a VAE fine-tuned from a model trained on Bandai carries Bandai's terms, whatever its own data
    bandai_vae = tmp_path / "bandai_vae"
    bandai_vae.mkdir()
    for name in ("vae.safetensors",):
        (bandai_vae / name).write_bytes((runs / "vae" / name).read_bytes())
    config = json.loads((runs / "vae" / "config.json").read_text())
    (bandai_vae / "config.json").write_text(json.dumps({**config, "training_data": [terms.BANDAI]}))
    assert main(["train", "vae", "--data", str(runs / "cmu_only"), "--out", str(tmp_path / "ft"), "--steps", "2",
                 "--threads", "1", "--init", str(bandai_vae), "--config", str(runs / "vae.json")]) == 0
    assert load_config(tmp_path / "ft").training_data == [terms.CMU, terms.BANDAI]
    # a denoiser on that VAE carries them too
    assert main(["train", "denoiser", "--data", str(runs / "cmu_only"), "--vae", str(tmp_path / "ft"), "--out",
                 str(tmp_path / "den"), "--steps", "2", "--threads", "1", "--config", json.dumps(TINY_DEN)]) == 0
    assert terms.commercial_use(load_config(tmp_path / "den").training_data) is False


def test_a_run_begun_before_the_records_resumes_with_its_first_sittings_data(runs, tmp_path):
    run = tmp_path / "vae"
    assert main(["train", "vae", "--data", str(runs / "cmu_only"), "--out", str(run), "--steps", "10",
                 "--threads", "1", "--config", str(runs / "vae.json")]) == 0
    config = json.loads((run / "config.json").read_text())
    del config["training_data"]
    (run / "config.json").write_text(json.dumps(config))
    import export_model  # its export reads the data its train_config.json names

    assert export_model.main([str(run), "--out", str(tmp_path / "exported")]) == 0
    assert load_config(tmp_path / "exported").training_data == [terms.CMU]
    assert "**may be used in commercial products**" in (tmp_path / "exported" / "MODEL_CARD.md").read_text()
    assert main(["train", "vae", "--data", str(runs / "cmu_only"), "--out", str(run), "--steps", "20",
                 "--threads", "1", "--config", str(runs / "vae.json"), "--resume"]) == 0
    assert load_config(run).training_data == [terms.CMU]


def test_the_card_and_the_addons_notice_say_whose_terms_the_weights_carry(runs, tmp_path):
    import build_addon
    import export_model

    assert export_model.main([str(runs / "den"), "--out", str(tmp_path / "cmu"),
                              "--data-description", "CMU"]) == 0
    card = (tmp_path / "cmu" / "MODEL_CARD.md").read_text()
    assert "**may be used in commercial products**" in card and "NSF EIA-0196217" in card
    assert "CC BY-NC" not in card.split("## Training")[0]
    notice = build_addon.weights_notice(tmp_path / "cmu")
    assert "in commercial products" in notice and "NSF EIA-0196217" in notice and "NonCommercial" not in notice
    # the same weights recorded as trained on Bandai too: non-commercial in the card and the notice
    config = json.loads((tmp_path / "cmu" / "config.json").read_text())
    (tmp_path / "cmu" / "config.json").write_text(json.dumps({**config, "training_data": [terms.CMU, terms.BANDAI]}))
    assert export_model.main([str(tmp_path / "cmu"), "--out", str(tmp_path / "mixed")]) == 0
    card = (tmp_path / "mixed" / "MODEL_CARD.md").read_text()
    assert "**non-commercial** (CC BY-NC 4.0)" in card and "Kobayashi et al. 2023" in card
    assert build_addon.weights_notice(tmp_path / "mixed") == build_addon.WEIGHTS_NOTICE
    # a folder of unknown terms: neither claim
    (tmp_path / "mixed" / "config.json").write_text(json.dumps({**config, "training_data": [terms.KIT]}))
    notice = build_addon.weights_notice(tmp_path / "mixed")
    assert "as its terms allow" in notice and "You may use them" not in notice


def test_tools_that_add_weights_or_captions_to_a_model_add_their_sources(runs, tmp_path, capsys):
    import attach_verb_guide
    import build_coverage_index

    model = tmp_path / "m"
    model.mkdir()
    for name in ("config.json", "vae.safetensors", "denoiser.safetensors"):
        (model / name).write_bytes((runs / "den" / name).read_bytes())
    other = _write_folder(tmp_path / "studio")
    terms.write(other, [terms.BANDAI])
    assert build_coverage_index.main(["--data", str(other), "--model", str(model), "--threads", "1"]) == 0
    assert load_config(model).training_data == [terms.CMU, terms.BANDAI]
    # a verb denoiser trained on other data brings its terms along
    action = tmp_path / "act"
    verb_data = _write_folder(tmp_path / "verbs", lambda k: f"a person {('jumps', 'kicks')[k % 2]}#a/DET#0.0#0.0\n")
    labels = json.loads((verb_data / "actions.json").read_text())
    (verb_data / "actions.json").write_text(json.dumps({"classes": ["jump", "kick"], "clips": {
        c: ("jump", "kick")[int(c[4:]) % 2] for c in labels["clips"]}}))
    terms.write(verb_data, [terms.KIT])
    assert main(["train", "denoiser", "--data", str(verb_data), "--vae", str(runs / "den"), "--out", str(action),
                 "--cond", "action", "--init", str(runs / "den"), "--steps", "2", "--threads", "1"]) == 0
    assert attach_verb_guide.main([str(runs / "den"), str(action), "--out", str(tmp_path / "guided")]) == 0
    assert load_config(tmp_path / "guided").training_data == [terms.CMU, terms.KIT]
    assert terms.commercial_use(load_config(tmp_path / "guided").training_data) is None


def test_the_panels_model_choices_say_what_the_weights_may_be_used_for():
    from blender_addon.worker.model_choice import model_items

    tips = {name: tip for name, _, tip in model_items()}
    assert tips["default"].endswith("Its weights: non-commercial (CC BY-NC 4.0)")
    assert load_config(REPO / "mld_core" / "weights" / "default").training_data == [terms.BANDAI]


def test_a_draft_and_its_text_encoder_installed_into_a_model_add_their_data(runs, tmp_path):
    import shutil

    model = tmp_path / "model"
    shutil.copytree(runs / "den", model)
    kit = _write_folder(tmp_path / "kit")
    terms.write(kit, [terms.KIT])
    assert main(["train", "draft", "--data", str(kit), "--teacher", str(model), "--out", str(tmp_path / "draft"),
                 "--threads", "1", "--steps", "2", "--install", "--config",
                 json.dumps({"batch_size": 8, "save_every": 10, "crops_per_clip": 2})]) == 0
    assert load_config(model).training_data == [terms.CMU, terms.KIT]
    bandai = _write_folder(tmp_path / "bandai")
    terms.write(bandai, [terms.BANDAI])
    assert main(["train", "draft-text", "--data", str(bandai), "--teacher", str(model), "--out",
                 str(tmp_path / "text"), "--threads", "1", "--steps", "2", "--install", "--config",
                 json.dumps({"batch_size": 8, "save_every": 10, "init_layers": [0], "val_texts": 4})]) == 0
    assert load_config(model).training_data == [terms.CMU, terms.KIT, terms.BANDAI]


def test_the_models_command_says_what_each_models_weights_may_be_used_for(runs, tmp_path, capsys):
    assert main(["models"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "default: mld-bandai-cpu-v3.8, non-commercial (CC BY-NC 4.0)" in out
    assert any(line.startswith("v4_preview: mld-v4-preview, non-commercial") for line in out)
    assert main(["models", str(runs / "den")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"{runs / 'den'}: den, may be used in commercial products" and "CMU Graphics Lab" in out[1]
    for bad in ("no_such_model", str(tmp_path)):
        assert main(["models", bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and len(err.strip().splitlines()) == 1


def test_a_take_records_what_the_weights_that_made_it_may_be_used_for(runs):
    from blender_addon.worker.generation import generate
    from blender_addon.worker.validation import validate_request
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained(runs / "den")
    request = validate_request("a person walks", 1.5, 3, 2, 0, 1, model_dir=str(runs / "den"))
    take = generate(pipe, request).takes[0]
    assert take.weights_use == "may be used in commercial products"
    assert take.provenance()["mld_weights_use"] == "may be used in commercial products"
    pipe.config.training_data = [terms.CMU, terms.BANDAI]
    assert generate(pipe, request).takes[0].provenance()["mld_weights_use"] == "non-commercial (CC BY-NC 4.0)"


def test_a_model_folder_set_in_the_preferences_says_what_its_weights_may_be_used_for(runs, tmp_path):
    from blender_addon.worker.model_choice import folder_weights_line

    folder = tmp_path / "mine"
    folder.mkdir()
    config = json.loads((runs / "den" / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps(config))
    assert folder_weights_line(str(folder)) == "Its weights: may be used in commercial products"
    (folder / "config.json").write_text(json.dumps({**config, "training_data": [terms.BANDAI]}))  # read again
    assert folder_weights_line(str(folder)) == "Its weights: non-commercial (CC BY-NC 4.0)"
    assert folder_weights_line(str(tmp_path / "missing")) == ""  # the panel's other line says it is missing
