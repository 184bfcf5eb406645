"""Both training entries end to end on a tiny folder written by the test: loss falls, runs resume, folders load."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mld_core.cli import main
from mld_core.motion.features import joints_to_features, mean_std
from mld_core.pipeline import MLDPipeline
from mld_core.training.common import Budget, boosted_weights, lr_factor

REPO = Path(__file__).resolve().parents[1]

TINY_VAE = {"vae": {"latent_dim": 32, "max_frames": 64,
                    "encoder": {"dim": 32, "heads": 2, "ff_dim": 64, "layers": 1, "dropout": 0.0},
                    "decoder": {"dim": 32, "heads": 2, "ff_dim": 64, "layers": 1, "dropout": 0.0,
                                "cross_attention": True}},
            "min_frames": 20, "max_frames": 40, "frames_per_batch": 160, "val_every": 10, "val_clips": 2}
TINY_DEN = {"denoiser": {"transformer": {"dim": 32, "heads": 2, "ff_dim": 64, "layers": 1, "dropout": 0.0},
                         "text_pool_tokens": 2},
            "text_encoder": {"kind": "minilm-random", "hidden": 32, "layers": 1, "heads": 2, "vocab_path": "builtin"},
            "batch_size": 16, "crops_per_clip": 2, "save_every": 10}


def _walk(T: int, speed: float, arm: float) -> np.ndarray:
    """A crude stick figure gliding forward with one arm raised by ``arm`` metres (enough to make features)."""
    base = np.load(__import__("pathlib").Path(__file__).parent / "fixtures" / "humanml3d" / "new_joints_012314.npy")[0]
    joints = np.repeat(base[None], T, axis=0).copy()
    joints[:, :, 2] += speed * np.arange(T)[:, None] / 20.0
    joints[:, 21, 1] += arm * np.sin(np.linspace(0, 3, T))
    return joints


def _write_folder(root, captions=lambda k: f"a person walks {k}#a/DET#0.0#0.0\nsomeone strolls#x#0.0#0.0\n"):
    """Eight tiny clips with ``captions(k)`` as clip k's texts file; six train, two val, labels "a" and "b"."""
    for sub in ("new_joint_vecs", "texts"):
        (root / sub).mkdir(parents=True)
    ids, feats = [], []
    for k in range(8):
        cid = f"clip{k}"
        f = joints_to_features(_walk(50 + 5 * k, speed=0.5 + 0.2 * (k % 2), arm=0.3 * (k % 3)))
        np.save(root / "new_joint_vecs" / f"{cid}.npy", f)
        (root / "texts" / f"{cid}.txt").write_text(captions(k))
        ids.append(cid)
        feats.append(f)
    mean, std = mean_std(feats)
    np.save(root / "Mean.npy", mean)
    np.save(root / "Std.npy", std)
    (root / "train.txt").write_text("\n".join(ids[:6]))
    (root / "val.txt").write_text("\n".join(ids[6:]))
    (root / "actions.json").write_text(json.dumps({"classes": ["a", "b"], "clips": {c: "ab"[i % 2] for i, c in enumerate(ids)}}))
    return root


def write_verb_folder(root):
    """The tiny folder with clips that jump, kick and walk in turn, labelled jump, kick and other."""
    data = _write_folder(root, lambda k: f"a person {('jumps', 'kicks', 'walks')[k % 3]} {k}#a/DET#0.0#0.0\n")
    labels = json.loads((data / "actions.json").read_text())
    labels["classes"] = ["jump", "kick", "other"]
    labels["clips"] = {c: labels["classes"][int(c[4:]) % 3] for c in labels["clips"]}
    (data / "actions.json").write_text(json.dumps(labels))
    return data


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return _write_folder(tmp_path_factory.mktemp("data"))


def test_lr_schedule_and_budget():
    assert lr_factor(0.2, 0.5) == 1.0
    assert lr_factor(1.0, 0.5) == pytest.approx(0.1)
    assert 0.1 < lr_factor(0.75, 0.5) < 1.0
    assert Budget(10, None).progress(5) == 0.5 and Budget(10, None).done(10)


def test_warmup_ramps_the_rate_over_the_first_steps_of_a_run(folder, tmp_path, capsys):
    """warmup_steps ramps a VAE's and a denoiser's rate up linearly (each log line records the rate it trained at);
    a bad value is refused in one line before anything is written."""
    from mld_core.training.common import warmup_factor
    assert [warmup_factor(s, 4) for s in range(6)] == [0.25, 0.5, 0.75, 1.0, 1.0, 1.0]
    assert warmup_factor(0, 0) == 1.0
    vae_run = tmp_path / "vae"
    vae_cfg = {**TINY_VAE, "val_every": 2, "decay_start": 1.0, "warmup_steps": 4}
    assert main(["train", "vae", "--data", str(folder), "--out", str(vae_run), "--steps", "6", "--threads", "1",
                 "--config", json.dumps(vae_cfg), "--lr", "2e-3"]) == 0
    rates = [json.loads(line)["lr"] for line in (vae_run / "log.jsonl").read_text().splitlines()]
    assert rates == pytest.approx([1e-3, 2e-3, 2e-3])  # the rates of steps 2, 4 and 6 (ramp factors 2/4, 4/4, 1)
    den_run = tmp_path / "den"
    den_args = ["train", "denoiser", "--data", str(folder), "--vae", str(vae_run), "--threads", "1", "--lr", "1e-3"]
    den_cfg = {**TINY_DEN, "save_every": 1, "decay_start": 1.0, "warmup_steps": 3}
    assert main(den_args + ["--out", str(den_run), "--steps", "4", "--config", json.dumps(den_cfg)]) == 0
    rates = [json.loads(line)["lr"] for line in (den_run / "log.jsonl").read_text().splitlines()]
    assert rates == pytest.approx([1e-3 / 3, 2e-3 / 3, 1e-3, 1e-3])
    capsys.readouterr()
    bad = tmp_path / "bad"
    assert main(den_args + ["--out", str(bad), "--steps", "1", "--config", json.dumps({**den_cfg, "warmup_steps": -1})]) == 2
    assert "warmup_steps must be between 0 and" in capsys.readouterr().err and not bad.exists()


