"""The evaluator (model, training, save/load) and the evaluate command on tiny seeded inputs."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
import pytest
import torch

from mld_core.eval import metrics
from mld_core.eval.evaluate import EvalSettings, PipelineGenerator, evaluate, format_table, write_json
from mld_core.eval.evaluator import Evaluator, EvaluatorConfig, EvaluatorError
from mld_core.eval.samples import draw_pairs
from mld_core.eval.train import EvaluatorTrainConfig, contrastive_loss, train_evaluator

TINY_TEXT = {"kind": "minilm-random", "seed": 0, "hidden": 32, "layers": 2, "heads": 2}
CONTENTS = ("walk", "run", "wave", "jump")


@dataclass
class Caption:
    text: str
    start_s: float = 0.0
    end_s: float = 0.0


@dataclass
class Clip:
    id: str
    features: np.ndarray
    captions: list = field(default_factory=list)
    action: str | None = None


def synthetic_clips(n: int, seed: int, dim: int = 12, prefix: str = "c") -> list[Clip]:
    """Each content has its own frequency in its own feature group, plus noise: learnable, not trivial."""
    rng = np.random.default_rng(seed)
    clips = []
    for i in range(n):
        k = i % len(CONTENTS)
        T = int(rng.integers(24, 60))
        t = np.arange(T)[:, None]
        x = 0.3 * rng.normal(size=(T, dim))
        group = slice(3 * k, 3 * k + 3)
        x[:, group] += np.sin(2 * np.pi * (k + 1) * t / 20 + rng.uniform(0, 6.28))
        caps = [Caption(f"a person does a {CONTENTS[k]}"), Caption(f"someone does a {CONTENTS[k]} motion")]
        clips.append(Clip(f"{prefix}{i:04d}", x.astype(np.float32), caps, CONTENTS[k]))
    return clips


@pytest.fixture(scope="module")
def text_encoder():
    from mld_core.models.text_encoder import load_text_encoder

    return load_text_encoder(dict(TINY_TEXT))


def tiny_config(dim: int = 12, **kw) -> EvaluatorConfig:
    base = dict(feature_dim=dim, hidden=32, embed_dim=16, layers=1, heads=2, ff_dim=64, dropout=0.0, text_dim=32,
                text_hidden=32, action_names=list(CONTENTS), text_encoder=dict(TINY_TEXT))
    base.update(kw)
    return EvaluatorConfig(**base)


def test_motion_embedding_is_the_same_alone_or_padded_in_a_batch():
    torch.manual_seed(0)
    model = Evaluator(tiny_config()).eval()
    rng = np.random.default_rng(0)
    short, long = rng.normal(size=(23, 12)).astype(np.float32), rng.normal(size=(61, 12)).astype(np.float32)
    alone = model.encode_motion([short])
    batched = model.encode_motion([long, short], batch_size=2)
    np.testing.assert_allclose(batched[1], alone[0], atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(batched, axis=1), 1.0, atol=1e-5)
    # (N, T, D) array + lengths is the same as a list of trimmed arrays
    padded = np.zeros((2, 61, 12), np.float32)
    padded[0], padded[1, :23] = long, short
    np.testing.assert_allclose(model.encode_motion(padded, lengths=[61, 23]), batched, atol=1e-6)
    # very short motions (fewer frames than the convolutions' stride) still embed
    assert np.isfinite(model.encode_motion([short[:2]])).all()


def test_embeddings_use_the_evaluators_own_normalisation():
    torch.manual_seed(0)
    mean, std = np.full(12, 3.0, np.float32), np.full(12, 2.0, np.float32)
    model = Evaluator(tiny_config(), mean, std).eval()
    plain = Evaluator(tiny_config()).eval()
    plain.load_state_dict({**model.state_dict(), "mean": torch.zeros(12), "std": torch.ones(12)})
    x = np.random.default_rng(1).normal(size=(30, 12)).astype(np.float32)
    np.testing.assert_allclose(model.encode_motion([x * 2.0 + 3.0]), plain.encode_motion([x]), atol=1e-5)


def test_contrastive_loss_hand_example_and_positives():
    t = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    m = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    # logits diag 1/tau, off 0: loss = log(1 + exp(-1/tau)) per row, both sides equal
    tau = 0.5
    expected = float(np.log1p(np.exp(-1 / tau)))
    assert float(contrastive_loss(t, m, torch.tensor([0, 1]), tau)) == pytest.approx(expected, rel=1e-6)
    # the same caption on both rows: both columns are positives -> loss = 0
    assert float(contrastive_loss(t, m, torch.tensor([0, 0]), tau)) == pytest.approx(0.0, abs=1e-6)


def test_save_load_roundtrip_fp16_and_errors(tmp_path):
    torch.manual_seed(0)
    model = Evaluator(tiny_config(), np.arange(12, dtype=np.float32), np.full(12, 0.5, np.float32)).eval()
    model.save_pretrained(tmp_path / "ev", card="# card\n")
    names = sorted(p.name for p in (tmp_path / "ev").iterdir())
    assert names == ["EVALUATOR_CARD.md", "config.json", "model.safetensors"]
    from safetensors import safe_open

    with safe_open(str(tmp_path / "ev" / "model.safetensors"), "pt") as f:
        assert f.get_tensor("motion_proj.weight").dtype == torch.float16
        assert f.get_tensor("mean").dtype == torch.float32
    loaded = Evaluator.from_pretrained(tmp_path / "ev")
    assert loaded.config == model.config
    x = [np.random.default_rng(2).normal(size=(40, 12)).astype(np.float32) + np.arange(12)]
    np.testing.assert_allclose(loaded.encode_motion(x), model.encode_motion(x), atol=2e-2)
    # a second save/load of the fp16 model is exact
    loaded.save_pretrained(tmp_path / "ev2")
    again = Evaluator.from_pretrained(tmp_path / "ev2")
    np.testing.assert_array_equal(again.encode_motion(x), loaded.encode_motion(x))
    with pytest.raises(EvaluatorError, match="not an evaluator folder"):
        Evaluator.from_pretrained(tmp_path / "missing")
    (tmp_path / "ev2" / "model.safetensors").write_bytes(b"garbage")
    with pytest.raises(EvaluatorError, match="cannot read"):
        Evaluator.from_pretrained(tmp_path / "ev2")


def test_text_encoder_is_frozen_and_not_part_of_the_evaluator(text_encoder):
    model = Evaluator(tiny_config())
    model._text_encoder = text_encoder
    own = {id(p) for p in model.parameters()}
    assert not any(id(p) in own for p in text_encoder.parameters())
    assert all(not p.requires_grad for p in text_encoder.parameters())
    emb = model.encode_text(["a person does a walk", "a person does a run"])
    assert emb.shape == (2, 16)
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)


def test_draw_pairs_crops_to_caption_segments_and_max_frames():
    x = np.arange(100 * 2, dtype=np.float32).reshape(100, 2)
    clip = Clip("a", x, [Caption("whole"), Caption("seg", 1.0, 2.0), Caption("tiny", 0.0, 0.2)])
    seen = set()
    for s in range(30):
        (p,) = draw_pairs([clip], np.random.default_rng(s), min_frames=10, max_frames=60)
        seen.add(p.text)
        assert p.text != "tiny"  # 4 frames < min_frames
        if p.text == "seg":
            np.testing.assert_array_equal(p.features, x[20:40])
        else:
            assert p.length == 60 and p.features[0, 0] % 2 == 0 and p.features[0, 0] / 2 <= 40
    assert seen == {"whole", "seg"}


def test_training_learns_synthetic_pairs_resumes_and_refuses_to_overwrite(tmp_path, text_encoder):
    train, val, test = synthetic_clips(96, 0), synthetic_clips(32, 1, prefix="v"), synthetic_clips(32, 2, prefix="t")
    data = (train, val, test, np.zeros(12), np.ones(12), list(CONTENTS))
    cfg = EvaluatorTrainConfig(data=str(tmp_path / "none"), out=str(tmp_path / "run"), epochs=3, minutes=None,
                               batch_size=16, lr=2e-3, warmup_steps=1, min_frames=10)
    logs = []
    out = train_evaluator(cfg, tiny_config(), text_encoder=text_encoder, data=data, progress=False, log=logs.append)
    history = json.loads((out / "history.json").read_text())
    assert [h["epoch"] for h in history["history"]] == [1, 2, 3]
    # resume: continue to 6 epochs from the saved state
    cfg6 = EvaluatorTrainConfig(**{**cfg.to_dict(), "epochs": 6})
    train_evaluator(cfg6, text_encoder=text_encoder, data=data, resume=True, progress=False, log=logs.append)
    history = json.loads((out / "history.json").read_text())
    assert [h["epoch"] for h in history["history"]] == [1, 2, 3, 4, 5, 6]
    assert any("resuming at epoch 3" in line for line in logs)
    report = history["report"]["test"]
    # 4 contents, pools of 32 with 8 clips per content: perfect content matching gives R@1 ~ 1/8, R@3 ~ 3/8
    assert report["action_acc"] > 0.9
    assert report["R@3"] > 0.25
    card = (out / "EVALUATOR_CARD.md").read_text()
    assert "CC BY-NC 4.0" in card and "| test (32 pairs) |" in card
    model = Evaluator.from_pretrained(out)
    assert model.config.action_names == list(CONTENTS)
    with pytest.raises(FileExistsError):
        train_evaluator(cfg, tiny_config(), text_encoder=text_encoder, data=data, progress=False, log=logs.append)
    with pytest.raises(FileNotFoundError):
        train_evaluator(EvaluatorTrainConfig(**{**cfg.to_dict(), "out": str(tmp_path / "new")}),
                        text_encoder=text_encoder, data=data, resume=True, progress=False)


# ----------------------------------------------------------------------------------------------- evaluate


def synthetic_263(n: int, seed: int) -> list[Clip]:
    """263-d clips around a standing pose (root height 0.9 m), small random motion."""
    rng = np.random.default_rng(seed)
    clips = []
    for i in range(n):
        k = i % len(CONTENTS)
        T = int(rng.integers(24, 50))
        x = 0.02 * rng.normal(size=(T, 263)).astype(np.float32)
        x[:, 3] += 0.9
        caps = [Caption(f"a person does a {CONTENTS[k]}")]
        clips.append(Clip(f"e{i:04d}", x, caps, CONTENTS[k]))
    return clips


@pytest.fixture(scope="module")
def tiny_evaluator(text_encoder):
    torch.manual_seed(0)
    model = Evaluator(tiny_config(dim=263, max_frames=60)).eval()
    model._text_encoder = text_encoder
    return model


SMALL = EvalSettings(replications=2, r_pool=8, diversity_times=10, mm_texts=3, mm_repeats=4, mm_times=3,
                     a2m_diversity_times=10, a2m_mm_times=4, kid_subsets=3, kid_subset_size=8, batch_size=8)


@pytest.mark.parametrize("task,cond", [("t2m", "text"), ("vae", "text"), ("uncond", "text"), ("a2m", "action"),
                                       ("a2m", "text")])
def test_evaluate_end_to_end_with_a_tiny_pipeline(tmp_path, tiny_evaluator, task, cond):
    from mld_core.testing import tiny_pipeline

    kwargs = {"actions": CONTENTS} if cond == "action" else {}
    pipe = tiny_pipeline(tmp_path / "model", cond=cond, **kwargs)
    clips = synthetic_263(16, 0)
    result = evaluate(task, tiny_evaluator, clips, PipelineGenerator(pipe, SMALL), SMALL, model_name="tiny",
                      progress=False)
    assert result["order"] == ["Real", "tiny"]
    assert result["pairs_per_replication"] == 16
    rows = result["rows"]
    expected = {"t2m": {"R@1", "R@2", "R@3", "FID", "MM-Dist", "Diversity", "MultiModality", "Content-Acc"},
                "vae": {"MPJPE", "MPJPE_global", "PA-MPJPE", "ACCEL", "FID", "Diversity"},
                "uncond": {"FID", "KID", "Diversity"},
                "a2m": {"FID", "Accuracy", "Diversity", "MultiModality"}}[task]
    assert set(rows["tiny"]) == expected
    for row in rows.values():
        for v in row.values():
            assert len(v["values"]) == 2 and np.isfinite(v["values"]).all()
            assert v["mean"] == pytest.approx(np.mean(v["values"]))
            assert v["ci"] == pytest.approx(metrics.mean_ci(v["values"])[1])
    if task == "t2m":
        assert 0.0 <= rows["tiny"]["R@1"]["mean"] <= rows["tiny"]["R@3"]["mean"] <= 1.0
        assert "MultiModality" not in rows["Real"]
    if task == "vae":
        assert rows["tiny"]["MPJPE"]["mean"] > 0.0  # a random VAE does not reconstruct
    # real motions against the reference draw of the same clips: FID far below the random model's
    assert rows["Real"]["FID"]["mean"] < rows["tiny"]["FID"]["mean"]
    table = format_table({**result, "data": "synthetic"})
    assert table.splitlines()[3].startswith("| Real") and "\u00b1" in table
    write_json(result, tmp_path / "out" / "r.json")
    assert json.loads((tmp_path / "out" / "r.json").read_text())["task"] == task


def test_evaluate_is_reproducible_and_replications_differ(tmp_path, tiny_evaluator):
    from mld_core.testing import tiny_pipeline

    pipe = tiny_pipeline(tmp_path / "model")
    clips = synthetic_263(24, 1)
    settings = EvalSettings(**{**SMALL.to_dict(), "mm_texts": 0, "max_pairs": 12})
    a = evaluate("t2m", tiny_evaluator, clips, PipelineGenerator(pipe, settings), settings, progress=False)
    b = evaluate("t2m", tiny_evaluator, clips, PipelineGenerator(pipe, settings), settings, progress=False)
    assert a["rows"] == b["rows"]
    assert a["pairs_per_replication"] == 12
    fids = a["rows"]["MLD"]["FID"]["values"]
    assert fids[0] != fids[1]  # each replication draws its own pairs and seeds


def test_evaluate_rejects_unusable_input(tmp_path, tiny_evaluator):
    from mld_core.testing import tiny_pipeline

    pipe = tiny_pipeline(tmp_path / "model")
    with pytest.raises(ValueError, match="unknown task"):
        evaluate("x2m", tiny_evaluator, synthetic_263(8, 0), PipelineGenerator(pipe, SMALL), SMALL, progress=False)
    with pytest.raises(ValueError, match="usable clips"):
        evaluate("t2m", tiny_evaluator, synthetic_263(8, 0)[:1], PipelineGenerator(pipe, SMALL), SMALL,
                 progress=False)
    unlabelled = synthetic_263(8, 0)
    for c in unlabelled:
        c.action = None
    with pytest.raises(ValueError, match="no clip"):
        evaluate("a2m", tiny_evaluator, unlabelled, PipelineGenerator(pipe, SMALL), SMALL, progress=False)


def test_mirror_side_accuracy_compares_own_and_mirrored_sided_captions():
    from types import SimpleNamespace

    from mld_core.eval.train import mirror_side_accuracy

    # motion "side" is encoded in feature 0 (+1 left, -1 right); texts map to +-1 in the same axis
    def clip(cid, side, text):
        return Clip(cid, np.full((10, 2), side, np.float32), [Caption(text)], None)

    clips = [clip("a", 1.0, "raise the left hand"), clip("Ma", -1.0, "raise the right hand"),
             clip("b", -1.0, "turn right"), clip("Mb", 1.0, "turn left"),
             clip("c", 1.0, "walk forward"), clip("Mc", 1.0, "walk forward")]  # unsided: skipped
    vec = {"raise the left hand": [1.0, 0.0], "raise the right hand": [-1.0, 0.0], "turn right": [-1.0, 0.0],
           "turn left": [1.0, 0.0]}
    stub = SimpleNamespace(config=SimpleNamespace(max_frames=196),
                           encode_pooled_text=lambda v: np.asarray(v),
                           encode_motion=lambda ms: np.array([[m[0, 0], 0.0] for m in ms]))
    lookup = lambda texts: np.array([vec[t] for t in texts])  # noqa: E731
    assert mirror_side_accuracy(stub, clips, lookup) == (1.0, 4)
    # an evaluator that swaps sides scores 0
    swapped = SimpleNamespace(**{**vars(stub), "encode_motion": lambda ms: np.array([[-m[0, 0], 0.0] for m in ms])})
    assert mirror_side_accuracy(swapped, clips, lookup) == (0.0, 4)
    assert mirror_side_accuracy(stub, clips[4:], lookup) is None


# ----------------------------------------------------------------------------------------------- CLI


def write_h3d_folder(root, clips_by_split: dict) -> None:
    """A HumanML3D-format folder: new_joint_vecs/, texts/, split lists, Mean/Std, actions.json."""
    (root / "new_joint_vecs").mkdir(parents=True)
    (root / "texts").mkdir()
    every = [c for clips in clips_by_split.values() for c in clips]
    for split, clips in clips_by_split.items():
        (root / f"{split}.txt").write_text("".join(f"{c.id}\n" for c in clips))
    for c in every:
        np.save(root / "new_joint_vecs" / f"{c.id}.npy", c.features)
        (root / "texts" / f"{c.id}.txt").write_text(
            "".join(f"{cap.text}#a/DET#{cap.start_s}#{cap.end_s}\n" for cap in c.captions))
    feats = np.concatenate([c.features for c in every])
    np.save(root / "Mean.npy", feats.mean(0).astype(np.float32))
    np.save(root / "Std.npy", (feats.std(0) + 1e-3).astype(np.float32))
    (root / "actions.json").write_text(json.dumps({"classes": list(CONTENTS), "clips": {c.id: c.action for c in every}}))


def test_cli_train_evaluator_then_evaluate_t2m_and_vae(tmp_path, capsys):
    from mld_core.cli import main
    from mld_core.testing import tiny_model

    data = tmp_path / "data"
    clips = synthetic_263(40, 3)
    write_h3d_folder(data, {"train": clips[:24], "val": clips[24:32], "test": clips[32:]})
    spec = json.dumps(TINY_TEXT)
    argv = ["train", "evaluator", "--data", str(data), "--out", str(tmp_path / "ev"), "--epochs", "2",
            "--hidden", "32", "--layers", "1", "--batch-size", "8", "--text-encoder", spec, "--no-progress"]
    assert main(argv) == 0
    assert (tmp_path / "ev" / "EVALUATOR_CARD.md").is_file()
    assert main(argv) == 2  # refuses to overwrite the run
    assert "--resume" in capsys.readouterr().err
    model = tiny_model(tmp_path / "model")
    out_json = tmp_path / "res" / "t2m.json"
    argv = ["evaluate", "t2m", "--model", str(model), "--data", str(data), "--evaluator", str(tmp_path / "ev"),
            "--replications", "2", "--mm-texts", "2", "--mm-repeats", "10", "--json", str(out_json), "--no-progress"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "| Real" in printed and "| tiny-text" in printed and "R@1" in printed
    result = json.loads(out_json.read_text())
    assert result["task"] == "t2m" and result["pairs_per_replication"] == 8
    assert len(result["rows"]["tiny-text"]["FID"]["values"]) == 2
    assert main(["evaluate", "vae"] + argv[2:-3] + ["--no-progress"]) == 0
    assert "MPJPE" in capsys.readouterr().out


def test_cli_evaluate_reports_user_errors(tmp_path, capsys):
    from mld_core.cli import main
    from mld_core.testing import tiny_model

    assert main(["evaluate", "t2m", "--data", str(tmp_path / "nowhere")]) == 2
    assert "no such folder" in capsys.readouterr().err
    data = tmp_path / "data"
    write_h3d_folder(data, {"train": synthetic_263(4, 0), "test": synthetic_263(4, 1)})
    assert main(["evaluate", "t2m", "--data", str(data), "--evaluator", str(tmp_path / "none")]) == 2
    assert "not an evaluator folder" in capsys.readouterr().err
    ev = tmp_path / "ev"
    Evaluator(tiny_config(dim=263)).save_pretrained(ev)
    action_model = tiny_model(tmp_path / "am", cond="action", actions=CONTENTS)
    assert main(["evaluate", "t2m", "--model", str(action_model), "--data", str(data), "--evaluator", str(ev)]) == 2
    assert "not text" in capsys.readouterr().err
    assert main(["train", "evaluator", "--data", str(data), "--out", str(tmp_path / "x"),
                 "--text-encoder", "{bad"]) == 2
    assert "not valid JSON" in capsys.readouterr().err


def test_bundled_evaluator_loads_and_embeds_a_real_motion(fixtures):
    model = Evaluator.from_pretrained()  # mld_core/weights/evaluator
    assert model.config.feature_dim == 263 and model.config.num_actions == 24
    assert model.config.text_encoder["kind"] == "minilm"
    feats = np.load(fixtures / "humanml3d" / "new_joint_vecs_012314.npy").astype(np.float32)
    emb = model.encode_motion([feats[:196], feats[:60]])
    assert emb.shape == (2, model.config.embed_dim)
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-4)
    np.testing.assert_allclose(model.encode_motion([feats[:60]])[0], emb[1], atol=1e-5)  # alone == batched
    logits = model.classify([feats[:196]])
    assert logits.shape == (1, 24) and np.isfinite(logits).all()
