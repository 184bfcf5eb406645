"""Folding a model's verb guidance into its text denoiser (``train denoiser`` with fold_verb_guide): the targets give
the guided step of the two denoisers, a tiny run learns towards them, and bad settings are refused before any work."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
import torch

from mld_core.checkpoint import load_config, load_weights
from mld_core.cli import main
from mld_core.condition.verb_guide import VerbGuide
from mld_core.models.denoiser import DenoiserConfig, LatentDenoiser
from mld_core.models.transformer import TransformerConfig
from mld_core.pipeline import MLDPipeline
from mld_core.sampling import VerbGuidance, guided_eps, null_and_cond_eps
from mld_core.training.denoiser import DenoiserTrainConfig
from mld_core.training.verb_fold import VerbFold, load_verb_fold
from test_training import TINY_DEN, TINY_VAE, write_verb_folder

REPO = Path(__file__).resolve().parents[1]
BLOCK = TransformerConfig(dim=16, heads=2, ff_dim=32, layers=1, dropout=0.0)


def _denoiser(seed: int, cond: str) -> LatentDenoiser:
    torch.manual_seed(seed)
    den = LatentDenoiser(DenoiserConfig(latent_tokens=2, latent_dim=16, cond=cond, num_actions=3, text_dim=8,
                                        text_pool_tokens=2, transformer=BLOCK)).eval()
    with torch.no_grad():  # an output that moves with its input, whatever the initialisation
        for p in den.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return den


def test_the_targets_guided_at_s_give_the_two_denoisers_guided_step():
    """eps(null) + s (target - eps(null)) on a verb row is the sampler's composed eps; other rows and dropped
    conditions are the model's own eps, untouched."""
    from mld_core.models.text_encoder import TextEmbedding

    teacher, verb = _denoiser(1, "text"), _denoiser(2, "action")
    guide = VerbGuide(verb, ["walk", "kick", "jump"], 2.5)
    fold = VerbFold(teacher, guide, 4.0, torch.tensor([2, -1, 1]))  # captions: a jump, none, a kick
    g = torch.Generator().manual_seed(0)
    z, lengths = torch.randn(3, 2, 16, generator=g), torch.tensor([40, 60, 80])
    t = torch.full((3,), 500)
    drop = torch.tensor([False, False, False])
    text_cond = TextEmbedding(pooled=torch.randn(3, 8, generator=g), tokens=torch.randn(3, 4, 8, generator=g),
                              mask=torch.ones(3, 4, dtype=torch.bool))
    target = fold.targets(z, t, lengths, text_cond, drop, captions=torch.tensor([0, 1, 2]))
    with torch.no_grad():
        cond, null = teacher.condition_tokens(3, text=text_cond), teacher.null_tokens(3)
        eps_null, eps_cond = null_and_cond_eps(teacher, z, 500, cond, null, lengths)
        rows = torch.tensor([0, 2])
        a_cond = verb.condition_tokens(2, actions=torch.tensor([2, 1]))
        sampled = VerbGuidance(verb, rows, a_cond, verb.null_tokens(2), 2.5).add_to(
            guided_eps(teacher, z, 500, cond, null, lengths, 4.0), z, 500, lengths)
    assert torch.allclose(eps_null + 4.0 * (target - eps_null), sampled, atol=1e-5)
    assert torch.allclose(target[1], eps_cond[1], atol=1e-6)  # names no label: the model's own eps
    assert float((target[rows] - eps_cond[rows]).abs().max()) > 1e-3  # the term is not nothing
    dropped = fold.targets(z, t, lengths, text_cond, torch.tensor([True, False, True]), torch.tensor([0, 1, 2]))
    assert torch.allclose(dropped[0], eps_null[0], atol=1e-6) and torch.allclose(dropped[2], eps_null[2], atol=1e-6)


@pytest.fixture(scope="module")
def guided(tmp_path_factory):
    """A tiny text model with a verb denoiser (labels jump, kick, other) attached at scale 8, and its data."""
    root = tmp_path_factory.mktemp("fold")
    data = write_verb_folder(root / "data")
    vae, text, action, model = (root / n for n in ("vae", "text", "action", "guided"))
    over = {k: v for k, v in TINY_DEN.items() if k != "denoiser"}
    base = ["--steps", "3", "--threads", "1"]
    assert main(["train", "vae", "--data", str(data), "--out", str(vae), *base, "--config", json.dumps(TINY_VAE)]) == 0
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(vae), "--out", str(text), *base,
                 "--config", json.dumps(TINY_DEN)]) == 0
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(text), "--out", str(action), "--cond",
                 "action", "--init", str(text), *base, "--config", json.dumps({**over, "lr": 1e-2})]) == 0
    spec = importlib.util.spec_from_file_location("attach_verb_guide", REPO / "scripts" / "attach_verb_guide.py")
    attach = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(attach)
    assert attach.main([str(text), str(action), "--out", str(model), "--scale", "8"]) == 0
    return {"data": data, "guided": model, "text": text, "vae": vae}


