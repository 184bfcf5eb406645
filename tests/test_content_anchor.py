"""The content anchor (mld_core.condition.content_anchor): fitting, moving a prompt's vector, files, and the
pipeline's use."""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F
from safetensors import safe_open

from mld_core.condition import content_anchor
from mld_core.checkpoint import CheckpointError, load_config, save_json
from mld_core.models.text_encoder import load_text_encoder
from mld_core.testing import TINY_TEXT_ENCODER, tiny_model

TEXTS = ["a person walks forward", "someone walks ahead", "a man walks forward slowly",
         "a person waves the left hand", "someone waves the right hand", "a woman waves her left hand",
         "a person bows", "someone bows deeply", "the man bows"]
LABELS = ["walk"] * 3 + ["wave-left-hand", "wave-right-hand", "wave-left-hand"] + ["bow"] * 3


@pytest.fixture(scope="module")
def tiny_encoder():
    return load_text_encoder(TINY_TEXT_ENCODER)


@pytest.fixture(scope="module")
def anchor(tiny_encoder):
    return content_anchor.fit(TEXTS, LABELS, tiny_encoder, steps=300, seed=0)


def test_side_free_label():
    assert content_anchor.side_free_label("walk-turn-left") == "walk-turn-side"
    assert content_anchor.side_free_label("raise-up-right-hand") == "raise-up-side-hand"
    assert content_anchor.side_free_label("wave-both-hands") == "wave-both-hands"


def test_fit_reads_its_training_captions_without_their_sides(anchor, tiny_encoder):
    assert anchor.classes == ["bow", "walk", "wave-side-hand"]
    plain = torch.from_numpy(content_anchor.encode_plain(tiny_encoder, TEXTS))
    predicted = [anchor.classes[i] for i in anchor.probabilities(plain).argmax(-1).tolist()]
    assert predicted == [content_anchor.side_free_label(label) for label in LABELS]
    assert torch.allclose(anchor.centroids.norm(dim=-1), torch.ones(3), atol=1e-5)


def test_fit_is_deterministic_for_a_seed(tiny_encoder, anchor):
    again = content_anchor.fit(TEXTS, LABELS, tiny_encoder, steps=300, seed=0)
    assert torch.equal(again.weight, anchor.weight) and torch.equal(again.centroids, anchor.centroids)
    with pytest.raises(ValueError, match="no labelled captions"):
        content_anchor.fit(["a person walks"], [""], tiny_encoder)


def test_anchored_moves_towards_the_classified_centroid_and_keeps_the_offset(anchor):
    gen = torch.Generator().manual_seed(1)
    plain = F.normalize(torch.randn(4, anchor.dim, generator=gen), dim=-1)
    side = 0.2 * F.normalize(torch.randn(4, anchor.dim, generator=gen), dim=-1)  # what side/style words add
    pooled = F.normalize(plain + side, dim=-1)
    assert torch.equal(anchor.anchored(pooled, plain, 0.0), pooled)  # off: untouched
    moved = anchor.anchored(pooled, plain, 1.0)
    assert torch.allclose(moved.norm(dim=-1), torch.ones(4), atol=1e-5)
    target = anchor.probabilities(plain) @ anchor.centroids
    assert (F.cosine_similarity(moved, target) > F.cosine_similarity(pooled, target)).all()
    # Two prompts that differ only in their side words keep that difference (up to the final normalisation).
    expected = F.normalize(pooled + (target - plain), dim=-1)
    assert torch.allclose(moved, expected, atol=1e-6)
    # A prompt already at its content's centroid, classified with certainty, does not move.
    certain = content_anchor.ContentAnchor(["a", "b"], torch.tensor([[50.0, 0.0], [-50.0, 0.0]]), torch.zeros(2),
                                           torch.tensor([[1.0, 0.0], [0.0, 1.0]]))
    at_centroid = torch.tensor([[1.0, 0.0]])
    assert torch.allclose(certain.anchored(at_centroid, at_centroid, 1.0), at_centroid, atol=1e-6)


def test_pinned_numbers(anchor):
    plain = F.normalize(torch.arange(anchor.dim, dtype=torch.float32)[None] - 15.5, dim=-1)
    probs = anchor.probabilities(plain)[0]
    assert probs.sum().item() == pytest.approx(1.0, abs=1e-6)
    assert probs.tolist() == pytest.approx([0.2979, 0.7019, 0.0001], abs=2e-3)