def test_train_vae_then_denoiser_then_generate(folder, tmp_path):
    cfg_vae = tmp_path / "vae.json"
    cfg_vae.write_text(json.dumps(TINY_VAE))
    vae_run = tmp_path / "vae"
    assert main(["train", "vae", "--data", str(folder), "--out", str(vae_run), "--steps", "20", "--threads", "1",
                 "--config", str(cfg_vae), "--lr", "3e-3"]) == 0
    log = [json.loads(line) for line in (vae_run / "log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == 20 and "val_mpjpe_mm" in log[-1]
    # refuses to overwrite a run without --resume; --resume continues counting
    assert main(["train", "vae", "--data", str(folder), "--out", str(vae_run), "--steps", "30", "--config", str(cfg_vae)]) == 2
    assert main(["train", "vae", "--data", str(folder), "--out", str(vae_run), "--steps", "30", "--config", str(cfg_vae),
                 "--resume", "--threads", "1"]) == 0
    log = [json.loads(line) for line in (vae_run / "log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == 30

    den_run = tmp_path / "mld"  # --config inline: the JSON object itself, not a file
    den_args = ["train", "denoiser", "--data", str(folder), "--vae", str(vae_run), "--out", str(den_run)]
    for bad in ('{"lr": 1e-3,', '{"lr": NaN}', '{"lr": 1e999}', '[1, 2]', str(tmp_path)):  # broken, nan, inf, a list,
        assert main(den_args + ["--config", bad, "--steps", "1"]) == 2 and not den_run.exists()  # a folder
    assert main(den_args + ["--steps", "40", "--threads", "1", "--config", json.dumps(TINY_DEN), "--lr", "1e-3",
                            "--bf16"]) == 0
    assert json.loads((den_run / "train_config.json").read_text())["bf16"] is True
    losses = [json.loads(line)["loss"] for line in (den_run / "log.jsonl").read_text().splitlines()]
    assert len(losses) == 4 and losses[-1] < losses[0]
    pipe = MLDPipeline.from_pretrained(den_run)
    out = pipe(["a person walks"], seconds=1.5, num_inference_steps=3)
    assert out.joints.shape == (1, 30, 22, 3) and np.isfinite(out.joints).all()
    # the run ships its prompt-coverage index: the training captions (normalised) and contents
    index = pipe.coverage_index
    assert index is not None and sorted(index.known_contents) == ["a", "b"]
    assert "someone strolls" in index.captions and len(index) == 7  # "a person walks 0".."5" + "someone strolls"
    assert pipe.coverage("someone strolls")[0].score == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize("bf16", [False, True])
def test_vae_loss_falls_on_the_tiny_folder(folder, tmp_path, bf16):
    cfg = tmp_path / "vae.json"
    cfg.write_text(json.dumps({**TINY_VAE, "val_every": 30}))
    run = tmp_path / "vae"
    assert main(["train", "vae", "--data", str(folder), "--out", str(run), "--steps", "60", "--threads", "1",
                 "--config", str(cfg), "--lr", "3e-3"] + (["--bf16"] if bf16 else [])) == 0
    first = json.loads((run / "log.jsonl").read_text().splitlines()[0])
    last = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    assert last["val_mpjpe_mm"] < first["val_mpjpe_mm"] or last["mse"] < first["mse"]


def test_bad_data_folder_exits_2(tmp_path, capsys):
    assert main(["train", "vae", "--data", str(tmp_path), "--out", str(tmp_path / "run")]) == 2
    assert "not a HumanML3D-format folder" in capsys.readouterr().err


def test_vae_fine_tunes_from_a_model_folder(tmp_path, capsys):
    """--init: the model folder's architecture and weights are where training starts (one step moves them little)."""
    from safetensors.torch import load_file

    from mld_core.cli import main
    from mld_core.testing import tiny_model
    from test_reliability import _h3d_folder

    model = tiny_model(tmp_path / "tiny")
    config = json.loads((model / "config.json").read_text())
    config["stepping"]["steps"], config["repair"]["plant_feet"] = 7, False  # the folder's own decoding settings
    (model / "config.json").write_text(json.dumps(config))
    data = _h3d_folder(tmp_path / "data")
    run = tmp_path / "run"
    assert main(["train", "vae", "--data", str(data), "--out", str(run), "--steps", "1", "--init", str(model),
                 "--lr", "1e-5"]) == 0
    start, tuned = load_file(str(model / "vae.safetensors")), load_file(str(run / "vae.safetensors"))
    assert set(start) == set(tuned)  # the tiny architecture, not the default one
    drift = max(float((start[k].float() - tuned[k].float()).abs().max()) for k in start)
    assert drift < 1e-3, drift
    tuned_config = json.loads((run / "config.json").read_text())  # a fine-tune keeps stepping and the repairs
    assert (tuned_config["stepping"]["steps"], tuned_config["repair"]["plant_feet"]) == (7, False)
    from mld_core.checkpoint import load_config
    from mld_core.training.vae import VAETrainConfig, train_vae

    (run / "config.json").unlink()  # a resumed fine-tune whose first sitting wrote no config yet
    train_vae(VAETrainConfig(data=str(data), out=str(run), steps=3, lr=1e-5, vae=load_config(model).vae,
                             init=str(model)), True)
    assert (load_config(run).stepping.steps, load_config(run).repair.plant_feet) == (7, False)
    capsys.readouterr()
    assert main(["train", "vae", "--data", str(data), "--out", str(tmp_path / "run2"), "--init",
                 str(tmp_path / "nowhere")]) == 2
    assert "is not a model folder" in capsys.readouterr().err and not (tmp_path / "run2").exists()


def test_geometric_terms_are_switches_that_train(folder, tmp_path):
    import torch

    from mld_core.training.vae import GeometricLoss, VAETrainConfig

    mean, std = np.load(folder / "Mean.npy").astype(np.float32), np.load(folder / "Std.npy").astype(np.float32)
    assert not GeometricLoss(VAETrainConfig(), mean, std)  # off by default
    x = torch.from_numpy(((joints_to_features(_walk(40, 0.8, 0.3)) - mean) / std)[None].astype(np.float32))
    loss, parts = GeometricLoss(VAETrainConfig(bone_weight=1.0), mean, std)(x, x)
    assert float(loss) == 0.0 and parts["geo_joints"] == 0.0  # a perfect reconstruction costs nothing
    worse = x.clone()
    worse[..., 4:67] *= 1.05  # every root-relative joint 5% farther out: bones stretch
    loss, parts = GeometricLoss(VAETrainConfig(bone_weight=1.0), mean, std)(worse, x)
    assert float(loss) > 0 and float(loss) == pytest.approx(parts["geo_bones"])
    cfg = tmp_path / "vae.json"
    cfg.write_text(json.dumps({**TINY_VAE, "val_every": 10, "contact_weight": 1.0, "bone_weight": 1.0}))
    run = tmp_path / "geo"
    assert main(["train", "vae", "--data", str(folder), "--out", str(run), "--steps", "10", "--threads", "1",
                 "--config", str(cfg)]) == 0
    record = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    assert {"geo_contact", "geo_bones", "val_global_mpjpe_mm"} <= set(record)


def test_contact_term_charges_a_planted_foot_for_sliding_not_for_lifting(folder):
    import torch

    from mld_core.motion import skeleton as sk
    from mld_core.motion.features import FOOT_CONTACT, RIC
    from mld_core.training.vae import GeometricLoss, VAETrainConfig

    mean, std = np.load(folder / "Mean.npy").astype(np.float32), np.load(folder / "Std.npy").astype(np.float32)
    feats = joints_to_features(_walk(40, 0.0, 0.0))  # standing still: both feet planted
    assert (feats[:, FOOT_CONTACT] > 0.5).all()
    term = GeometricLoss(VAETrainConfig(contact_weight=1.0), mean, std)
    x = torch.from_numpy(((feats - mean) / std)[None].astype(np.float32))  # (1, T, F)
    wobble = 0.05 * np.sin(np.linspace(0, 6, len(feats)))  # metres, per frame
    def moved(axis: int) -> torch.Tensor:
        f = feats.copy()
        for j in sk.FOOT_LEFT + sk.FOOT_RIGHT:
            f[:, RIC.start + 3 * (j - 1) + axis] += wobble  # the feet move relative to a still root
        return torch.from_numpy(((f - mean) / std)[None].astype(np.float32))
    assert term(x, x)[1]["geo_contact"] == pytest.approx(0.0, abs=1e-10)
    assert term(moved(1), x)[1]["geo_contact"] == pytest.approx(0.0, abs=1e-10)  # lifted in place: no slide
    slide = term(moved(0), x)[1]["geo_contact"]  # swayed sideways: slides
    assert slide == pytest.approx((np.diff(wobble) ** 2).mean(), rel=0.01)  # the sway's squared speed per frame


def _add_content_anchor(model_dir) -> None:
    """Fit a content anchor on a few captions with the model's own text encoder and switch it on (weight 1)."""
    from mld_core.condition import content_anchor
    from mld_core.checkpoint import load_config, save_json
    from mld_core.models.text_encoder import load_text_encoder

    config = load_config(model_dir)
    texts = ["a person walks forward", "someone walks ahead", "a person bows", "someone bows deeply"]
    anchor = content_anchor.fit(texts, ["walk", "walk", "bow", "bow"], load_text_encoder(config.text_encoder), steps=5)
    anchor.save(model_dir / content_anchor.FILE_NAME)
    config.content_anchor = content_anchor.ContentAnchorConfig(weight=1.0)
    save_json(model_dir / "config.json", config.to_dict())


def test_draft_distillation_trains_resumes_and_installs(folder, tmp_path):
    import shutil

    from mld_core.checkpoint import load_config

    cfg_vae, cfg_den = tmp_path / "vae.json", tmp_path / "den.json"
    cfg_vae.write_text(json.dumps(TINY_VAE))
    cfg_den.write_text(json.dumps(TINY_DEN))
    assert main(["train", "vae", "--data", str(folder), "--out", str(tmp_path / "vae"), "--steps", "10",
                 "--threads", "1", "--config", str(cfg_vae)]) == 0
    teacher = tmp_path / "teacher"
    assert main(["train", "denoiser", "--data", str(folder), "--vae", str(tmp_path / "vae"), "--out", str(teacher),
                 "--steps", "20", "--threads", "1", "--config", str(cfg_den), "--lr", "1e-3"]) == 0
    _add_content_anchor(teacher)  # a teacher with a content anchor: its Draft run folder must load with it
    cfg_draft = tmp_path / "draft.json"
    cfg_draft.write_text(json.dumps({"batch_size": 16, "save_every": 10, "crops_per_clip": 2}))
    run = tmp_path / "draft"
    args = ["train", "draft", "--data", str(folder), "--teacher", str(teacher), "--out", str(run), "--threads", "1",
            "--config", str(cfg_draft), "--lr", "1e-3"]
    assert main(args + ["--steps", "40"]) == 0
    losses = [json.loads(line)["loss"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert len(losses) == 4 and losses[-1] < losses[0]
    assert main(args + ["--steps", "50", "--resume"]) == 0
    assert json.loads((run / "log.jsonl").read_text().splitlines()[-1])["step"] == 50
    # the run folder is a model folder with a Draft; installing copies it (fp16) into the teacher's folder
    run_pipe = MLDPipeline.from_pretrained(run)
    assert run_pipe.content_anchor is not None and run_pipe.config.content_anchor.weight == 1.0
    assert run_pipe.config.draft.denoiser.guidance_input and run_pipe.config.provenance["draft_steps"] == 50
    d = run_pipe.config.draft  # the sampler the shipped Draft uses (docs/draft.md), not LCM's defaults
    assert (d.num_inference_steps, d.teacher_steps, d.fresh_noise, d.teacher_guidance) == (2, 1, 0.0, 1.5)
    assert d.timesteps == [981, 601] and run_pipe("a person walks", 1.5, draft=True).joints.shape[1] == 30
    from mld_core.training.draft import DraftTrainConfig

    from mld_core.schedulers import LCMScheduler
    from mld_core.training.draft import draft_timesteps

    grid = LCMScheduler(run_pipe.config.scheduler, 50)  # by default only a 2-step Draft with a teacher step has its own
    assert draft_timesteps(DraftTrainConfig(), grid) == [981, 601]
    assert draft_timesteps(DraftTrainConfig(draft_steps=3), grid) is None
    assert draft_timesteps(DraftTrainConfig(teacher_steps=0), grid) is None
    assert draft_timesteps(DraftTrainConfig(original_steps=2), LCMScheduler(run_pipe.config.scheduler, 2)) == [501, 1]
    checked = DraftTrainConfig(teacher_steps="1", draft_steps="2", fresh_noise="0.5", batch_size="16")
    assert (checked.teacher_steps, checked.draft_steps, checked.fresh_noise, checked.batch_size) == (1, 2, 0.5, 16)
    # a new denoiser on the anchored model's VAE: the anchor, built for the old denoiser, is not carried over
    assert main(["train", "denoiser", "--data", str(folder), "--vae", str(teacher), "--out", str(tmp_path / "den2"),
                 "--steps", "2", "--threads", "1", "--config", str(cfg_den)]) == 0
    assert load_config(tmp_path / "den2").content_anchor.weight == 0
    assert MLDPipeline.from_pretrained(tmp_path / "den2").content_anchor is None
    installed = tmp_path / "installed"
    shutil.copytree(teacher, installed)
    assert main(args[:6] + ["--teacher", str(installed), "--out", str(tmp_path / "draft2"), "--threads", "1",
                            "--config", str(cfg_draft), "--steps", "10", "--install"]) == 0
    assert (installed / "draft.safetensors").is_file() and load_config(installed).draft is not None
    from mld_core.training.draft import install_draft

    install_draft(run, installed)  # the 50-step run into the same folder
    a = run_pipe(["a person walks"], seconds=1.5, seed=3, draft=True)
    b = MLDPipeline.from_pretrained(installed)(["a person walks"], seconds=1.5, seed=3, draft=True)
    assert np.allclose(a.joints, b.joints, atol=2e-2)  # fp16 weights
    assert main(["train", "draft", "--data", str(folder), "--teacher", str(tmp_path / "vae"), "--out",
                 str(tmp_path / "bad"), "--steps", "1"]) == 2  # a VAE-only folder has nothing to distil
    assert not (tmp_path / "bad").exists()
    # re-distilling after the teacher changed: the student starts from a model folder's Draft
    from safetensors.torch import load_file

    cfg_init = tmp_path / "init.json"
    cfg_init.write_text(json.dumps({"batch_size": 16, "save_every": 1, "crops_per_clip": 2, "init": str(run)}))
    assert main(["train", "draft", "--data", str(folder), "--teacher", str(teacher), "--out", str(tmp_path / "re"),
                 "--threads", "1", "--config", str(cfg_init), "--lr", "1e-12", "--steps", "1"]) == 0
    start, again = load_file(str(run / "draft.safetensors")), load_file(str(tmp_path / "re" / "draft.safetensors"))
    assert max(float((start[k] - again[k]).abs().max()) for k in start) < 1e-6
    cfg_init.write_text(json.dumps({"init": str(teacher)}))
    assert main(["train", "draft", "--data", str(folder), "--teacher", str(teacher), "--out", str(tmp_path / "re2"),
                 "--config", str(cfg_init), "--steps", "1"]) == 2  # the teacher's folder has no Draft
    assert not (tmp_path / "re2").exists()


@pytest.mark.parametrize("flags, config, words", [
    (["--minutes", "0"], {}, "minutes must be above 0"),
    (["--steps", "-5"], {}, "steps must be between"),
    (["--lr", "-1"], {}, "lr must be between"),
    ([], {"guidance_min": 6.0, "guidance_max": 4.0}, "guidance_min must be above 0 and at most guidance_max"),
    ([], {"guidance_min": "high"}, "guidance_min must be a number"),
    ([], {"save_every": 0}, "save_every must be between"),
    ([], {"draft_steps": 60}, "draft_steps must be between 1 and 50"),
    ([], {"teacher_steps": 50}, "teacher_steps must be between 0 and 49"),
    ([], {"fresh_noise": 2.0}, "fresh_noise must be between 0"),
    ([], {"timesteps": [981, 600]}, "timesteps must be 2 descending points of its grid"),
    ([], {"timesteps": [981, 601], "draft_steps": 3}, "timesteps must be 3 descending points of its grid"),
], ids=["minutes", "steps", "lr", "guidance", "guidance-text", "save-every", "draft-steps", "teacher-steps",
        "fresh-noise", "timesteps-off-grid", "timesteps-count"])
def test_train_draft_refuses_bad_settings_before_any_work(folder, tmp_path, capsys, flags, config, words):
    cfg = tmp_path / "draft.json"
    cfg.write_text(json.dumps(config))
    code = main(["train", "draft", "--data", str(folder), "--out", str(tmp_path / "run"), "--config", str(cfg),
                 *flags])
    err = capsys.readouterr().err
    assert code == 2 and words in err and "Traceback" not in err, err
    assert not (tmp_path / "run").exists()


def test_draft_text_distillation_trains_resumes_installs_and_only_the_draft_uses_it(folder, tmp_path):
    import shutil

    from mld_core.checkpoint import load_config
    from mld_core.testing import tiny_model

    model = tiny_model(tmp_path / "model", draft=True)  # its text encoder has 2 layers
    before = MLDPipeline.from_pretrained(model)
    cfg = tmp_path / "text.json"
    cfg.write_text(json.dumps({"batch_size": 8, "save_every": 10, "init_layers": [1], "val_texts": 4}))
    run = tmp_path / "text"
    args = ["train", "draft-text", "--data", str(folder), "--teacher", str(model), "--out", str(run), "--threads", "1",
            "--config", str(cfg), "--lr", "3e-3"]
    assert main(args + ["--steps", "30"]) == 0
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert log[0]["step"] == 0 and log[-1]["step"] == 30 and {"val_cond0", "val_cond1"} <= set(log[-1])
    assert log[-1]["val_mse"] < log[0]["val_mse"] and log[-1]["val_cos"] > log[0]["val_cos"]
    assert main(args + ["--steps", "40", "--resume"]) == 0
    assert json.loads((run / "log.jsonl").read_text().splitlines()[-1])["step"] == 40
    assert main(args + ["--steps", "40", "--install"]) == 2  # the run exists: no overwrite without --resume
    installed = tmp_path / "installed"
    shutil.copytree(model, installed)
    assert main(args[:5] + [str(installed), "--out", str(tmp_path / "text2"), "--threads", "1", "--config", str(cfg),
                            "--steps", "10", "--install"]) == 0
    assert load_config(installed).draft.text_layers == 1 and (installed / "draft_text.safetensors").is_file()
    pipe = MLDPipeline.from_pretrained(installed)
    assert pipe.draft_text_layers == 1 and len(pipe.text_encoder.layers) == 2
    fp32 = MLDPipeline.from_pretrained(installed, draft_precision="fp32")  # the fp16 file runs in float32 there
    assert fp32.draft_text_layers == 1 and fp32.draft_text_encoder.dtype == torch.float32
    assert np.isfinite(fp32("a person walks", 1.5, seed=3, draft=True).joints).all()
    final = pipe("a person walks", 1.5, seed=3)
    assert np.array_equal(final.joints, before("a person walks", 1.5, seed=3).joints)  # Final never changes
    draft = pipe("a person walks", 1.5, seed=3, draft=True)
    assert np.isfinite(draft.joints).all()
    assert not np.array_equal(draft.joints, before("a person walks", 1.5, seed=3, draft=True).joints)
    # installing a Draft denoiser again keeps the text encoder's layers
    from mld_core.training.draft import install_draft

    shutil.copytree(model, tmp_path / "draft_run")
    install_draft(tmp_path / "draft_run", installed)
    assert load_config(installed).draft.text_layers == 1
    (installed / "draft_text.safetensors").write_bytes(b"broken")  # a broken file costs the Draft only its speed
    with pytest.warns(UserWarning, match="full text encoder"):
        fallback = MLDPipeline.from_pretrained(installed)
    assert len(fallback.draft_text_encoder.layers) == 2
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"init_layers": [5]}))
    assert main(args[:7] + [str(tmp_path / "bad"), "--config", str(bad), "--steps", "1"]) == 2
    assert not (tmp_path / "bad").exists()
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"batch_size": 8, "init_layers": [0]}))
    assert main(args[:8] + ["--config", str(other), "--steps", "50", "--resume"]) == 2  # another student: refused
    assert json.loads((run / "log.jsonl").read_text().splitlines()[-1])["step"] == 40
    from mld_core.training.draft_text import install_draft_text

    (run / "draft_text.safetensors").write_bytes(b"not a safetensors file")
    before = (installed / "config.json").read_text()
    with pytest.raises(ValueError, match="cannot install"):
        install_draft_text(run, installed)
    assert (installed / "config.json").read_text() == before  # nothing written


