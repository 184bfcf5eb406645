"""Take fix 4, side redraw (config ``side_redraws``): a free take whose prompt names a side (a turn, a drift, a wave, a
raised hand: mld_core.eval.named_side) that the take did not use (side badge "opposite" or "neither") is drawn again
from its seed's next draws, and replaced by the first that uses the side, else by the first that at least does not use
the opposite one. The takes record which draw each row is.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, ClassVar


@dataclass
class SideRedraw:
    """The fix: at most ``redraws`` more draws per row; ``redo(rows, k)`` makes those rows again from draw k of their
    seeds, exactly as the first draw was made but without redraws (an MLDOutput of those rows)."""

    redraws: int
    redo: Callable
    timings: ClassVar[tuple] = ("side_redraws_s",)

    def apply(self, takes, decoder):
        from mld_core.eval.quality import side_badge

        n = takes.lengths.tolist()
        joints = takes.joints if takes.joints is not None else decoder.joints(takes.features, n)
        features, draws = takes.features, list(takes.draws)
        verdicts = [side_badge(takes.prompts[r], joints[r, : n[r]], decoder.fps) for r in range(len(n))]
        first = draws[0] if draws else 0
        for k in range(first + 1, first + self.redraws + 1):
            rows = [r for r, v in enumerate(verdicts) if v in ("opposite", "neither")]
            if not rows:
                break
            again = self.redo(rows, k)
            for j, r in enumerate(rows):
                v = side_badge(again.prompts[j], again.joints[j, : int(again.lengths[j])], again.fps)
                if v == "named" or (v == "neither" and verdicts[r] == "opposite"):
                    m = again.features.shape[1]  # (B', T', F): T' <= these takes' T
                    features[r] = 0.0
                    features[r, :m] = again.features[j]
                    joints[r, :m] = again.joints[j]
                    joints[r, m:] = again.joints[j, int(again.lengths[j]) - 1]  # (frames past the length repeat)
                    draws[r], verdicts[r] = k, v
        return replace(takes, features=features, joints=joints, draws=draws)
