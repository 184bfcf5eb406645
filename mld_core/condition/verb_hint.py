"""The checked verb a prompt names, as the id a verb-hinted text denoiser reads beside the sentence.

The same rule labels the training captions and the prompts (``mld_core.data.verbs.verbs_in``, its first verb), so
"a person hops over a puddle" is read as a jump whichever words ask for it. Id 0: no verb the model reads is named.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from mld_core.data.verbs import verbs_in

NO_VERB = 0


def verb_id(text: str, verbs: Sequence[str]) -> int:
    """1 + the index in ``verbs`` of the first of ``verbs`` that ``text`` asks for; ``NO_VERB`` if none."""
    for verb in verbs_in(text):
        if verb in verbs:
            return 1 + list(verbs).index(verb)
    return NO_VERB


def verb_ids(texts: Sequence[str], verbs: Sequence[str], device=None) -> torch.Tensor:
    """``verb_id`` of each text: (B,) long."""
    return torch.tensor([verb_id(t, verbs) for t in texts], dtype=torch.long, device=device)