def test_text_variants_keep_splice_drop_or_swap_sides():
    from mld_core.training.draft_text import DraftTextTrainConfig, text_variant

    captions = ["a person turns left and walks forward.", "someone waves the right hand"]
    rng = np.random.default_rng(0)
    only = dict(splice_share=0.0, drop_share=0.0, swap_share=0.0, reword_share=0.0, composed_share=0.0,
                random_share=0.0)
    assert {text_variant(captions, rng, DraftTextTrainConfig(**only)) for _ in range(20)} == set(captions)
    swapped = {text_variant(captions, rng, DraftTextTrainConfig(**{**only, "swap_share": 1.0})) for _ in range(20)}
    assert swapped == {"a person turns right and walks backward.", "someone waves the left hand"}
    dropped = [text_variant(captions, rng, DraftTextTrainConfig(**{**only, "drop_share": 1.0})) for _ in range(20)]
    assert all(set(d.split()) <= set(" ".join(captions).split()) for d in dropped) and set(dropped) - set(captions)
    spliced = [text_variant(captions, rng, DraftTextTrainConfig(**{**only, "splice_share": 1.0})) for _ in range(40)]
    assert any(s.startswith("a person") and s.endswith("hand") for s in spliced)
    reworded = {text_variant(captions, rng, DraftTextTrainConfig(**{**only, "reword_share": 1.0})) for _ in range(40)}
    assert len(reworded) > 5 and all(r.split()[-1] in ("forward.", "hand", "ahead.", "arm", "front.") for r in reworded)
    composed = {text_variant(captions, rng, DraftTextTrainConfig(**{**only, "composed_share": 1.0})) for _ in range(20)}
    assert len(composed) > 15 and not composed & set(captions)
    vocabulary = ["alpha", "beta", "gamma"]
    random = [text_variant(captions, rng, DraftTextTrainConfig(**{**only, "random_share": 1.0}), vocabulary)
              for _ in range(20)]
    assert all(2 <= len(r.split()) <= 12 and set(r.split()) <= set(vocabulary) for r in random)
    with pytest.raises(ValueError, match="must be at most 1"):
        DraftTextTrainConfig(splice_share=0.5, drop_share=0.3, swap_share=0.3)
    with pytest.raises(ValueError, match="composed_share \\+ random_share must be at most 1"):
        DraftTextTrainConfig(composed_share=0.8, random_share=0.3)


