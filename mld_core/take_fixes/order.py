"""The order in which a call's takes are decoded and fixed (:func:`fixes_for`), and the takes each fix reads and
returns (:class:`Takes`).

1. stepping (``stepping.py``): a Final take's z_0 refined until its feet step;
2. constraints (``meet_constraints.py``): z_0 and then the features refined until they are met; this is how a
   directed take is decoded. A free take is decoded as it is (:class:`Decode`), x = D(z_0);
3. repair (``repair.py``): a free take's features with one skeleton and planted feet;
4. side redraw (``side_redraw.py``): a free take that misses the side its prompt names is drawn again;
5. verb redraw (``verb_redraw.py``): a free take that does not show the checked verbs its prompt names is drawn
   again.

Each fix is a small object with its settings, ``apply(takes, decoder) -> Takes`` and the timing keys it fills.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, ClassVar

import numpy as np
import torch

from mld_core.take_fixes.meet_constraints import MeetConstraints
from mld_core.take_fixes.repair import Repair
from mld_core.take_fixes.side_redraw import SideRedraw
from mld_core.take_fixes.stepping import Stepping
from mld_core.take_fixes.verb_redraw import VerbRedraw


@dataclass
class Takes:
    """One call's rows between sampling and output."""

    latents: torch.Tensor  # (B, n, d) z_0 as fixed so far
    sampled: torch.Tensor  # (B, n, d) z_0 as sampled
    lengths: torch.Tensor  # (B,) frames
    prompts: list  # per row (a side redraw reads the side they name)
    draws: list  # per row, which z_T of its seed the take is
    draft: bool = False  # sampled by the Draft: decoded by its decoder
    stepped: bool = False  # stepping refined the latents (the constraints then weigh the feet's slide)
    features: np.ndarray | None = None  # (B, T, F) denormalised, zero beyond each length; None until decoded
    joints: np.ndarray | None = None  # (B, T, 22, 3); None until a fix needs them (else made at the output)
    redrawn_for: list | None = None  # per row, as MLDOutput.redrawn_for ("side", "verb", either + " missed", "")


class Decode:
    """A free take's decode, x = D(z_0)."""

    timings: ClassVar[tuple] = ("decode_s",)

    def apply(self, takes: Takes, decoder) -> Takes:
        return replace(takes, features=decoder.features(takes.latents, takes.lengths, takes.draft))


def fixes_for(config, *, draft: bool, step: bool, repair: bool, constraints, side_redraws: int,
              redo: Callable, verb_redraws: int = 0, draw: int = 0) -> list:
    """The decode and the fixes of one call, in order, each only where it applies. ``config``: the model's (its
    ``stepping``, ``repair`` and feature size); ``step``, ``repair``: the call's; ``constraints``: a Constraints or
    None; ``side_redraws``, ``verb_redraws``: at most this many more draws per row for each (0 for a model not
    conditioned on text); ``redo``: see SideRedraw; ``draw``: the call's draw, the one its takes start from."""
    fixes = []
    if step and not draft and config.stepping.steps > 0 and config.vae.feature_dim == 263:
        fixes.append(Stepping(config.stepping, config.repair, constrained=bool(constraints)))
    fixes.append(MeetConstraints(constraints, config.stepping) if constraints else Decode())
    if repair and not constraints:  # constraints already place the root and joints
        fixes.append(Repair(config.repair))
    if side_redraws and not constraints:  # a directed take is not drawn again
        fixes.append(SideRedraw(side_redraws, redo, after=draw))
    if verb_redraws and not constraints:
        fixes.append(VerbRedraw(verb_redraws, redo, after=draw + side_redraws))
    return fixes
