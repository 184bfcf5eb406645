"""Take fix 5, verb redraw (config ``verb_redraws``): a free take whose prompt names checked verbs (jump, crawl, kick,
... : mld_core.data.verbs) that the take does not all show by their physical checks (mld_core.eval.physical) is drawn
again from its seed's next draws, and replaced by a draw that shows more of them ("lies down and stands up" asks for
both). Between draws that show as many, the side the prompt names (the side badge) decides.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, ClassVar

from mld_core.eval.quality import verbs_shown
from mld_core.take_fixes.redraw import redraw_missed
from mld_core.take_fixes.side_redraw import judge_side


def judge_verb(prompt: str, joints, fps: float) -> tuple[tuple[int, int], bool]:
    """((verbs shown, side score), complete) of a take; a prompt naming no checked verb is complete."""
    shown, named = verbs_shown(prompt, joints, fps)
    return (shown, judge_side(prompt, joints, fps)[0]), shown == named


@dataclass
class VerbRedraw:
    """The fix: at most ``redraws`` more draws per row, draws ``after`` + 1, + 2, ... of its seed (``after``: the
    call's draw plus the side redraws' draws, so the two fixes never draw the same z_T); ``redo`` as SideRedraw's."""

    redraws: int
    redo: Callable
    after: int = 0
    timings: ClassVar[tuple] = ("verb_redraws_s",)

    def apply(self, takes, decoder):
        draws = range(self.after + 1, self.after + self.redraws + 1)
        return redraw_missed(takes, decoder, self.redo, draws, judge_verb, "verb")