def test_save_load_parity_and_a_corrupt_file(anchor, tmp_path):
    path = anchor.save(tmp_path / content_anchor.FILE_NAME)
    loaded = content_anchor.ContentAnchor.load(path)
    assert loaded.classes == anchor.classes
    for name in ("weight", "bias", "centroids"):  # kept as fp16, like the weights; computed in fp32
        assert getattr(loaded, name).dtype == torch.float32
        assert torch.equal(getattr(loaded, name), getattr(anchor, name).half().float())
    with safe_open(str(path), framework="pt") as f:
        assert {f.get_tensor(k).dtype for k in f.keys()} == {torch.float16}
    path.write_bytes(b"not safetensors")
    with pytest.raises(ValueError, match="cannot read the content anchor"):
        content_anchor.ContentAnchor.load(path)


def _anchored_model(tmp_path, anchor, strength, full_below=None, index_captions=()):
    from mld_core.condition import coverage
    from mld_core.pipeline import MLDPipeline

    folder = tiny_model(tmp_path / f"m{strength}-{full_below}", draft=True)
    anchor.save(folder / content_anchor.FILE_NAME)
    if index_captions:
        coverage.build_index(list(index_captions), ["walk"] * len(index_captions),
                             load_text_encoder(TINY_TEXT_ENCODER)).save(folder / coverage.INDEX_NAME)
    config = load_config(folder)
    config.content_anchor = content_anchor.ContentAnchorConfig(strength, full_below)
    save_json(folder / "config.json", config.to_dict())
    return MLDPipeline.from_pretrained(folder)


def test_pipeline_anchors_the_final_prompts(tmp_path, anchor):
    off, on = _anchored_model(tmp_path, anchor, 0.0), _anchored_model(tmp_path, anchor, 1.0)
    prompts = ["a person walks forward", "someone waves the left hand"]
    plain_rows, anchored_rows = off.text_embeddings(prompts), on.text_embeddings(prompts)
    assert torch.equal(plain_rows.tokens, anchored_rows.tokens)  # the anchor moves the sentence vector only
    assert not torch.allclose(plain_rows.pooled, anchored_rows.pooled)
    on.clear_text_cache()
    single = on.text_embeddings(prompts[1:])
    assert torch.allclose(single.pooled, anchored_rows.pooled[1:], atol=1e-6)  # batch equals single
    draft_off, draft_on = off.text_embeddings(prompts, draft=True), on.text_embeddings(prompts, draft=True)
    assert not torch.allclose(draft_off.pooled, draft_on.pooled)  # the Draft's prompts are anchored too
    a = on(prompts[:1], 2.0, seed=3).features
    b = off(prompts[:1], 2.0, seed=3).features
    assert a.shape == b.shape and not (a == b).all()


def test_a_prompt_worded_as_a_training_caption_is_not_moved_with_the_ramp(tmp_path, anchor):
    caption, other = "a person walks forward", "someone waves the left hand"
    ramped = _anchored_model(tmp_path, anchor, 1.0, full_below=0.5, index_captions=[caption])
    off = _anchored_model(tmp_path, anchor, 0.0)
    rows_ramped, rows_off = ramped.text_embeddings([caption, other]), off.text_embeddings([caption, other])
    assert torch.allclose(rows_ramped.pooled[0], rows_off.pooled[0], atol=1e-6)  # score 1: weight 0
    assert not torch.allclose(rows_ramped.pooled[1], rows_off.pooled[1])


def test_ramp_strengths():
    ramp = content_anchor.ContentAnchorConfig(weight=1.0, full_below=0.9)
    got = ramp.strengths(torch.tensor([1.0, 0.95, 0.9, 0.5]))
    assert got.tolist() == pytest.approx([0.0, 0.5, 1.0, 1.0])
    assert content_anchor.ContentAnchorConfig(weight=0.5).strengths(torch.tensor([1.0])) == 0.5


