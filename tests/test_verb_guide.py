"""Verb guidance: an action denoiser on a text model's latents guiding the takes whose prompt names its label (tiny
seeded models)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mld_core.checkpoint import CheckpointError, load_config
from mld_core.condition.verb_guide import VerbGuide
from mld_core.models.denoiser import DenoiserConfig, LatentDenoiser
from mld_core.models.transformer import TransformerConfig
from mld_core.pipeline import MLDPipeline
from mld_core.sampling import VerbGuidance, guided_eps
from mld_core.testing import tiny_model

REPO = Path(__file__).resolve().parents[1]
ATTACH = REPO / "scripts" / "attach_verb_guide.py"
BLOCK = TransformerConfig(dim=16, heads=2, ff_dim=32, layers=1, dropout=0.0)
PROMPTS = ["a person hops over a puddle", "a person waves", "someone kicks a ball"]


def _action_denoiser(seed: int = 0, classes: int = 3) -> LatentDenoiser:
    torch.manual_seed(seed)
    den = LatentDenoiser(DenoiserConfig(latent_tokens=2, latent_dim=16, cond="action", num_actions=classes,
                                        text_pool_tokens=0, transformer=BLOCK)).eval()
    with torch.no_grad():  # an output that moves with its input, whatever the initialisation
        for p in den.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return den


def _attach(text: Path, action: Path, out: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ATTACH), str(text), str(action), "--out", str(out), *args],
                          capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """A tiny text model, an action model with the same VAE (labels jump, walk, kick), and the two attached."""
    root = tmp_path_factory.mktemp("verb_guide")
    text = tiny_model(root / "text", seed=0)
    action = tiny_model(root / "action", seed=0, cond="action", actions=("jump", "walk", "kick"))
    torch.manual_seed(1)
    fresh = LatentDenoiser(load_config(action).denoiser).state_dict()
    state = {k: v + 0.1 * torch.randn_like(v) for k, v in fresh.items()}
    from safetensors.torch import save_file

    save_file(state, str(action / "denoiser.safetensors"))  # a denoiser whose labels change what it predicts
    guided = root / "guided"
    proc = _attach(text, action, guided, "--scale", "3")
    assert proc.returncode == 0, proc.stderr
    return text, action, guided


def test_a_guide_takes_the_prompts_that_name_one_of_its_labels_by_a_checked_verb():
    guide = VerbGuide(_action_denoiser(), ["walk", "kick", "jump"], 2.0)
    assert guide.verbs == ["jump", "kick"]  # walk is a label but not a checked verb
    rows, labels = guide.rows_and_labels(PROMPTS + ["a person throws a ball", "jump"])
    assert rows.tolist() == [0, 2, 4] and labels.tolist() == [2, 1, 2]
    rows, labels = guide.rows_and_labels(["a person walks"])
    assert rows.tolist() == [] and labels.tolist() == []
    two = VerbGuide(_action_denoiser(classes=4), ["jump", "stand_up", "get_low", "on_ground"], 2.0)
    rows, labels = two.rows_and_labels(["a person stands up from sitting on the ground", "a person sits, then jumps"])
    assert labels.tolist() == [1, 2]  # the verb named first, not the table's first


def test_verbs_in_order_follows_the_sentence():
    from mld_core.data.verbs import verbs_in, verbs_in_order

    text = "a person stands up from sitting on the ground"
    assert verbs_in(text) == ["get_low", "on_ground", "stand_up"]
    assert verbs_in_order(text) == ["stand_up", "get_low", "on_ground"]
    assert verbs_in_order("jumps and kicks") == ["jump", "kick"] and verbs_in_order("a person waves") == []


def test_the_term_is_added_on_its_rows_only_as_scale_times_the_labels_guidance():
    text_den = _action_denoiser(seed=1)  # any denoiser stands for the text one: only its eps is read
    action_den = _action_denoiser(seed=2)
    g = torch.Generator().manual_seed(0)
    z, lengths = torch.randn(3, 2, 16, generator=g), torch.tensor([40, 60, 80])
    cond, null = text_den.condition_tokens(3, actions=torch.tensor([0, 1, 2])), text_den.null_tokens(3)
    rows = torch.tensor([0, 2])
    a_cond = action_den.condition_tokens(2, actions=torch.tensor([1, 1]))
    a_null = action_den.null_tokens(2)
    with torch.no_grad():
        base = guided_eps(text_den, z, 500, cond, null, lengths, 4.0)
        eps = VerbGuidance(action_den, rows, a_cond, a_null, 2.5).add_to(base, z, 500, lengths)
        t = torch.full((2,), 500)
        expected = 2.5 * (action_den(z[rows], t, a_cond, lengths[rows]) - action_den(z[rows], t, a_null, lengths[rows]))
    assert torch.equal(eps[1], base[1])
    assert torch.allclose(eps[rows] - base[rows], expected, atol=1e-5)
    assert float(expected.abs().max()) > 1e-3  # the term is not nothing


def test_the_attached_folder_loads_its_guide_and_guides_only_the_named_verbs(folders):
    text, action, guided = folders
    config = load_config(guided)
    assert config.verb_guide.actions == ["jump", "walk", "kick"] and config.verb_guide.scale == 3.0
    assert config.provenance["verb_guide"]["model_id"] == "tiny-action"
    assert "## Verb guidance" in (guided / "MODEL_CARD.md").read_text()
    assert (text / "MODEL_CARD.md").read_text() in (guided / "MODEL_CARD.md").read_text()
    plain, pipe = MLDPipeline.from_pretrained(text), MLDPipeline.from_pretrained(guided)
    assert plain.verb_guide is None and pipe.verb_guide.verbs == ["jump", "kick"]
    kw = dict(seconds=2.0, seed=5, num_inference_steps=3, repair=False, side_redraws=0)
    a, b = plain(PROMPTS, **kw).joints, pipe(PROMPTS, **kw).joints
    assert np.array_equal(a[1], b[1])  # "waves" names no label: the text model's take
    assert not np.allclose(a[0], b[0], atol=1e-4) and not np.allclose(a[2], b[2], atol=1e-4)
    single = pipe(PROMPTS[2], **kw).joints
    assert np.allclose(single[0], b[2], atol=1e-4)  # a batch equals single runs
    pipe.verb_guide.scale = 0.0
    assert np.array_equal(pipe(PROMPTS, **kw).joints, a)  # scale 0: the text model alone
    draft_free = pipe(PROMPTS, guidance_scale=1.0, **kw).joints  # unguided sampling gets no verb term either
    assert np.array_equal(draft_free, plain(PROMPTS, guidance_scale=1.0, **kw).joints)


def test_attaching_refuses_other_latents_a_wrong_kind_and_an_existing_folder(folders, tmp_path):
    text, action, guided = folders
    other = tiny_model(tmp_path / "other", seed=1, cond="action", actions=("jump",))
    proc = _attach(text, other, tmp_path / "x")
    assert proc.returncode == 2 and "VAE weights differ" in proc.stderr and not (tmp_path / "x").exists()
    proc = _attach(action, text, tmp_path / "x")
    assert proc.returncode == 2 and "not a text-conditioned model" in proc.stderr
    no_verbs = tiny_model(tmp_path / "nv", seed=0, cond="action", actions=("walk", "run"))
    proc = _attach(text, no_verbs, tmp_path / "x")
    assert proc.returncode == 2 and "no label that is a checked verb" in proc.stderr
    before = (guided / "config.json").read_text()
    proc = _attach(text, action, guided)
    assert proc.returncode == 2 and "exists" in proc.stderr and (guided / "config.json").read_text() == before
    assert "Traceback" not in proc.stderr
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")
    proc = _attach(text, action, a_file, "--overwrite")
    assert proc.returncode == 2 and "not a folder" in proc.stderr and a_file.read_text() == "mine"
    for out in (text, text / "inside"):
        proc = _attach(text, action, out, "--overwrite")
        assert proc.returncode == 2 and "new folder" in proc.stderr
    assert sorted(p.name for p in text.iterdir()) == sorted(p.name for p in guided.iterdir() if p.name !=
                                                            "verb_denoiser.safetensors")
    for scale in ("nan", "inf", "-1"):
        proc = _attach(text, action, tmp_path / "s", "--scale", scale)
        assert proc.returncode == 2 and "--scale" in proc.stderr and not (tmp_path / "s").exists()


def test_attaching_again_replaces_the_guide_and_its_card_section(folders, tmp_path):
    text, action, guided = folders
    again = tmp_path / "again"
    assert _attach(guided, action, again, "--scale", "5").returncode == 0
    assert load_config(again).verb_guide.scale == 5.0
    card = (again / "MODEL_CARD.md").read_text()
    assert card.count("## Verb guidance") == 1 and "at scale 5" in card


@pytest.mark.parametrize("change, message", [
    ({"scale": -1}, "verb_guide.scale"),
    ({"scale": "2"}, "verb_guide.scale"),
    ({"actions": ["jump"]}, "one label per class"),
    ({"denoiser": {"cond": "action", "num_actions": 3, "latent_dim": 8}}, "is not the VAE's"),
    ("not an object", "verb_guide must be an object"),
])
def test_a_broken_verb_guide_config_is_refused_when_loading(folders, tmp_path, change, message):
    import shutil

    _, _, guided = folders
    folder = tmp_path / "m"
    shutil.copytree(guided, folder)
    data = json.loads((folder / "config.json").read_text())
    data["verb_guide"] = {**data["verb_guide"], **change} if isinstance(change, dict) else change
    (folder / "config.json").write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match=message):
        load_config(folder)


def _interval_script():
    import importlib.util

    spec = importlib.util.spec_from_file_location("verb_guide_interval",
                                                  REPO / "research" / "v4" / "verb_guide_interval.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_guiding_an_interval_of_the_steps_adds_the_term_there_only(folders, monkeypatch):
    """research/v4/verb_guide_interval.py: [0, 1) is every step (the guided take exactly), a half is neither the
    guided take nor the text model's; a prompt naming no verb is untouched; an empty interval is refused."""
    interval = _interval_script()
    assert interval.guided_timesteps([901, 601, 301, 1], 0.0, 0.5) == {901, 601}
    assert interval.guided_timesteps([901, 601, 301, 1], 0.5, 1.0) == {301, 1}
    text, _, guided = folders
    kw = dict(seconds=2.0, seed=5, num_inference_steps=4, repair=False, side_redraws=0)
    plain = MLDPipeline.from_pretrained(text)(PROMPTS, **kw).joints
    full = MLDPipeline.from_pretrained(guided)(PROMPTS, **kw).joints
    monkeypatch.setattr(MLDPipeline, "_verb_guidance", MLDPipeline._verb_guidance)  # restored after the test
    interval.guide_only_on(0.0, 1.0)
    assert np.array_equal(MLDPipeline.from_pretrained(guided)(PROMPTS, **kw).joints, full)
    interval.guide_only_on(0.0, 0.5)
    half = MLDPipeline.from_pretrained(guided)(PROMPTS, **kw).joints
    assert np.array_equal(half[1], plain[1])
    for row in (0, 2):
        assert not np.allclose(half[row], full[row], atol=1e-5) and not np.allclose(half[row], plain[row], atol=1e-5)
    assert interval.main(["--interval", "0.5", "0.5", "--", "--data", "x"]) == 2


