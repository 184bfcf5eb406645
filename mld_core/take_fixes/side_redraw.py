"""Take fix 4, side redraw (config ``side_redraws``): a free take whose prompt names a side (a turn, a drift, a wave, a
raised hand: mld_core.eval.named_side) that the take did not use (side badge "opposite" or "neither") is drawn again
from its seed's next draws, and replaced by the first that uses the side, else by the first that at least does not use
the opposite one. The takes record which draw each row is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, ClassVar

from mld_core.take_fixes.redraw import redraw_missed

# A side badge as a score: the named side beats neither side, which beats the opposite one; no side named is met.
SIDE_SCORE = {"named": 2, "neither": 1, "opposite": 0, None: 2}


def judge_side(prompt: str, joints, fps: float) -> tuple[int, bool]:
    """(score, complete) of a take's side badge."""
    from mld_core.eval.quality import side_badge

    score = SIDE_SCORE[side_badge(prompt, joints, fps)]
    return score, score == 2


@dataclass
class SideRedraw:
    """The fix: at most ``redraws`` more draws per row, draws ``after`` + 1, + 2, ... of its seed (``after``: the
    call's draw); ``redo(rows, k)`` makes those rows again from draw k of their seeds, exactly as the first draw was
    made but without redraws (an MLDOutput of those rows)."""

    redraws: int
    redo: Callable
    after: int = 0
    timings: ClassVar[tuple] = ("side_redraws_s",)

    def apply(self, takes, decoder):
        draws = range(self.after + 1, self.after + self.redraws + 1)
        return redraw_missed(takes, decoder, self.redo, draws, judge_side, "side")