def test_pipeline_refuses_a_weight_without_its_file_and_bad_settings(tmp_path):
    from mld_core.pipeline import MLDPipeline

    folder = tiny_model(tmp_path / "m")
    data = json.loads((folder / "config.json").read_text())
    data["content_anchor"] = {"weight": 1.0, "full_below": None}
    (folder / "config.json").write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match="no content_anchor.safetensors"):
        MLDPipeline.from_pretrained(folder)
    content_anchor.fit(TEXTS, LABELS, load_text_encoder(TINY_TEXT_ENCODER), steps=10).save(
        folder / content_anchor.FILE_NAME)
    data["content_anchor"] = {"weight": 1.0, "full_below": 0.9}
    (folder / "config.json").write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match="full_below needs the folder's coverage index"):
        MLDPipeline.from_pretrained(folder)
    for bad, message in [({"weight": "strong"}, "weight must be a number"),
                         ({"weight": 1.0, "full_below": 1.5}, "full_below must be null or a number"),
                         (1.0, "content_anchor must be a JSON object")]:
        data["content_anchor"] = bad
        (folder / "config.json").write_text(json.dumps(data))
        with pytest.raises((CheckpointError, ValueError), match=message):
            MLDPipeline.from_pretrained(folder)


def test_anchor_fitted_on_caption_templates_reads_other_wordings(minilm):
    """Fitted with the real sentence encoder on captions written as the data's (every content x style), the anchor
    calls wordings unlike those captions by their content."""
    from mld_core.data.captions import CONTENTS, STYLES, captions_for

    texts, labels = [], []
    for content in CONTENTS:
        for style in STYLES:
            caps = captions_for(content, style, f"clip_{content}_{style}", n=2)
            texts += caps
            labels += [content] * len(caps)
    anchor = content_anchor.fit(texts, labels, minilm, steps=800)
    prompts = ["the man backs up slowly", "someone greets a friend by waving the right hand", "someone runs forward",
               "a person bows"]
    plain = torch.from_numpy(content_anchor.encode_plain(minilm, prompts))
    read = [anchor.classes[i] for i in anchor.probabilities(plain).argmax(-1).tolist()]
    assert read == ["walk-back", "wave-side-hand", "run", "bow"]


def _caption_folder(root, labelled=True):
    (root / "texts").mkdir(parents=True)
    ids = []
    for i, (text, label) in enumerate(zip(TEXTS, LABELS)):
        cid = f"clip{i}"
        ids.append(cid)
        (root / "texts" / f"{cid}.txt").write_text(f"{text}#{text}#0.0#0.0\n")
    (root / "train.txt").write_text("\n".join(ids) + "\n")
    if labelled:
        (root / "actions.json").write_text(json.dumps({"classes": sorted(set(LABELS)),
                                                       "clips": {f"clip{i}": l for i, l in enumerate(LABELS)}}))
    return root


def test_build_script_writes_the_anchor_and_its_settings(tmp_path, capsys):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    from build_content_anchor import main

    data, model = _caption_folder(tmp_path / "data"), tiny_model(tmp_path / "model")
    before = (model / "config.json").read_text()
    assert main(["--data", str(data), "--model", str(model), "--weight", "3"]) == 2
    assert "content_anchor.weight must be a number in 0..2" in capsys.readouterr().err
    assert not (model / content_anchor.FILE_NAME).exists() and (model / "config.json").read_text() == before
    for bad, message in [(["--full-below", "0.9"], "--full-below needs --weight"),
                         (["--rewordings", "-1"], "--rewordings must be between 0 and 20"),
                         (["--weight", "nan"], "content_anchor.weight must be a number"),
                         (["--weight", "1", "--full-below", "1"], "full_below must be null or a number")]:
        assert main(["--data", str(data), "--model", str(model)] + bad) == 2
        assert message in capsys.readouterr().err
    assert main(["--data", str(tmp_path / "missing"), "--model", str(model)]) == 2
    assert "has no train.txt" in capsys.readouterr().err
    assert main(["--data", str(data), "--model", str(tmp_path / "missing")]) == 2
    assert "model folder not found" in capsys.readouterr().err
    assert not (model / content_anchor.FILE_NAME).exists() and (model / "config.json").read_text() == before
    unlabelled = _caption_folder(tmp_path / "unlabelled", labelled=False)
    assert main(["--data", str(unlabelled), "--model", str(model)]) == 2
    assert "has no content labels" in capsys.readouterr().err
    assert main(["--data", str(data), "--model", str(model), "--weight", "1.0", "--full-below", "0.9",
                 "--rewordings", "1"]) == 0
    anchor = content_anchor.load_for_model(model)
    assert anchor.classes == ["bow", "walk", "wave-side-hand"]
    assert load_config(model).content_anchor == content_anchor.ContentAnchorConfig(1.0, 0.9)
    built = load_config(model).provenance["content_anchor_build"]  # how the file was made, beside the weights' runs
    assert (built["rewordings"], built["contents"], built["steps"], built["seed"]) == (1, 3, 1500, 0)
