"""Side contrast (mld_core.condition.side_contrast): the vector math, its setting, and the pipeline's use."""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F

from mld_core.condition import side_contrast
from mld_core.checkpoint import CheckpointError, load_config, save_json
from mld_core.testing import tiny_model


def test_contrasted_moves_away_from_the_mirrored_vector_and_stays_unit():
    p = F.normalize(torch.tensor([[1.0, 0.2, 0.0], [0.0, 1.0, 1.0]]), dim=-1)
    m = F.normalize(torch.tensor([[1.0, -0.2, 0.0], [0.0, 1.0, 1.0]]), dim=-1)  # row 1: a prompt equal to its mirror
    assert side_contrast.contrasted(p, m, 0.0) is p  # off: untouched
    out = side_contrast.contrasted(p, m, 0.5)
    assert torch.allclose(out.norm(dim=-1), torch.ones(2), atol=1e-6)
    assert (out[0] @ m[0]) < (p[0] @ m[0])  # further from the other side
    assert torch.allclose(out[1], p[1], atol=1e-6)  # no side part, no move
    # p = (0.9806, 0.1961), p - m = (0, 0.3922): p + 0.5 (p - m) = (0.9806, 0.3922), then unit length
    assert out[0].tolist() == pytest.approx([0.9285, 0.3714, 0.0], abs=1e-4)
    half = side_contrast.contrasted(p.half(), m.half(), 0.5)
    assert half.dtype == torch.float16


@pytest.mark.parametrize("bad", [-0.1, 2.5, float("nan"), True, "0.5", None])
def test_the_setting_is_checked(tmp_path, bad):
    folder = tiny_model(tmp_path / "m")
    data = json.loads((folder / "config.json").read_text())
    data["side_contrast"] = bad
    (folder / "config.json").write_text(json.dumps(data))
    with pytest.raises((CheckpointError, ValueError), match="side_contrast must be a number in 0..2"):
        load_config(folder)


def _model(tmp_path, weight):
    from mld_core.pipeline import MLDPipeline

    folder = tiny_model(tmp_path / f"m{weight}", draft=True)
    config = load_config(folder)
    config.side_contrast = weight
    save_json(folder / "config.json", config.to_dict())
    return MLDPipeline.from_pretrained(folder)


def test_pipeline_contrasts_only_sided_prompts_final_and_draft(tmp_path):
    off, on = _model(tmp_path, 0.0), _model(tmp_path, 0.5)
    assert load_config(tmp_path / "m0.0").side_contrast == 0.0 and on.config.side_contrast == 0.5
    prompts = ["a person walks forward", "someone waves the left hand", "a person turns right"]
    plain, moved = off.text_embeddings(prompts), on.text_embeddings(prompts)
    assert torch.equal(plain.tokens, moved.tokens)  # the sentence vector only
    assert torch.equal(plain.pooled[0], moved.pooled[0])  # no side named: untouched
    for r in (1, 2):
        assert not torch.allclose(plain.pooled[r], moved.pooled[r])
    mirrored = off.text_embeddings(["someone waves the right hand"]).pooled[0]
    expected = side_contrast.contrasted(plain.pooled[1:2], mirrored[None], 0.5)[0]
    assert torch.allclose(moved.pooled[1], expected, atol=1e-6)
    on.clear_text_cache()
    assert torch.allclose(on.text_embeddings(prompts[2:]).pooled, moved.pooled[2:], atol=1e-6)  # batch = single
    draft_plain, draft_moved = off.text_embeddings(prompts, draft=True), on.text_embeddings(prompts, draft=True)
    assert torch.equal(draft_plain.pooled[0], draft_moved.pooled[0])
    assert not torch.allclose(draft_plain.pooled[1], draft_moved.pooled[1])  # the Draft's sided prompts too
    a, b = on(prompts[1:2], 2.0, seed=3).features, off(prompts[1:2], 2.0, seed=3).features
    assert a.shape == b.shape and not (a == b).all()
