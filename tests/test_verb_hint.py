"""Verb hints: the checked verb a prompt names, read by a text denoiser beside the sentence (tiny seeded models)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from mld_core.checkpoint import load_config, save_model
from mld_core.cli import main
from mld_core.condition.verb_hint import NO_VERB, verb_id, verb_ids
from mld_core.data.verbs import VERBS
from mld_core.models.denoiser import DenoiserConfig, LatentDenoiser, with_condition, with_verb_hints
from mld_core.models.text_encoder import TextEmbedding
from mld_core.models.transformer import TransformerConfig
from mld_core.pipeline import MLDPipeline
from mld_core.testing import tiny_config

BLOCK = TransformerConfig(dim=32, heads=2, ff_dim=64, layers=1, dropout=0.0)


def _text(B: int = 3, seed: int = 0) -> TextEmbedding:
    g = torch.Generator().manual_seed(seed)
    return TextEmbedding(pooled=torch.randn(B, 24, generator=g), tokens=torch.randn(B, 5, 24, generator=g),
                         mask=torch.ones(B, 5, dtype=torch.bool))


def _text_denoiser(seed: int = 0) -> LatentDenoiser:
    torch.manual_seed(seed)
    return LatentDenoiser(DenoiserConfig(latent_tokens=2, latent_dim=16, text_dim=24, text_pool_tokens=2,
                                         transformer=BLOCK)).eval()


def test_a_prompt_is_read_as_the_first_hinted_verb_it_names_by_any_of_its_words():
    verbs = ["jump", "kick", "throw"]
    assert verb_id("a person hops over a puddle", verbs) == 1
    assert verb_id("someone KICKS a ball", verbs) == 2
    assert verb_id("a man jumps, then kicks", verbs) == 1  # the table's order, as the training labels take it
    assert verb_id("a person waves", verbs) == NO_VERB
    assert verb_id("a person sits down", verbs) == NO_VERB  # get_low is named, but not a verb this model reads
    assert verb_id("a person sits down", VERBS) == 1 + VERBS.index("get_low")
    assert verb_ids(["jump", "walk", "toss a ball"], verbs).tolist() == [1, 0, 3]


def test_hints_start_at_zero_so_a_warm_start_makes_what_its_text_denoiser_makes():
    """with_verb_hints: every weight carried over and the hint vectors zero, so each verb id gives the plain text
    condition; a trained hint moves the first condition token only, and only for prompts naming its verb; hints of
    a verb the source already read are kept when carried to another list."""
    text, emb = _text_denoiser(), _text()
    hinted = with_verb_hints(text, ["jump", "kick"]).eval()
    plain = text.condition_tokens(3, text=emb)
    for ids in ([0, 0, 0], [1, 2, 0]):
        assert torch.equal(hinted.condition_tokens(3, text=emb, verbs=torch.tensor(ids)), plain)
    with torch.no_grad():
        hinted.verb_embedding.weight[2] = 1.0  # kick
    cond = hinted.condition_tokens(3, text=emb, verbs=torch.tensor([1, 2, 0]))
    assert torch.equal(cond[[0, 2]], plain[[0, 2]]) and torch.equal(cond[1, 1:], plain[1, 1:])
    assert torch.allclose(cond[1, 0], plain[1, 0] + 1.0)
    assert torch.equal(hinted.condition_tokens(3, text=emb), plain)  # no ids: no verb named
    dropped = hinted.condition_tokens(3, text=emb, verbs=torch.tensor([2, 2, 2]), drop=torch.tensor([True] * 3))
    assert torch.equal(dropped, hinted.null_tokens(3))  # the guidance branch has no hint either
    carried = with_verb_hints(hinted, ["kick", "throw"])
    assert torch.equal(carried.verb_embedding.weight[1], hinted.verb_embedding.weight[2])
    assert not carried.verb_embedding.weight[2].any() and not carried.verb_embedding.weight[0].any()
    assert not any(k.startswith("verb_embedding") for k in with_verb_hints(hinted, []).state_dict())


def test_hints_are_a_text_denoisers_only_and_not_carried_to_an_action_one():
    with pytest.raises(ValueError, match="text-conditioned"):
        DenoiserConfig(cond="action", num_actions=2, verb_hints=["jump"])
    hinted = with_verb_hints(_text_denoiser(), ["jump"])
    action = with_condition(hinted, DenoiserConfig(**{**hinted.config.to_dict(), "cond": "action", "num_actions": 2,
                                                      "verb_hints": []}))
    assert not any(k.startswith("verb_embedding") for k in action.state_dict())


def test_a_hinted_model_saves_loads_and_the_pipeline_gives_its_denoiser_the_prompts_verbs(tmp_path):
    """The config keeps the hinted verbs in order; the pipeline's condition for a prompt naming one carries its
    vector, a prompt naming none gets the plain text condition; batched prompts equal single ones."""
    config = tiny_config()
    config.denoiser.verb_hints = ["jump", "kick"]
    torch.manual_seed(0)
    from mld_core.models.vae import MotionVAE

    den = LatentDenoiser(config.denoiser)
    with torch.no_grad():
        den.verb_embedding.weight[1:] = torch.randn(2, 32)
    folder = save_model(tmp_path / "m", config, MotionVAE(config.vae), den, card="# tiny\n")
    assert load_config(folder).denoiser.verb_hints == ["jump", "kick"]
    pipe = MLDPipeline.from_pretrained(folder)
    prompts = ["a person hops in place", "a person kicks", "a person waves"]
    cond, _ = pipe._condition(prompts, None, "text", pipe.denoiser)
    emb = pipe.text_embeddings(prompts)
    plain = pipe.denoiser.condition_tokens(3, text=emb)
    hints = pipe.denoiser.verb_embedding.weight.detach()
    assert torch.allclose(cond[0, 0], plain[0, 0] + hints[1], atol=1e-5)
    assert torch.allclose(cond[1, 0], plain[1, 0] + hints[2], atol=1e-5)
    assert torch.equal(cond[2], plain[2]) and torch.equal(cond[:, 1:], plain[:, 1:])
    batch = pipe(prompts, seconds=1.5, seed=3, num_inference_steps=2).joints
    single = pipe(prompts[1], seconds=1.5, seed=3, num_inference_steps=2).joints
    assert np.allclose(batch[1], single[0], atol=1e-4)


def test_a_draft_is_not_distilled_from_a_hinted_teacher(tmp_path):
    from mld_core.training.draft import DraftTrainConfig, train_draft

    config = tiny_config()
    config.denoiser.verb_hints = ["jump"]
    from mld_core.models.vae import MotionVAE

    folder = save_model(tmp_path / "m", config, MotionVAE(config.vae), LatentDenoiser(config.denoiser), card="#\n")
    with pytest.raises(ValueError, match="verb hints"):
        train_draft(DraftTrainConfig(data=str(tmp_path), teacher=str(folder), out=str(tmp_path / "d"), steps=1))


def test_the_hint_vectors_train_at_their_own_rate():
    """parameter_groups: a hinted denoiser's verb vectors in a group of their own that set_lr scales; one group for
    a plain text denoiser."""
    from mld_core.training.common import set_lr
    from mld_core.training.denoiser import parameter_groups

    plain = _text_denoiser()
    assert len(parameter_groups(plain, list(plain.parameters()), 30.0)) == 1
    hinted = with_verb_hints(plain, ["jump"])
    groups = parameter_groups(hinted, list(hinted.parameters()), 30.0)
    assert [len(g["params"]) for g in groups] == [len(list(plain.parameters())), 1]
    opt = torch.optim.AdamW(groups, lr=1e-4)
    set_lr(opt, 2e-4)
    assert [g["lr"] for g in opt.param_groups] == pytest.approx([2e-4, 6e-3])