def test_root_weight_scales_only_the_root_channels_and_trains(folder, tmp_path, capsys):
    from mld_core.models.vae import MotionVAE, VAEConfig
    from mld_core.training.vae import VAETrainConfig, feature_weights, selection_metric

    assert feature_weights(263, 1.0) is None  # the default loss is the plain mean
    weights = feature_weights(263, 30.0)
    assert weights[:4].tolist() == [30.0] * 4 and weights[4:].eq(1.0).all()
    with pytest.raises(ValueError, match="263-d"):
        feature_weights(12, 30.0)
    torch.manual_seed(0)
    vae = MotionVAE(VAEConfig(**TINY_VAE["vae"])).eval()
    x, lengths = torch.randn(2, 30, 263), torch.tensor([30, 24])
    with torch.no_grad():
        torch.manual_seed(1)
        plain, _, recon = vae.loss(x, lengths, return_recon=True)
        torch.manual_seed(1)
        weighted, _ = vae.loss(x, lengths, feature_weights=weights)
    err = ((recon - x) ** 2)[~(torch.arange(30)[None] >= lengths[:, None])]  # (valid frames, F)
    assert float(weighted - plain) == pytest.approx(float(29.0 * err[:, :4].sum(-1).mean() / 263), rel=1e-4)
    # the best checkpoint: root-relative by default, or root-relative + global
    record = {"val_mpjpe_mm": 30.0, "val_global_mpjpe_mm": 150.0}
    assert selection_metric(record, "mpjpe", 5) == 30.0 and selection_metric(record, "mpjpe_sum", 5) == 180.0
    assert selection_metric({}, "mpjpe_sum", 5) == -5
    with pytest.raises(ValueError, match="select_by"):
        VAETrainConfig(select_by="fid")
    cfg = tmp_path / "vae.json"
    cfg.write_text(json.dumps({**TINY_VAE, "root_weight": 20.0, "select_by": "mpjpe_sum"}))
    run = tmp_path / "root"
    assert main(["train", "vae", "--data", str(folder), "--out", str(run), "--steps", "10", "--threads", "1",
                 "--config", str(cfg)]) == 0
    saved = json.loads((run / "config.json").read_text())["provenance"]
    assert saved["vae_training"]["root_weight"] == 20.0 and saved["vae_val_global_mpjpe_mm"] > 0
    cfg.write_text(json.dumps({**TINY_VAE, "root_weight": 0}))
    capsys.readouterr()
    assert main(["train", "vae", "--data", str(folder), "--out", str(tmp_path / "bad"), "--steps", "1",
                 "--config", str(cfg)]) == 2
    assert "root_weight must be between" in capsys.readouterr().err
    from mld_core.training.denoiser import DenoiserTrainConfig

    for make, value, words in ((lambda v: VAETrainConfig(root_weight=v), float("nan"), "root_weight must be a"),
                               (lambda v: VAETrainConfig(clip_start_share=v), 1.5, "clip_start_share must be between"),
                               (lambda v: DenoiserTrainConfig(reworded_captions=v), -1, "reworded_captions must be"),
                               (lambda v: DenoiserTrainConfig(reworded_turns=v), "false", "reworded_turns must be true"),
                               (lambda v: DenoiserTrainConfig(reworded_turns=v), 1, "reworded_turns must be true"),
                               (lambda v: DenoiserTrainConfig(reworded_sides=v), "yes", "reworded_sides must be true")):
        with pytest.raises(ValueError, match=words):
            make(value)


def test_reworded_captions_add_versions_in_other_words_and_keep_the_originals():
    from mld_core.training.denoiser import Unit, with_reworded_captions

    units = [Unit(features=np.zeros((40, 263), np.float32), label="walk-turn-left",
                  captions=["a person walks forward and turns left.", "someone runs."])]
    assert with_reworded_captions(units, 0, seed=0) == [units[0].captions]  # off: the captions as they are
    texts = with_reworded_captions(units, 3, seed=0)[0]
    assert texts[:2] == units[0].captions and 2 < len(texts) <= 8 and len(set(texts)) == len(texts)
    # other subjects and verbs, never another side
    assert all("left" in t or t.split()[-1] in ("runs.", "jogs.", "sprints.", "dashes.") for t in texts), texts
    assert any(not t.startswith(("a person", "someone")) or "walks" not in t and "runs" not in t for t in texts)
    assert texts == with_reworded_captions(units, 3, seed=0)[0]  # seeded


def test_rewording_never_names_a_style_the_caption_lacks():
    """In the captions a subject such as "an old man" or "a tired person" names the clip's style: a rewording that
    put one in place of "a person" would teach that style on clips without it."""
    from mld_core.data.captions import STYLES, captions_for, reworded

    style_words = {w for style in STYLES.values() for subject in style["subject"] for w in subject.split()
                   if w not in ("a", "an", "person", "someone", "man", "woman", "who", "is", "the")}
    rng = np.random.default_rng(0)
    introduced = set()
    for content in ("walk", "walk-back", "wave-both-hands"):
        for caption in captions_for(content, "normal", f"x_{content}_normal_000", n=6):
            for _ in range(40):
                before, after = set(caption.lower().split()), set(reworded(caption, rng).lower().split())
                introduced |= (after - before) & style_words
    assert introduced == set(), introduced


def test_rewording_brings_in_no_wording_of_the_held_out_paraphrases():
    """side_accuracy.py's paraphrases measure wordings the captions lack; a synonym that writes one of them
    into training would turn that measure into recall (function words such as pronouns aside)."""
    import re
    import sys
    from pathlib import Path

    from mld_core.data.captions import CONTENTS, STYLES, SYNONYMS, TURN_VERBS, captions_for

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "research"))
    from side_accuracy import PARAPHRASES

    held_out = " | ".join(p.lower() for texts in PARAPHRASES.values() for p in texts)
    captions = " | ".join(c.lower() for content in CONTENTS for style in STYLES for i in range(8)
                          for c in captions_for(content, style, f"x_{content}_{style}_{i:03d}"))
    options = [option for word, options in SYNONYMS.items() if word not in ("his", "their") for option in options]
    leaked = [option for option in options + list(TURN_VERBS)
              if re.search(rf"\b{re.escape(option)}\b", held_out) and not re.search(rf"\b{re.escape(option)}\b", captions)]
    assert leaked == []
    assert not {"veers", "swerves", "changes", "direction"} & {w for verb in TURN_VERBS for w in verb.split()}


def test_turn_rewording_says_turning_to_a_side_in_other_verbs_and_keeps_the_side():
    from mld_core.data.captions import TURN_VERBS, reworded
    from mld_core.training.denoiser import Unit, with_reworded_captions

    rng = np.random.default_rng(0)
    caption = "a person walks forward and turns to the left."
    with_turns = [reworded(caption, rng, turns=True) for _ in range(200)]
    assert all(t.endswith("to the left.") for t in with_turns)
    assert {verb for verb in TURN_VERBS if any(f" {verb} to the left" in t for t in with_turns)} == set(TURN_VERBS)
    plain = [reworded(caption, rng) for _ in range(200)]
    assert not any(f" {verb} to the left" in t for t in plain for verb in TURN_VERBS)
    # "turns" that is not a turn to a side stays a turn
    for other in ("a person performs a dance with lots of turns.", "someone turns around."):
        assert not any(verb in reworded(other, rng, turns=True) for _ in range(50) for verb in TURN_VERBS)
    units = [Unit(features=np.zeros((40, 263), np.float32), label="walk-turn-right",
                  captions=["someone walks and turns right."])]
    texts = with_reworded_captions(units, 8, seed=0, turns=True)[0]
    assert any(f" {verb} right." in t for t in texts for verb in TURN_VERBS), texts
    assert with_reworded_captions(units, 8, seed=0)[0] != texts  # the switch changes what trains


def test_side_rewording_names_the_side_from_the_body_and_never_in_the_held_out_words():
    from mld_core.data.captions import reworded
    from mld_core.training.denoiser import Unit, with_reworded_captions

    rng = np.random.default_rng(0)
    owners = {"a woman": {"the", "her"}, "she": {"the", "her"}, "the lady": {"the", "her"}, "a man": {"the", "his"},
              "he": {"the", "his"}, "a guy": {"the", "his"}}
    for caption in ("a woman walks forward and turns to the left.", "the man walks ahead while drifting to the right."):
        side = caption.split()[-1]
        texts = [reworded(caption, rng, sides=True) for _ in range(400)]
        assert {t.split()[-2] for t in texts} == {"the", "his", "her"} and all(t.endswith(side) for t in texts)
        for subject, allowed in owners.items():  # the owner agrees with the (reworded) subject
            said = {t.split()[-2] for t in texts if t.startswith(subject + " ")}
            assert said and said <= allowed, (subject, said)
        assert not any("their left" in t or "their right" in t for t in texts)  # "his" -> "their" comes before
        assert not any(" his " in t or " her " in t for t in (reworded(caption, rng) for _ in range(100)))
    assert all(" the left " in reworded("a person waves the left hand.", rng, sides=True) for _ in range(50))
    units = [Unit(features=np.zeros((40, 263), np.float32), label="walk-turn-left",
                  captions=["someone walks forward and turns to the left."])]
    assert with_reworded_captions(units, 8, seed=0, sides=True) != with_reworded_captions(units, 8, seed=0)


def test_caption_embedding_cache_is_remade_for_another_caption_list(tmp_path):
    from mld_core.training.denoiser import cached_caption_embeddings

    calls = []

    def make(texts):
        def run():
            calls.append(list(texts))
            return {"pooled": torch.arange(len(texts), dtype=torch.float32)[:, None]}
        return run

    path = tmp_path / "text.safetensors"
    first = cached_caption_embeddings(path, ["a", "b"], make(["a", "b"]))
    again = cached_caption_embeddings(path, ["a", "b"], make(["a", "b"]))
    assert len(calls) == 1 and torch.equal(first["pooled"], again["pooled"])  # read back, not remade
    cached_caption_embeddings(path, ["a", "c"], make(["a", "c"]))  # same count, other captions: remade
    cached_caption_embeddings(path, ["a", "c", "d"], make(["a", "c", "d"]))
    assert calls[1:] == [["a", "c"], ["a", "c", "d"]]