def test_a_verb_term_reused_between_steps_is_computed_on_every_nth_guided_step(folders, monkeypatch):
    """research/v4/verb_guide_interval.py --every N: the verb denoiser runs on guided steps 0, N, 2N, ... and its term
    is added unchanged on the steps between; --every 1 is the guided take exactly; a prompt naming no verb is
    untouched; N below 1 is refused."""
    interval = _interval_script()
    text, _, guided = folders
    kw = dict(seconds=2.0, seed=5, num_inference_steps=4, repair=False, side_redraws=0)
    plain = MLDPipeline.from_pretrained(text)(PROMPTS, **kw).joints
    full = MLDPipeline.from_pretrained(guided)(PROMPTS, **kw).joints
    monkeypatch.setattr(MLDPipeline, "_verb_guidance", MLDPipeline._verb_guidance)  # restored after the test
    runs = []
    monkeypatch.setattr(VerbGuidance, "add_to", _counting(VerbGuidance.add_to, runs))
    interval.guide_only_on(0.0, 1.0, every=1)
    assert np.array_equal(MLDPipeline.from_pretrained(guided)(PROMPTS, **kw).joints, full) and len(runs) == 4
    runs.clear()
    interval.guide_only_on(0.0, 1.0, every=2)
    reused = MLDPipeline.from_pretrained(guided)(PROMPTS, **kw).joints
    assert len(runs) == 2  # steps 0 and 2 of 4
    assert np.array_equal(reused[1], plain[1])
    for row in (0, 2):
        assert not np.allclose(reused[row], full[row], atol=1e-5) and not np.allclose(reused[row], plain[row], atol=1e-5)
    assert interval.main(["--every", "0", "--", "--data", "x"]) == 2


def _counting(add_to, runs):
    def counted(self, eps, z, t, lengths):
        runs.append(int(t))
        return add_to(self, eps, z, t, lengths)
    return counted


def test_attaching_into_a_folder_another_run_took_meanwhile_keeps_that_run_s_folder(folders, tmp_path, capsys):
    """Two runs racing for one new --out: the later one says so and leaves the first one's folder as it was."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("attach_verb_guide", ATTACH)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    text, action, _ = folders
    out = tmp_path / "guided"
    plain_attach = script.attach

    def attach_while_another_run_finishes(*args):
        plain_attach(*args)
        out.mkdir()
        (out / "theirs.txt").write_text("the other run's")

    script.attach = attach_while_another_run_finishes
    assert script.main([str(text), str(action), "--out", str(out)]) == 2
    assert "another run" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["theirs.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["guided"]  # no partial folder left beside it