def _fold_args(data, model, out, steps, vae=None, **settings):
    over = {k: v for k, v in TINY_DEN.items() if k != "denoiser"}
    return ["train", "denoiser", "--data", str(data), "--vae", str(vae or model), "--init", str(model),
            "--out", str(out), "--steps", str(steps), "--threads", "1", "--config", json.dumps({**over, "fold_verb_guide": True, **settings})]


def _distance_to_targets(model_dir: Path, fold: VerbFold, captions: list[str]) -> float:
    """Mean squared distance of the folder's denoiser's noise from the fold's targets on the verb captions (seeded
    latents and timesteps; conditions kept)."""
    from mld_core.models.text_encoder import load_text_encoder

    config = load_config(model_dir)
    den = LatentDenoiser(config.denoiser)
    load_weights(model_dir / "denoiser.safetensors", den)
    den.eval()
    emb = load_text_encoder(config.text_encoder)(captions)
    g = torch.Generator().manual_seed(3)
    B = len(captions)
    z = torch.randn(B, config.denoiser.latent_tokens, config.denoiser.latent_dim, generator=g)
    t, lengths = torch.randint(0, 1000, (B,), generator=g), torch.full((B,), 30)
    keep = torch.zeros(B, dtype=torch.bool)
    with torch.no_grad():
        target = fold.targets(z, t, lengths, emb, keep, torch.arange(B))
        eps = den(z, t, den.condition_tokens(B, text=emb, drop=keep), lengths)
    return float(((eps - target) ** 2).mean())


def test_a_fold_run_learns_the_guided_noise_and_needs_no_verb_denoiser(guided, tmp_path):
    data, model = guided["data"], guided["guided"]
    out = tmp_path / "folded"
    assert main(_fold_args(data, model, out, 40, lr=3e-3, ema_decay=0.5)) == 0
    config = load_config(out)
    assert config.verb_guide is None and not (out / "verb_denoiser.safetensors").exists()
    assert config.provenance["folded_verb_guide"] == {"scale": 8.0, "actions": ["jump", "kick", "other"],
                                                      "guidance_scale": 4.0}
    assert config.provenance["denoiser_training"]["fold_verb_guide"] is True
    captions = ["a person jumps 0", "a person kicks 1", "a person jumps 3", "a person kicks 4"]
    fold = load_verb_fold(model, load_config(model), model, captions, torch.device("cpu"))
    assert fold.caption_labels.tolist() == [0, 1, 0, 1]
    before, after = _distance_to_targets(model, fold, captions), _distance_to_targets(out, fold, captions)
    assert after < 0.5 * before, (before, after)  # the run moved towards the guided noise
    pipe = MLDPipeline.from_pretrained(out)
    assert pipe.verb_guide is None
    take = pipe("a person jumps", seconds=1.5, seed=0, num_inference_steps=2)
    assert torch.isfinite(torch.as_tensor(take.joints)).all()


def test_fold_settings_are_refused_in_one_line_before_any_work(guided, tmp_path, capsys, monkeypatch):
    from mld_core.training import denoiser

    import shutil

    from safetensors.torch import load_file, save_file

    data, model = guided["data"], guided["guided"]
    for bad in ({"cond": "action"}, {"init": None}, {"init": "x", "renormalise_latents": True}):
        with pytest.raises(ValueError, match="fold_verb_guide goes with --cond text and --init"):
            DenoiserTrainConfig(**{"init": "x", **bad, "fold_verb_guide": True})
    with pytest.raises(ValueError, match="fold_verb_guide must be"):
        DenoiserTrainConfig(init="x", fold_verb_guide="yes")
    encoded = []
    monkeypatch.setattr(denoiser, "encode_latents", lambda *a, **k: encoded.append(1))
    capsys.readouterr()
    out = tmp_path / "no_guide"
    assert main(_fold_args(data, guided["text"], out, 1)) == 2  # the text model before its guide was attached
    err = capsys.readouterr().err
    assert "has no verb denoiser" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert encoded == [] and not out.exists()
    other = tmp_path / "other_vae"
    shutil.copytree(model, other)
    state = load_file(str(other / "vae.safetensors"))
    save_file({k: v + 1e-3 for k, v in state.items()}, str(other / "vae.safetensors"))
    with pytest.raises(ValueError, match="is not .*'s VAE"):
        load_verb_fold(model, load_config(model), other, ["a"], torch.device("cpu"))
    assert main(_fold_args(data, model, tmp_path / "on_other", 1, vae=other)) == 2
    assert "is not" in capsys.readouterr().err and not (tmp_path / "on_other" / "config.json").exists()


