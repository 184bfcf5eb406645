"""A prompt's text condition: the text encoder's embedding of it, with its sentence vector moved by the model's
conditioning tricks, in this order:

0. a bare command worded as the captions word a motion (``wording.py``, config ``commands_as_sentences``): "jump" is
   encoded as "a person jumps";
1. the content anchor (``content_anchor.py``, config ``content_anchor``): towards the content a classifier reads in it;
2. the side contrast (``side_contrast.py``, config ``side_contrast``): away from its mirrored wording's, when it names
   a side.

Each prompt is encoded once per text encoder and kept (:class:`TextCache`): re-generating a prompt with other seconds
or seeds, as the live preview does, skips the text encoder. A new conditioning trick is one more function here,
called in :func:`encode`, with its setting in the model's config.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Callable

import torch

from mld_core.condition import side_contrast, wording
from mld_core.condition.coverage import normalise
from mld_core.motion.features import mirror_text


def encode(prompts: list, encoder, config, anchor=None, coverage_index=None):
    """``encoder``'s embeddings of ``prompts`` (a TextEmbedding, one row per prompt) with their sentence vectors
    anchored and then side-contrasted, bare commands first worded as sentences. ``config``: the model's
    (``commands_as_sentences``, ``content_anchor`` and ``side_contrast`` are read); ``anchor``: its ContentAnchor
    (None: none); ``coverage_index``: its CoverageIndex (the anchor's ramp reads it)."""
    def anchored(texts: list, emb):
        return anchor_vectors(texts, emb, encoder, config.content_anchor, anchor, coverage_index)

    texts = [wording.as_sentence(p) for p in prompts] if config.commands_as_sentences else list(prompts)
    emb = anchored(texts, encoder(texts))
    return contrast_sides(texts, emb, lambda mirrored: anchored(mirrored, encoder(mirrored)).pooled,
                          config.side_contrast)


def anchor_vectors(prompts: list, emb, encoder, settings, anchor, coverage_index):
    """``emb`` (``encoder``'s embeddings of ``prompts``) with its pooled vectors moved by the content anchor, when the
    model has one and ``settings.weight`` (config ``content_anchor``) is above 0. The Draft's text encoder, distilled
    from the Final's, shares its vector space and so its anchor. Runs on the CPU."""
    if anchor is None or settings.weight == 0 or anchor.dim != emb.pooled.shape[-1]:
        return emb
    plain = encoder([normalise(p) or p for p in prompts]).pooled.float().cpu()
    plain = torch.nn.functional.normalize(plain, dim=-1)  # (B, D) the prompts without side and style words
    scores = None
    if settings.full_below is not None:  # from_pretrained made sure the folder has a coverage index
        scores = torch.from_numpy(coverage_index.nearest_scores(plain.numpy()))
    pooled = anchor.anchored(emb.pooled.cpu(), plain, settings.strengths(scores))
    return type(emb)(pooled.to(emb.pooled.device), emb.tokens, emb.mask)


def contrast_sides(prompts: list, emb, pooled_of: Callable[[list], torch.Tensor], weight: float):
    """``emb`` (the anchored embeddings of ``prompts``) with the pooled vector of each prompt that names a side pushed
    away from its mirrored wording's (``pooled_of(mirrored prompts)``: their anchored vectors (R, D)), when
    ``weight`` (config ``side_contrast``) is above 0."""
    if not weight:
        return emb
    mirrored = [mirror_text(p) for p in prompts]
    rows = [i for i, (p, m) in enumerate(zip(prompts, mirrored)) if p != m]
    if not rows:
        return emb
    mirrored_pooled = pooled_of([mirrored[i] for i in rows])  # (R, D)
    pooled = emb.pooled.clone()
    pooled[rows] = side_contrast.contrasted(emb.pooled[rows], mirrored_pooled, weight)
    return type(emb)(pooled, emb.tokens, emb.mask)


class TextCache(OrderedDict):
    """prompt -> its TextEmbedding (one row, its own tokens), the last ``SIZE`` prompts used."""

    SIZE = 256

    def embeddings(self, prompts: list, encode_new: Callable[[list], object]):
        """The embeddings of ``prompts`` (one row each), encoding with ``encode_new(prompts)`` only those not kept."""
        from mld_core.models.text_encoder import TextEmbedding

        rows = {p: self[p] for p in prompts if p in self}
        new = [p for p in dict.fromkeys(prompts) if p not in rows]
        if new:
            emb = encode_new(new)
            for i, p in enumerate(new):
                n = int(emb.mask[i].sum())
                rows[p] = TextEmbedding(emb.pooled[i:i + 1], emb.tokens[i:i + 1, :n], emb.mask[i:i + 1, :n])
        for p in dict.fromkeys(prompts):
            self[p] = rows[p]
            self.move_to_end(p)
        while len(self) > self.SIZE:
            self.popitem(last=False)
        return TextEmbedding.cat([rows[p] for p in prompts])
