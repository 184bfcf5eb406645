"""Which rows of a text call a verb denoiser guides, and with which of its labels.

A verb denoiser is an action-conditioned denoiser trained on the same latents as the model's text denoiser. When a
prompt names one of its labels by a checked verb (the words of ``mld_core.data.verbs``, the table that labels the
training captions), the Final sampler adds that label's guidance to the sentence's (``mld_core.sampling.VerbGuidance``):
the sentence still says how, the label says what. A prompt naming several is guided by the one it names first ("stands
up from sitting on the ground": stand up). Prompts that name no label are sampled as without it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from mld_core.data.verbs import VERBS, verbs_in_order
from mld_core.models.denoiser import LatentDenoiser


@dataclass
class VerbGuide:
    """An action-conditioned ``denoiser`` whose labels are ``actions``, guiding at ``scale``."""

    denoiser: LatentDenoiser
    actions: list
    scale: float

    @property
    def verbs(self) -> list:
        """The checked verbs that are labels of the verb denoiser."""
        return [v for v in VERBS if v in self.actions]

    def rows_and_labels(self, prompts: Sequence[str], device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(rows, label ids), each (B',) long: the prompts that name one of the labels' verbs, and that label."""
        named = [[v for v in verbs_in_order(p) if v in self.actions] for p in prompts]
        rows = [i for i, verbs in enumerate(named) if verbs]
        labels = [self.actions.index(named[i][0]) for i in rows]
        return (torch.tensor(rows, dtype=torch.long, device=device),
                torch.tensor(labels, dtype=torch.long, device=device))