def test_train_modules_trains_only_the_named_modules_and_refuses_unknown_names(tmp_path, capsys):
    """train_modules: the named top-level modules move; every other weight stays the --init model's, bit for bit,
    also across --resume. An unknown name or a bare string is refused before any work, leaving no folder."""
    from safetensors.torch import load_file

    from mld_core.testing import tiny_model
    from mld_core.training.denoiser import DenoiserTrainConfig
    from test_reliability import _h3d_folder

    model = tiny_model(tmp_path / "tiny")
    data = _h3d_folder(tmp_path / "data")
    run = tmp_path / "run"
    args = ["train", "denoiser", "--data", str(data), "--vae", str(model), "--init", str(model), "--out", str(run),
            "--threads", "1", "--lr", "1e-2"]
    encoder = json.loads((model / "config.json").read_text())["text_encoder"]
    text_only = json.dumps({"train_modules": ["text_proj", "token_proj"], "batch_size": 8, "save_every": 3,
                            "text_encoder": encoder})
    assert main(args + ["--steps", "3", "--config", text_only]) == 0
    capsys.readouterr()
    assert main(args + ["--steps", "6", "--resume"]) == 2  # another setting cannot continue the optimiser's state
    assert "trained train_modules ['text_proj', 'token_proj']" in capsys.readouterr().err
    assert main(args + ["--steps", "6", "--config", text_only, "--resume"]) == 0
    start, tuned = load_file(str(model / "denoiser.safetensors")), load_file(str(run / "denoiser.safetensors"))
    moved = sorted({k.split(".")[0] for k in start if not torch.equal(start[k].float(), tuned[k].float())})
    assert moved == ["text_proj", "token_proj"]
    saved = json.loads((run / "config.json").read_text())["provenance"]["denoiser_training"]
    assert saved["train_modules"] == ["text_proj", "token_proj"]
    assert saved["init"] == str(model)  # outside the checkout: as given

    capsys.readouterr()
    bad = tmp_path / "bad"
    bad_args = [a if a != str(run) else str(bad) for a in args]
    assert main(bad_args + ["--steps", "1", "--config", '{"train_modules": ["text_projection"]}']) == 2
    err = capsys.readouterr().err
    assert "no module text_projection" in err and "token_proj" in err and not bad.exists()
    assert main(bad_args + ["--steps", "1", "--config", '{"train_modules": "text_proj"}']) == 2
    assert "train_modules must be a non-empty list" in capsys.readouterr().err and not bad.exists()
    for bad in ([], {"text_proj": 1}, 5, [""], ["text_proj", 3]):
        with pytest.raises(ValueError, match="train_modules must be"):
            DenoiserTrainConfig(train_modules=bad)


def test_decoder_only_vae_fine_tune_keeps_the_encoder_and_swaps_in_under_the_denoiser(tmp_path, capsys):
    """train vae with the decoder modules only: the encoder stays the --init model's bit for bit, so
    export_model --vae-decoder pairs the new decoder with the model's denoiser; a VAE whose encoder moved is refused
    in one line, and so is an unknown module name or another train_modules on --resume."""
    import shutil
    import sys
    from pathlib import Path

    from safetensors.torch import load_file

    from mld_core.models.vae import DECODER_MODULES, ENCODER_MODULES
    from mld_core.testing import tiny_model
    from test_reliability import _h3d_folder

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    import export_model

    model = tiny_model(tmp_path / "tiny", draft=True)
    data = _h3d_folder(tmp_path / "data")
    config = json.loads((model / "config.json").read_text())
    np.save(data / "Mean.npy", np.asarray(config["mean"], np.float32))
    np.save(data / "Std.npy", np.asarray(config["std"], np.float32))
    np.save(data / "new_joint_vecs" / "000001.npy", np.random.default_rng(0).normal(size=(60, 263)).astype(np.float32))

    def train(run, steps, modules, *extra):
        settings = {"val_every": 100, "joint_weight": 1.0, "min_frames": 16}
        if modules is not None:
            settings["train_modules"] = modules
        return main(["train", "vae", "--data", str(data), "--init", str(model), "--out", str(run), "--threads", "1",
                     "--lr", "1e-2", "--steps", str(steps), "--config", json.dumps(settings), *extra])

    run = tmp_path / "decoder_run"
    assert train(run, 2, list(DECODER_MODULES)) == 0
    capsys.readouterr()
    assert train(run, 4, None, "--resume") == 2
    assert "trained train_modules ['latent_positions', 'decoder', 'head']" in capsys.readouterr().err
    assert train(run, 4, list(DECODER_MODULES), "--resume") == 0
    start, tuned = load_file(str(model / "vae.safetensors")), load_file(str(run / "vae.safetensors"))
    moved = sorted({k.split(".")[0] for k in start if not torch.equal(start[k].float(), tuned[k].float())})
    assert moved == sorted(DECODER_MODULES)
    capsys.readouterr()
    assert train(tmp_path / "bad", 1, ["decoder", "heads"]) == 2
    err = capsys.readouterr().err
    assert "no module heads in this VAE" in err and "latent_positions" in err and not (tmp_path / "bad").exists()

    shipped = tmp_path / "shipped"
    assert export_model.main([str(model), "--out", str(shipped), "--vae-decoder", str(run)]) == 0
    out = load_file(str(shipped / "vae.safetensors"))
    for key, value in out.items():
        source = tuned if key.split(".")[0] in DECODER_MODULES else start
        assert torch.equal(value, source[key].half()), key
    assert load_file(str(shipped / "denoiser.safetensors")).keys() == load_file(str(model / "denoiser.safetensors")).keys()
    provenance = json.loads((shipped / "config.json").read_text())["provenance"]
    assert provenance["vae_decoder_training"]["train_modules"] == list(DECODER_MODULES)
    for shift, accepted in ((3e-18, True), (1e-3, False)):  # float noise of a re-prepared folder vs another folder
        donor = tmp_path / f"donor_{shift}"
        shutil.copytree(run, donor)
        donor_config = json.loads((donor / "config.json").read_text())
        donor_config["mean"][0] += shift
        (donor / "config.json").write_text(json.dumps(donor_config))
        capsys.readouterr()
        code = export_model.main([str(model), "--out", str(tmp_path / f"out_{shift}"), "--vae-decoder", str(donor)])
        assert code == (0 if accepted else 2), shift
        assert accepted or "another data folder's" in capsys.readouterr().err
    draft = load_file(str(model / "draft.safetensors"))  # the Draft samples the same latents: it comes along
    assert all(torch.equal(v, draft[k].half()) for k, v in load_file(str(shipped / "draft.safetensors")).items())
    from mld_core.pipeline import MLDPipeline
    take = MLDPipeline.from_pretrained(shipped)(["a person walks"], seconds=1.0, draft=True)
    assert take.joints.shape == (1, 20, 22, 3)
    broken = tmp_path / "no_draft_weights"
    shutil.copytree(model, broken)
    (broken / "draft.safetensors").unlink()
    capsys.readouterr()
    assert export_model.main([str(broken), "--out", str(tmp_path / "refused_draft")]) == 2
    assert "names a Draft in config.json but has no draft.safetensors" in capsys.readouterr().err
    assert not (tmp_path / "refused_draft").exists()

    whole = tmp_path / "whole_run"
    assert train(whole, 2, None) == 0
    capsys.readouterr()
    assert export_model.main([str(model), "--out", str(tmp_path / "refused"), "--vae-decoder", str(whole)]) == 2
    err = capsys.readouterr().err
    assert "another encoder" in err and "Traceback" not in err and not (tmp_path / "refused").exists()
    everything = load_file(str(whole / "vae.safetensors"))
    assert {k.split(".")[0] for k in start if not torch.equal(start[k].float(), everything[k].float())} \
        >= set(ENCODER_MODULES)


def test_vae_resumed_with_another_selection_starts_its_best_afresh(folder, tmp_path):
    """The best checkpoint's number is the metric its sitting selects by: a sitting that selects by the sum of the
    root-relative and global errors does not compare it with a root-relative best, and keeps its own best."""
    run = tmp_path / "vae"
    args = ["train", "vae", "--data", str(folder), "--out", str(run), "--threads", "1", "--lr", "3e-3"]
    assert main(args + ["--steps", "20", "--config", json.dumps(TINY_VAE)]) == 0
    first = (run / "vae.safetensors").read_bytes()
    assert main(args + ["--steps", "30", "--resume", "--config",
                        json.dumps({**TINY_VAE, "select_by": "mpjpe_sum"})]) == 0
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == 30 and log[-1]["val_global_mpjpe_mm"] > 0
    assert (run / "vae.safetensors").read_bytes() != first  # step 30 is the new sitting's first (and best) record
    assert json.loads((run / "config.json").read_text())["provenance"]["vae_steps"] == 30


def test_action_conditioned_denoiser_trains_and_generates_each_label(folder, tmp_path):
    """`train denoiser --cond action` learns one class per label of actions.json (the CLI does not need the count)
    and `generate --action` makes a take of a label."""
    vae_run = tmp_path / "vae"
    assert main(["train", "vae", "--data", str(folder), "--out", str(vae_run), "--steps", "10", "--threads", "1",
                 "--config", json.dumps(TINY_VAE)]) == 0
    den = {k: v for k, v in TINY_DEN.items() if k != "text_encoder"}
    run = tmp_path / "act"
    assert main(["train", "denoiser", "--data", str(folder), "--vae", str(vae_run), "--out", str(run), "--cond",
                 "action", "--steps", "20", "--threads", "1", "--config", json.dumps(den)]) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["denoiser"]["cond"] == "action" and config["denoiser"]["num_actions"] == 2
    assert config["actions"] == ["a", "b"]
    out = tmp_path / "take.npz"
    assert main(["generate", "--model", str(run), "--action", "b", "--seconds", "1.5", "--steps", "3",
                 "--out", str(out)]) == 0
    assert np.isfinite(np.load(out)["joints"]).all()


def test_action_denoiser_starts_from_a_text_denoiser_with_init(folder, tmp_path):
    """`train denoiser --cond action --init TEXT_RUN`: the action model starts with the text model's transformer
    (a warm start, not a copy of its condition) and generates each label."""
    from safetensors.torch import load_file

    vae_run, text_run, act_run = tmp_path / "vae", tmp_path / "text", tmp_path / "act"
    assert main(["train", "vae", "--data", str(folder), "--out", str(vae_run), "--steps", "2", "--threads", "1",
                 "--config", json.dumps(TINY_VAE)]) == 0
    assert main(["train", "denoiser", "--data", str(folder), "--vae", str(vae_run), "--out", str(text_run),
                 "--steps", "2", "--threads", "1", "--config", json.dumps(TINY_DEN)]) == 0
    den = {k: v for k, v in TINY_DEN.items() if k not in ("text_encoder", "denoiser")}
    assert main(["train", "denoiser", "--data", str(folder), "--vae", str(vae_run), "--out", str(act_run), "--cond",
                 "action", "--init", str(text_run), "--steps", "1", "--lr", "1e-9", "--threads", "1",
                 "--config", json.dumps(den)]) == 0
    config = json.loads((act_run / "config.json").read_text())
    assert config["denoiser"]["cond"] == "action" and config["denoiser"]["num_actions"] == 2
    old, new = load_file(str(text_run / "denoiser.safetensors")), load_file(str(act_run / "denoiser.safetensors"))
    shared = [k for k in new if k.startswith(("transformer.", "latent_in", "time_mlp"))]
    assert len(shared) > 5 and all(torch.allclose(new[k].float(), old[k].float(), atol=1e-3) for k in shared)
    assert "action_embedding.weight" in new and "text_proj.weight" not in new
    again = tmp_path / "again"  # an action model continued on the same labels keeps its class embedding (another
    # seed, so that a fresh one would differ)
    assert main(["train", "denoiser", "--data", str(folder), "--vae", str(vae_run), "--out", str(again), "--cond",
                 "action", "--init", str(act_run), "--steps", "1", "--lr", "1e-9", "--threads", "1", "--seed", "1",
                 "--config", json.dumps(den)]) == 0
    kept = load_file(str(again / "denoiser.safetensors"))["action_embedding.weight"].float()
    assert torch.allclose(kept, new["action_embedding.weight"].float(), atol=1e-3)
    out = tmp_path / "take.npz"
    assert main(["generate", "--model", str(act_run), "--action", "a", "--seconds", "1.5", "--steps", "2",
                 "--out", str(out)]) == 0
    assert np.isfinite(np.load(out)["joints"]).all()