def test_the_verb_term_scales_with_each_rows_weight():
    """with_verb_term: weight 0 leaves a row as it is; weight w adds w times the fold's term (the Draft's teacher
    guided at w), on the rows naming a label only."""
    teacher, verb = _denoiser(1, "text"), _denoiser(2, "action")
    fold = VerbFold(teacher, VerbGuide(verb, ["walk", "kick", "jump"], 2.5), 4.0, torch.tensor([2, -1, 1]))
    g = torch.Generator().manual_seed(1)
    z, eps = torch.randn(3, 2, 16, generator=g), torch.randn(3, 2, 16, generator=g)
    t, lengths, caps = torch.full((3,), 300), torch.tensor([40, 60, 80]), torch.tensor([0, 1, 2])
    with torch.no_grad():
        one = fold.with_verb_term(eps, z, t, lengths, caps, torch.ones(3)) - eps
        three = fold.with_verb_term(eps, z, t, lengths, caps, torch.tensor([3.0, 3.0, 0.0])) - eps
    assert float(one[0].abs().max()) > 1e-3 and torch.equal(one[1], torch.zeros_like(one[1]))  # row 1: no label
    assert torch.allclose(three[0], 3 * one[0], atol=1e-5) and torch.equal(three[2], torch.zeros_like(three[2]))


def _draft_args(data, teacher, out, **settings):
    config = {"batch_size": 8, "crops_per_clip": 2, "save_every": 2, **settings}
    return ["train", "draft", "--data", str(data), "--teacher", str(teacher), "--out", str(out), "--steps", "2",
            "--threads", "1", "--lr", "1e-2", "--config", json.dumps(config)]


def test_a_draft_distilled_with_the_verb_fold_learns_another_goal(guided, tmp_path, capsys):
    """train draft's fold_verb_guide: the teacher's steps carry the verb term, so the same seeded run ends elsewhere;
    a teacher without a verb denoiser is refused in one line before any work."""
    from safetensors.torch import load_file

    data, model = guided["data"], guided["guided"]
    assert main(_draft_args(data, model, tmp_path / "plain")) == 0
    assert main(_draft_args(data, model, tmp_path / "folded", fold_verb_guide=True)) == 0
    assert load_config(tmp_path / "folded").provenance["draft_training"]["fold_verb_guide"] is True
    plain, folded = (load_file(str(tmp_path / n / "draft.safetensors")) for n in ("plain", "folded"))
    assert max(float((plain[k] - folded[k]).abs().max()) for k in plain) > 1e-6
    capsys.readouterr()
    assert main(_draft_args(data, guided["text"], tmp_path / "no_guide", fold_verb_guide=True)) == 2
    err = capsys.readouterr().err
    assert "has no verb denoiser" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "no_guide").exists()


def test_the_drafts_teacher_step_carries_the_verb_term_when_its_config_says_so(guided, tmp_path):
    """draft.teacher_verb_guide: a verb prompt's Draft take changes, a prompt naming no label stays the same, and
    rows of a batch still equal single runs."""
    import shutil

    from mld_core.training.draft import install_draft

    run = tmp_path / "draft_run"
    assert main(_draft_args(guided["data"], guided["guided"], run)) == 0
    takes = {}
    for on in (False, True):
        folder = tmp_path / f"model_{on}"
        shutil.copytree(guided["guided"], folder)
        install_draft(run, folder)
        data = json.loads((folder / "config.json").read_text())
        data["draft"].update(teacher_steps=1, teacher_guidance=1.5, teacher_verb_guide=on)
        (folder / "config.json").write_text(json.dumps(data))
        pipe = MLDPipeline.from_pretrained(folder, draft_precision="fp32")
        out = pipe(["a person jumps", "a person walks"], seconds=1.5, seed=[0, 1], draft=True, verb_redraws=0)
        single = pipe("a person jumps", seconds=1.5, seed=0, draft=True, verb_redraws=0)
        assert torch.allclose(torch.as_tensor(out.joints[0]), torch.as_tensor(single.joints[0]), atol=1e-5)
        takes[on] = out.joints
    assert float(abs(takes[True][0] - takes[False][0]).max()) > 1e-4  # the jump: its teacher step guided by "jump"
    assert float(abs(takes[True][1] - takes[False][1]).max()) == 0.0  # the walk names no label of the guide
