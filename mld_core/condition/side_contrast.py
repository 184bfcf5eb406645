"""Side contrast: push the sentence vector of a prompt that names a side away from its mirrored wording's.

Why (docs/evaluation.md, "Side contrast"): a prompt's side lives in a small part of its sentence vector, and on a
few seeds the denoiser turns the other way ("turns to the right" taken left on 7 of 512 fresh caption takes of v3.7).
The difference between the prompt's vector and that of the same prompt with left and right swapped
(``mld_core.motion.features.mirror_text``) is that side part alone; adding a share of it makes the side louder:

    p' = normalize(p + weight * (p - p_mirrored))

Config ``side_contrast`` (a number in 0..2; 0: off) sets the weight. Prompts naming no side are not touched.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

MAX_WEIGHT = 2.0


def check_weight(weight) -> None:
    if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not 0 <= weight <= MAX_WEIGHT:
        raise ValueError(f"side_contrast must be a number in 0..{MAX_WEIGHT:g}, got {weight!r}")


def contrasted(pooled: torch.Tensor, mirrored: torch.Tensor, weight: float) -> torch.Tensor:
    """Sentence vectors ``pooled`` (B, D) moved by ``weight`` x (``pooled`` - ``mirrored``, the mirrored prompts'
    vectors (B, D)), unit length, in ``pooled``'s dtype."""
    if weight == 0:
        return pooled
    p = pooled.float()
    return F.normalize(p + weight * (p - mirrored.float()), dim=-1).to(pooled.dtype)