def test_vae_fine_tune_takes_a_new_kl_weight_and_keeps_it_on_resume(tmp_path, capsys):
    """kl_weight overrides the --init model's KL weight (the fine-tuned folder's config says so) and the KL term of
    the loss moves with it; --resume keeps the first sitting's weight; a weight outside 0..1 is refused in one line."""
    from mld_core.testing import tiny_model
    from mld_core.training.vae import VAETrainConfig
    from test_reliability import _h3d_folder

    model = tiny_model(tmp_path / "tiny")
    data = _h3d_folder(tmp_path / "data")
    before = json.loads((model / "config.json").read_text())["vae"]["kl_weight"]

    def train(run, steps, settings, *extra):
        return main(["train", "vae", "--data", str(data), "--init", str(model), "--out", str(run), "--threads", "1",
                     "--steps", str(steps), "--config", json.dumps({"val_every": 100, "min_frames": 16, **settings}),
                     *extra])

    losses = {}
    for name, settings in (("kept", {}), ("loosened", {"kl_weight": 0.0})):
        assert train(tmp_path / name, 1, settings) == 0
        record = json.loads((tmp_path / name / "log.jsonl").read_text().splitlines()[-1])
        losses[name] = (record["loss"], record["mse"], record["kl"])
        saved = json.loads((tmp_path / name / "config.json").read_text())["vae"]["kl_weight"]
        assert saved == (before if name == "kept" else 0.0)
    loss, mse, kl = losses["kept"]
    assert kl > 0 and loss == pytest.approx(mse + before * kl, rel=1e-5)
    loss, mse, _ = losses["loosened"]
    assert loss == pytest.approx(mse, rel=1e-6)  # the same first batch, no KL term
    assert train(tmp_path / "loosened", 2, {"kl_weight": 0.5}, "--resume") == 0
    for name in ("config.json", "train_config.json"):
        assert json.loads((tmp_path / "loosened" / name).read_text())["vae"]["kl_weight"] == 0.0
    capsys.readouterr()
    assert train(tmp_path / "bad", 1, {"kl_weight": 2.0}) == 2
    assert "kl_weight must be between 0 and 1, got 2" in capsys.readouterr().err and not (tmp_path / "bad").exists()
    with pytest.raises(ValueError, match="kl_weight"):
        VAETrainConfig(kl_weight=float("nan"))


def test_vae_latent_noise_scales_the_posterior_draw(tmp_path, monkeypatch):
    """latent_noise scales the training draw z = mu + latent_noise * sigma * eps: 0 trains on mu itself, 1 (the
    default) is the VAE's own sampling; outside 0..1 is refused."""
    from mld_core.models.vae import MotionVAE
    from mld_core.testing import tiny_model
    from mld_core.training.vae import VAETrainConfig
    from test_reliability import _h3d_folder

    model = tiny_model(tmp_path / "tiny")
    data = _h3d_folder(tmp_path / "data")
    seen = []
    forward = MotionVAE.forward

    def recording(self, x, lengths, sample=True, noise=None):
        seen.append(noise.detach().clone())
        return forward(self, x, lengths, sample=sample, noise=noise)

    monkeypatch.setattr(MotionVAE, "forward", recording)
    draws = {}
    for scale in (1.0, 0.25, 0.0):
        seen.clear()
        settings = {"val_every": 100, "min_frames": 16, "latent_noise": scale}
        assert main(["train", "vae", "--data", str(data), "--init", str(model), "--out", str(tmp_path / f"run{scale}"),
                     "--threads", "1", "--steps", "1", "--config", json.dumps(settings)]) == 0
        draws[scale] = seen[0]
    assert draws[1.0].std() > 0.5 and torch.allclose(draws[0.25], 0.25 * draws[1.0])  # the same eps, scaled
    assert torch.count_nonzero(draws[0.0]) == 0
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="latent_noise"):
            VAETrainConfig(latent_noise=bad)


def test_denoiser_fine_tune_renormalises_another_vaes_latents_when_asked(tmp_path):
    """--init keeps the init model's latent normalisation (the latents it learned); renormalise_latents, for a
    denoiser moved onto a retrained encoder, normalises the new latents afresh: their mean and 1/std."""
    from safetensors.torch import load_file

    from mld_core.testing import tiny_model
    from mld_core.training.denoiser import LATENT_CACHE
    from test_reliability import _h3d_folder

    model = tiny_model(tmp_path / "tiny")
    data = _h3d_folder(tmp_path / "data")
    init = json.loads((model / "config.json").read_text())
    encoder = init["text_encoder"]
    saved = {}
    for flag in (False, True):
        run = tmp_path / f"run_{flag}"
        settings = {"batch_size": 8, "text_encoder": encoder, "renormalise_latents": flag}
        assert main(["train", "denoiser", "--data", str(data), "--vae", str(model), "--init", str(model), "--out",
                     str(run), "--threads", "1", "--steps", "1", "--config", json.dumps(settings)]) == 0
        config = json.loads((run / "config.json").read_text())
        saved[flag] = (config["latent_mean"], config["latent_scale"])
        mu = load_file(str(run / LATENT_CACHE))["mu"]
    assert saved[False] == (init["latent_mean"], init["latent_scale"])
    assert saved[True] == pytest.approx((float(mu.mean()), float(1.0 / mu.std())), rel=1e-6)
    assert saved[True] != saved[False]


def test_vae_fine_tune_grows_the_init_latent_and_resumes_at_its_new_shape(tmp_path, capsys):
    """grow_latent_tokens: the run's VAE has the grown latent (config and weights), its first validation is near the
    init model's (the copies decode as the old latent), --resume continues at that shape; without --init it is
    refused in one line, leaving no folder."""
    from safetensors.torch import load_file

    from mld_core.testing import tiny_model
    from test_reliability import _h3d_folder

    model = tiny_model(tmp_path / "tiny")
    data = _h3d_folder(tmp_path / "data")
    before = json.loads((model / "config.json").read_text())["vae"]["latent_tokens"]

    def train(run, steps, settings, *extra, init=True):
        return main(["train", "vae", "--data", str(data), "--out", str(run), "--threads", "1", "--steps", str(steps),
                     *(["--init", str(model)] if init else []), "--lr", "1e-9",
                     "--config", json.dumps({"val_every": 1, "min_frames": 16, **settings}), *extra])

    assert train(tmp_path / "same", 1, {}) == 0
    assert train(tmp_path / "grown", 1, {"grow_latent_tokens": before + 3}) == 0
    config = json.loads((tmp_path / "grown" / "config.json").read_text())
    assert config["vae"]["latent_tokens"] == before + 3
    weights = load_file(str(tmp_path / "grown" / "vae.safetensors"))
    assert weights["latent_positions"].shape[0] == before + 3
    assert weights["distribution_tokens"].shape[0] == 2 * (before + 3)
    same, grown = (json.loads((tmp_path / n / "log.jsonl").read_text().splitlines()[0]) for n in ("same", "grown"))
    assert grown["val_mpjpe_mm"] == pytest.approx(same["val_mpjpe_mm"], rel=0.2)
    assert train(tmp_path / "grown", 2, {"grow_latent_tokens": before + 3}, "--resume") == 0
    assert json.loads((tmp_path / "grown" / "train_config.json").read_text())["vae"]["latent_tokens"] == before + 3
    capsys.readouterr()
    assert train(tmp_path / "bad", 1, {"grow_latent_tokens": 4}, init=False) == 2
    assert "grow_latent_tokens grows the latent of the --init model" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_denoiser_fine_tune_grows_onto_a_grown_vae_and_generates(tmp_path):
    """--init on a VAE whose latent was grown (n -> 2n tokens): the denoiser's latent positions grow the same way
    (copies of the old ones, a little noise), every other weight starts as the init model's, and the run
    generates takes of the new latent's shape."""
    from safetensors.torch import load_file

    from mld_core.pipeline import MLDPipeline
    from mld_core.testing import tiny_model
    from test_reliability import _h3d_folder

    model = tiny_model(tmp_path / "tiny")
    data = _h3d_folder(tmp_path / "data")
    init = json.loads((model / "config.json").read_text())
    n = init["vae"]["latent_tokens"]
    grown_vae = tmp_path / "vae"
    assert main(["train", "vae", "--data", str(data), "--init", str(model), "--out", str(grown_vae), "--threads", "1",
                 "--steps", "1", "--config", json.dumps({"min_frames": 16, "grow_latent_tokens": 2 * n})]) == 0
    run = tmp_path / "run"
    settings = {"batch_size": 8, "text_encoder": init["text_encoder"], "renormalise_latents": True}
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(grown_vae), "--init", str(model), "--out",
                 str(run), "--threads", "1", "--steps", "1", "--lr", "1e-9", "--config", json.dumps(settings)]) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["denoiser"]["latent_tokens"] == config["vae"]["latent_tokens"] == 2 * n
    old, new = load_file(str(model / "denoiser.safetensors")), load_file(str(run / "denoiser.safetensors"))
    old_positions, new_positions = old["positions"].float(), new["positions"].float()
    assert new_positions.shape[0] == old_positions.shape[0] + n
    assert torch.allclose(new_positions[-2 * n:-n], old_positions[-n:], atol=1e-3)
    assert torch.allclose(new_positions[-n:], old_positions[-n:], atol=0.05)  # the copies, with the growth noise
    assert torch.allclose(new["latent_in.weight"].float(), old["latent_in.weight"].float(), atol=1e-3)
    take = MLDPipeline.from_pretrained(run)(["a person walks"], seconds=1.0, num_inference_steps=2)
    assert np.isfinite(take.joints).all() and take.joints.shape[0] == 1


