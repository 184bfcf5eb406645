"""A prompt's text condition (mld_core.condition.text): the conditioning tricks in their order (the content anchor,
then the side contrast against the mirrored wording, itself anchored), and the cache that encodes each prompt once."""

from __future__ import annotations

from types import SimpleNamespace

import torch
import torch.nn.functional as F

from mld_core.condition import side_contrast
from mld_core.condition.content_anchor import ContentAnchorConfig
from mld_core.condition.text import TextCache, encode
from mld_core.models.text_encoder import TextEmbedding


class _Encoder:
    """A stand-in text encoder: a text's vector counts its letters and its side words; token rows as many as words."""

    def __init__(self):
        self.calls = []

    def __call__(self, texts):
        self.calls.append(list(texts))
        pooled = F.normalize(torch.tensor([[len(t), t.count("left"), t.count("right"), 1.0] for t in texts]), dim=-1)
        words = max(len(t.split()) for t in texts)
        mask = torch.tensor([[i < len(t.split()) for i in range(words)] for t in texts])
        return TextEmbedding(pooled, pooled[:, None, :].repeat(1, words, 1) * mask[..., None], mask)


class _Anchor:
    """A stand-in content anchor: every vector moved by ``strength`` towards the last axis."""

    dim = 4

    def anchored(self, pooled, plain, strength):
        return F.normalize(pooled + strength * torch.tensor([0.0, 0.0, 0.0, 1.0]), dim=-1)


def _config(anchor_weight: float, contrast: float):
    return SimpleNamespace(content_anchor=ContentAnchorConfig(weight=anchor_weight), side_contrast=contrast)


def test_the_anchor_comes_first_and_the_contrast_pushes_from_the_anchored_mirror():
    encoder, anchor = _Encoder(), _Anchor()
    prompts = ["a person turns left", "a person walks"]
    emb = encode(prompts, encoder, _config(0.5, 0.5), anchor)
    own = anchor.anchored(encoder(prompts).pooled, None, 0.5)  # (2, D)
    mirrored = anchor.anchored(encoder(["a person turns right"]).pooled, None, 0.5)  # (1, D)
    assert torch.allclose(emb.pooled[0], side_contrast.contrasted(own[:1], mirrored, 0.5)[0], atol=1e-6)
    assert torch.allclose(emb.pooled[1], own[1], atol=1e-6)  # no side named: anchored only
    assert torch.equal(emb.tokens, encoder(prompts).tokens)  # the tricks move the sentence vector only
    plain = encode(prompts, encoder, _config(0.0, 0.0), anchor)
    assert torch.equal(plain.pooled, encoder(prompts).pooled)  # both off: the encoder's own vectors
    assert not torch.allclose(encode(prompts, encoder, _config(0.0, 0.5), anchor).pooled[0], emb.pooled[0])


def test_the_cache_encodes_each_prompt_once_and_keeps_the_last_ones():
    encoder, cache = _Encoder(), TextCache()
    first = cache.embeddings(["a walk", "a long slow walk", "a walk"], encoder)
    assert encoder.calls == [["a walk", "a long slow walk"]]  # one row per prompt, duplicates encoded once
    assert [int(m.sum()) for m in first.mask] == [2, 4, 2] and first.tokens.shape[:2] == (3, 4)
    again = cache.embeddings(["a long slow walk", "a run"], encoder)
    assert encoder.calls[1:] == [["a run"]]
    assert torch.equal(again.pooled[0], first.pooled[1])
    cache.SIZE = 2
    cache.embeddings(["a jump"], encoder)
    assert list(cache) == ["a run", "a jump"]  # the least recently used went