def test_label_boost_multiplies_a_labels_sampling_share_and_refuses_a_label_no_clip_has(folder, tmp_path, capsys):
    from mld_core.training.vae import VAETrainConfig

    labels = ["walk"] * 8 + ["kick"] * 2
    plain = boosted_weights(labels, 0.5, None)
    boosted = boosted_weights(labels, 0.5, {"kick": 6})
    assert plain[8:].sum() == pytest.approx(2 ** 0.5 / (8 ** 0.5 + 2 ** 0.5))  # 1/3 of draws by the balance
    assert boosted[8:].sum() == pytest.approx(6 * 2 ** 0.5 / (8 ** 0.5 + 6 * 2 ** 0.5))  # 3/4 with the boost
    assert boosted[:8].sum() + boosted[8:].sum() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="no train clip is labelled 'kik'"):
        boosted_weights(labels, 0.5, {"kik": 6})
    for bad, words in (({"kick": 0}, "label_boost\\['kick'\\] must be between"), ([6], "label_boost must be"),
                       ({}, "label_boost must be")):
        with pytest.raises(ValueError, match=words):
            VAETrainConfig(label_boost=bad)
    cfg = tmp_path / "vae.json"  # the fixture's train clips alternate labels "a" and "b"
    cfg.write_text(json.dumps({**TINY_VAE, "label_boost": {"b": 4.0}}))
    run = tmp_path / "boost"
    assert main(["train", "vae", "--data", str(folder), "--out", str(run), "--steps", "2", "--threads", "1",
                 "--config", str(cfg)]) == 0
    assert json.loads((run / "config.json").read_text())["provenance"]["vae_training"]["label_boost"] == {"b": 4.0}
    cfg.write_text(json.dumps({**TINY_VAE, "label_boost": {"c": 4.0}}))
    capsys.readouterr()
    assert main(["train", "vae", "--data", str(folder), "--out", str(tmp_path / "bad"), "--steps", "1",
                 "--config", str(cfg)]) == 2
    assert "no train clip is labelled 'c' (labels: a, b)" in capsys.readouterr().err


def test_a_denoiser_draws_its_boosted_labels_more_often_and_refuses_a_label_no_clip_has(folder, tmp_path, capsys,
                                                                                          monkeypatch):
    """train denoiser's label_boost, as the VAE's: the sampling weights it trains with are boosted_weights' of the
    train units' labels, recorded in the run's provenance; a label no clip has is one line, exit 2, no run written."""
    from mld_core.training import denoiser

    vae_run = tmp_path / "vae"
    assert main(["train", "vae", "--data", str(folder), "--out", str(vae_run), "--steps", "2", "--threads", "1",
                 "--config", json.dumps(TINY_VAE)]) == 0
    used = []

    def spy(labels, power, boost):
        used.append((sorted(set(labels)), boost))
        return boosted_weights(labels, power, boost)

    monkeypatch.setattr(denoiser, "boosted_weights", spy)
    args = ["train", "denoiser", "--data", str(folder), "--vae", str(vae_run), "--steps", "2", "--threads", "1"]
    run = tmp_path / "den"
    assert main(args + ["--out", str(run), "--config", json.dumps({**TINY_DEN, "label_boost": {"b": 4}})]) == 0
    assert used == [(["a", "b"], {"b": 4.0})]
    assert json.loads((run / "config.json").read_text())["provenance"]["denoiser_training"]["label_boost"] == {"b": 4.0}
    capsys.readouterr()
    encoded = []
    monkeypatch.setattr(denoiser, "encode_latents", lambda *a, **k: encoded.append(1))
    bad = tmp_path / "bad"
    assert main(args + ["--out", str(bad), "--config", json.dumps({**TINY_DEN, "label_boost": {"c": 4}})]) == 2
    assert "no train clip is labelled 'c' (labels: a, b)" in capsys.readouterr().err
    assert encoded == [] and not bad.exists()  # refused before the slow encoding, nothing left behind


def test_vae_sittings_carry_their_lineage_and_a_vae_alone_exports_to_continue_from(tmp_path, capsys):
    """Each --init sitting records the training it started from (provenance.vae_lineage, kept on --resume); a VAE
    run exports as a fp16 VAE folder whose card lists every sitting, which the next sitting continues from; options
    that need a denoiser are refused in one line, with nothing written."""
    import sys
    from pathlib import Path

    from safetensors.torch import load_file

    from mld_core.checkpoint import DEFAULT_MODEL_DIR, load_config, load_weights, recorded_path
    from mld_core.models.vae import MotionVAE
    from mld_core.testing import tiny_model
    from test_reliability import _h3d_folder

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    import export_model

    model = tiny_model(tmp_path / "tiny")
    data = _h3d_folder(tmp_path / "data")

    def sitting(out, init, steps, *extra):
        return main(["train", "vae", "--data", str(data), "--out", str(out), "--threads", "1", "--steps", str(steps),
                     "--config", json.dumps({"val_every": 100, "min_frames": 16}),
                     *(["--init", str(init)] if init else []), *extra])

    def lineage(run):
        return [(s["model_id"], s["steps"]) for s in load_config(run).provenance.get("vae_lineage", [])]

    tiny_id = load_config(model).model_id
    assert sitting(tmp_path / "first", model, 2) == 0
    assert lineage(tmp_path / "first") == [(tiny_id, None)]  # the tiny folder records no VAE steps of its own
    assert sitting(tmp_path / "second", tmp_path / "first", 2) == 0
    assert lineage(tmp_path / "second") == [(tiny_id, None), ("first-vae", 2)]
    assert sitting(tmp_path / "second", None, 3, "--resume") == 0  # a resumed run keeps where it started from
    assert lineage(tmp_path / "second") == [(tiny_id, None), ("first-vae", 2)]
    assert load_config(tmp_path / "second").provenance["vae_steps"] == 3
    state_file = tmp_path / "second" / "train_state.pt"  # a train state saved before lineages were kept:
    state = torch.load(state_file, weights_only=True)    # resuming with --init names where it started
    state["extra"] = json.dumps({k: v for k, v in json.loads(state["extra"]).items() if k != "vae_lineage"})
    torch.save(state, state_file)
    (tmp_path / "second" / "config.json").unlink()  # so the sitting writes it afresh
    assert sitting(tmp_path / "second", tmp_path / "first", 4, "--resume") == 0
    assert lineage(tmp_path / "second") == [(tiny_id, None), ("first-vae", 2)]
    assert sitting(tmp_path / "scratch", None, 1) == 0 and lineage(tmp_path / "scratch") == []  # from nothing

    kept = tmp_path / "kept"
    assert export_model.main([str(tmp_path / "second"), "--out", str(kept), "--model-id", "v-kept"]) == 0
    assert sorted(p.name for p in kept.iterdir()) == ["MODEL_CARD.md", "config.json", "vae.safetensors"]
    assert {v.dtype for v in load_file(str(kept / "vae.safetensors")).values()} == {torch.float16}
    card = (kept / "MODEL_CARD.md").read_text()
    assert "4 in its own sitting, 6 over the 3 sittings below" in card and "- first-vae: 2 steps from" in card and "v-kept: 4 steps" in card
    run_vae, kept_vae = MotionVAE(load_config(tmp_path / "second").vae), MotionVAE(load_config(kept).vae)
    load_weights(tmp_path / "second" / "vae.safetensors", run_vae)
    load_weights(kept / "vae.safetensors", kept_vae)
    x = torch.randn(1, 30, 263)
    with torch.no_grad():
        a = run_vae.decode(run_vae.encode(x, torch.tensor([30]))[0], torch.tensor([30]))
        b = kept_vae.decode(kept_vae.encode(x, torch.tensor([30]))[0], torch.tensor([30]))
    assert torch.allclose(a, b, atol=2e-2) and not torch.equal(a, torch.zeros_like(a))
    assert sitting(tmp_path / "third", kept, 1) == 0  # the exported folder is where the next sitting starts
    assert lineage(tmp_path / "third")[-1] == ("v-kept", 4) and len(lineage(tmp_path / "third")) == 3

    capsys.readouterr()
    assert export_model.main([str(tmp_path / "second"), "--out", str(tmp_path / "no"), "--data", str(data)]) == 2
    assert "is a VAE alone" in capsys.readouterr().err and not (tmp_path / "no").exists()
    assert export_model.main([str(tmp_path / "second"), "--out", str(kept)]) == 2  # no silent overwrite
    assert "pass --overwrite" in capsys.readouterr().err and (kept / "vae.safetensors").is_file()
    assert recorded_path(str(DEFAULT_MODEL_DIR)) == "mld_core/weights/default"
    assert recorded_path(str(tmp_path)) == str(tmp_path)
    assert load_config(tmp_path / "first").provenance["vae_training"]["init"] == str(model)


def test_a_denoiser_run_records_paths_inside_the_checkout_relative_to_it(tmp_path):
    """The bundled model as --init (its default) and a VAE folder in the checkout are recorded as the same text on
    every machine; a folder elsewhere as given."""
    from mld_core.checkpoint import DEFAULT_MODEL_DIR, PROJECT_ROOT
    from mld_core.training.denoiser import DenoiserTrainConfig, recorded_settings

    cfg = DenoiserTrainConfig(data=str(tmp_path / "data"), vae=str(PROJECT_ROOT / "research" / "v4" / "vae"),
                              out="runs/x", init=str(DEFAULT_MODEL_DIR))
    saved = recorded_settings(cfg)
    assert saved["init"] == "mld_core/weights/default" and saved["vae"] == "research/v4/vae"
    assert saved["data"] == str(tmp_path / "data") and "denoiser" not in saved


def test_export_model_card_says_where_the_model_came_from_and_takes_the_notes_limits(tmp_path):
    """The card's first line says fine-tuned when the denoiser started from weights, its data row is
    --data-description's, and notes with their own Limits replace the Bandai model's (one Limits section)."""
    import sys
    from pathlib import Path

    from mld_core.testing import tiny_model

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    import export_model

    model = tiny_model(tmp_path / "tiny")
    config = json.loads((model / "config.json").read_text())
    config["provenance"]["denoiser_training"] = {"init": "mld_core/weights/v4_preview"}
    (model / "config.json").write_text(json.dumps(config))
    notes = tmp_path / "notes.md"
    notes.write_text("## Measurements of this run\nnone\n\n## Limits\nKicks are weak.\n")
    out = tmp_path / "out"
    assert export_model.main([str(model), "--out", str(out), "--notes", str(notes),
                              "--data-description", "Bandai + CMU, 20.4 h"]) == 0
    card = (out / "MODEL_CARD.md").read_text()
    assert "fine-tuned from the weights named under Training" in card and "| data | Bandai + CMU, 20.4 h |" in card
    assert card.count("## Limits") == 1 and "Kicks are weak." in card and "24 content classes" not in card
    del config["provenance"]["denoiser_training"]
    (model / "config.json").write_text(json.dumps(config))
    assert export_model.main([str(model), "--out", str(tmp_path / "plain")]) == 0
    card = (tmp_path / "plain" / "MODEL_CARD.md").read_text()
    assert "trained from scratch on two CPU cores" in card and "3,076 BVH clips" in card
    assert card.count("## Limits") == 1 and "24 content classes" in card


def test_train_denoiser_with_verb_hints_from_a_text_run(tmp_path):
    """`train denoiser --init TEXT_RUN` with verb_hints: the run reads every checked verb, starts as the text run
    (the shared weights carried over), learns vectors for the verbs its captions name and none for the others;
    continued without hints it drops them; an action run refuses them with a one-line message."""
    from safetensors.torch import load_file

    from mld_core.data.verbs import VERBS

    data = _write_folder(tmp_path / "data", lambda k: f"a person {('jumps', 'kicks', 'walks')[k % 3]} {k}#a/DET#0.0#0.0\n")
    vae, text, hinted = tmp_path / "vae", tmp_path / "text", tmp_path / "hinted"
    assert main(["train", "vae", "--data", str(data), "--out", str(vae), "--steps", "2", "--threads", "1",
                 "--config", json.dumps(TINY_VAE)]) == 0
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(vae), "--out", str(text), "--steps", "2",
                 "--threads", "1", "--config", json.dumps(TINY_DEN)]) == 0
    over = {k: v for k, v in TINY_DEN.items() if k != "denoiser"}
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(vae), "--out", str(hinted), "--init",
                 str(text), "--steps", "20", "--lr", "3e-3", "--threads", "1",
                 "--config", json.dumps({**over, "verb_hints": True, "verb_hint_dropout": 0.0})]) == 0
    config = json.loads((hinted / "config.json").read_text())
    assert config["denoiser"]["verb_hints"] == list(VERBS)
    rows = load_file(str(hinted / "denoiser.safetensors"))["verb_embedding.weight"].float().abs().sum(1)
    named = {1 + VERBS.index("jump"), 1 + VERBS.index("kick")}
    assert all(rows[i] > 0 for i in named) and all(rows[i] == 0 for i in range(len(rows)) if i not in named)
    out = tmp_path / "take.npz"
    assert main(["generate", "a person jumps", "--model", str(hinted), "--seconds", "1.5", "--steps", "2",
                 "--out", str(out)]) == 0
    assert np.isfinite(np.load(out)["joints"]).all()
    plain = tmp_path / "plain"
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(vae), "--out", str(plain), "--init",
                 str(hinted), "--steps", "1", "--threads", "1", "--config", json.dumps(over)]) == 0
    assert json.loads((plain / "config.json").read_text())["denoiser"]["verb_hints"] == []
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(vae), "--out", str(tmp_path / "act"),
                 "--cond", "action", "--steps", "1", "--threads", "1",
                 "--config", json.dumps({"verb_hints": True})]) == 2


def test_an_action_run_on_a_text_runs_latents_guides_it_and_the_guide_stays_with_that_text_run(tmp_path):
    """train denoiser --cond action --vae TEXT --init TEXT, then scripts/attach_verb_guide.py: the folder generates
    from the CLI, exports with its verb denoiser, and a denoiser trained on its VAE does not inherit the guide."""
    import importlib.util

    from mld_core.checkpoint import load_config
    from mld_core.pipeline import MLDPipeline

    spec = importlib.util.spec_from_file_location("attach_verb_guide", REPO / "scripts" / "attach_verb_guide.py")
    attach = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(attach)
    data = write_verb_folder(tmp_path / "data")
    vae, text, action, guided = (tmp_path / n for n in ("vae", "text", "action", "guided"))
    over = {k: v for k, v in TINY_DEN.items() if k != "denoiser"}
    assert main(["train", "vae", "--data", str(data), "--out", str(vae), "--steps", "2", "--threads", "1",
                 "--config", json.dumps(TINY_VAE)]) == 0
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(vae), "--out", str(text), "--steps", "2",
                 "--threads", "1", "--config", json.dumps(TINY_DEN)]) == 0
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(text), "--out", str(action), "--cond",
                 "action", "--init", str(text), "--steps", "2", "--threads", "1", "--config", json.dumps(over)]) == 0
    assert attach.main([str(text), str(action), "--out", str(guided), "--scale", "8"]) == 0
    assert load_config(guided).verb_guide.scale == 8.0
    out = tmp_path / "take.npz"
    assert main(["generate", "a person jumps", "--model", str(guided), "--seconds", "1.5", "--steps", "2",
                 "--out", str(out)]) == 0
    assert np.isfinite(np.load(out)["joints"]).all()
    exported = tmp_path / "exported"
    assert subprocess.run([sys.executable, str(REPO / "scripts" / "export_model.py"), str(guided), "--out",
                           str(exported)], capture_output=True, text=True, timeout=300).returncode == 0
    assert (exported / "verb_denoiser.safetensors").is_file()
    assert MLDPipeline.from_pretrained(exported).verb_guide.verbs == ["jump", "kick"]
    again = tmp_path / "again"
    assert main(["train", "denoiser", "--data", str(data), "--vae", str(guided), "--out", str(again), "--steps", "1",
                 "--threads", "1", "--config", json.dumps(TINY_DEN)]) == 0
    config = load_config(again)
    assert config.verb_guide is None and "verb_guide" not in config.provenance
    assert MLDPipeline.from_pretrained(again).verb_guide is None


def test_a_denoiser_run_reuses_another_runs_caches_with_caches_from(folder, tmp_path, monkeypatch):
    """caches_from: the latent and caption caches are copied from a run of the same data and VAE, so nothing is
    encoded again; a caption cache made for other captions is still made again (its SHA-256)."""
    from mld_core.training import denoiser

    vae_run = tmp_path / "vae"
    assert main(["train", "vae", "--data", str(folder), "--out", str(vae_run), "--steps", "2", "--threads", "1",
                 "--config", json.dumps(TINY_VAE)]) == 0
    args = ["train", "denoiser", "--data", str(folder), "--vae", str(vae_run), "--steps", "2", "--threads", "1"]
    first = tmp_path / "first"
    assert main(args + ["--out", str(first), "--config", json.dumps(TINY_DEN)]) == 0

    def refuse(*a, **k):
        raise AssertionError("encoded again")

    monkeypatch.setattr(denoiser, "encode_latents", refuse)
    monkeypatch.setattr(denoiser, "embed_captions", refuse)
    second = tmp_path / "second"
    assert main(args + ["--out", str(second), "--config", json.dumps({**TINY_DEN, "caches_from": str(first)})]) == 0
    for name in (denoiser.LATENT_CACHE, denoiser.TEXT_CACHE):
        assert (second / name).read_bytes() == (first / name).read_bytes()
    reworded = tmp_path / "reworded"  # other captions: the copied caption cache does not fit and is made again
    with pytest.raises(AssertionError, match="encoded again"):
        denoiser.train_denoiser(denoiser.DenoiserTrainConfig(
            data=str(folder), vae=str(vae_run), out=str(reworded), steps=1, threads=1, reworded_captions=2,
            caches_from=str(first), **{k: v for k, v in TINY_DEN.items() if k != "denoiser"},
            denoiser=denoiser.DenoiserConfig(**TINY_DEN["denoiser"])))


def test_caches_from_that_is_not_a_folder_is_refused_before_anything_is_written(folder, tmp_path, capsys):
    """A misspelt caches_from would silently encode everything again: one line, exit 2, no run folder."""
    vae_run = tmp_path / "vae"
    assert main(["train", "vae", "--data", str(folder), "--out", str(vae_run), "--steps", "1", "--threads", "1",
                 "--config", json.dumps(TINY_VAE)]) == 0
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")
    for where in (tmp_path / "missing", a_file):
        out = tmp_path / f"run_{where.name}"
        capsys.readouterr()
        assert main(["train", "denoiser", "--data", str(folder), "--vae", str(vae_run), "--steps", "1", "--out",
                     str(out), "--config", json.dumps({**TINY_DEN, "caches_from": str(where)})]) == 2
        err = capsys.readouterr().err
        assert f"caches_from: {where} is not a run folder" in err and "Traceback" not in err
        assert not out.exists() and a_file.read_text() == "mine"


@pytest.mark.parametrize("stage", ["denoiser", "draft"])
@pytest.mark.parametrize("setting", [{"caches_from": 5}, {"caches_from": ""}, {"caches_from": ["a"]}])
def test_a_folder_setting_that_is_not_a_path_is_one_line(folder, tmp_path, capsys, stage, setting):
    args = ["train", stage, "--data", str(folder), "--out", str(tmp_path / "run"), "--steps", "1",
            "--config", json.dumps(setting)]
    assert main(args + (["--vae", str(tmp_path / "vae")] if stage == "denoiser" else [])) == 2
    err = capsys.readouterr().err
    assert "caches_from must be a folder's path" in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()
