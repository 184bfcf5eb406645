"""The side badge: which side a prompt names for which motion, and whether a take used that side.

"turns to the left", "waves the right hand", "walks diagonally to the left", "raises the left arm": a prompt that
names one side (left or right, not both) for a turn, a drift, a wave or a raised hand gets a :class:`SideAsk`;
:func:`side_used` reads the matching physical check (``mld_core.eval.physical``) on a take and says
``"named"`` (the named side, alone or with the other hand), ``"opposite"`` (only the other side), or
``"neither"``. Prompts that name no side, both sides, or a side of something no check reads (a kick's leg, a
step's foot) get None: no badge.

Reading the prompt, with plain English word lists:

- a side word followed by hand(s) / arm(s) asks for a hand: a wave when the prompt has a waving word (wave,
  bye, goodbye, farewell), else a raised hand;
- followed by leg(s) / foot / feet: a leg, which no check reads (None);
- otherwise a direction: a turn when the prompt has a turning word (turn, veer, changes direction, ...) not
  after "without" / "not" / "no" / "never", else a drift when it has a travelling word (walk, stroll, drift,
  diagonally, ...), else None.

Only numpy (through the physical checks): the pipeline's ranking and the evaluation scripts use it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from mld_core.eval import physical

__all__ = ["SideAsk", "asked_side", "side_used"]

_SIDES = {"left", "right"}
_HAND_WORDS = {"hand", "hands", "arm", "arms"}
_LEG_WORDS = {"leg", "legs", "foot", "feet", "knee", "toe", "toes"}
_WAVE_WORDS = {"wave", "waves", "waving", "waved", "bye", "byebye", "goodbye", "farewell"}
_TURN_WORDS = {"turn", "turns", "turning", "turned", "veer", "veers", "veering", "veered", "direction", "rotate",
               "rotates", "rotating", "pivot", "pivots", "pivoting", "swerve", "swerves", "swerving"}
_TRAVEL_WORDS = {"walk", "walks", "walking", "walked", "stroll", "strolls", "strolling", "drift", "drifts", "drifting",
                 "diagonally", "diagonal", "step", "steps", "stepping", "sidestep", "sidesteps", "move", "moves",
                 "moving", "go", "goes", "going", "heads", "heading", "march", "marches", "jog", "jogs",
                 "run", "runs", "running", "shuffle", "shuffles", "lumber", "lumbers", "stride", "strides",
                 "forward", "forwards", "ahead", "sideways"}

_NEGATIONS = {"without", "not", "no", "never"}  # "diagonally to the left without turning" is a drift

# The content label whose side check reads each kind of ask (physical.detected_side).
_LABEL = {"turn": "walk-turn-{}", "drift": "walk-{}", "wave": "wave-{}-hand", "raise": "raise-up-{}-hand"}
# What a take of each kind did, for the note on a take that used the other side.
_DOING = {"turn": "turns {}", "drift": "drifts {}", "wave": "waves the {} hand", "raise": "raises the {} hand"}
# What the prompt asked, for the note on a take that was drawn again.
_ASKED = {"turn": "turn {}", "drift": "drift {}", "wave": "wave the {} hand", "raise": "raise the {} hand"}


@dataclass(frozen=True)
class SideAsk:
    """What a prompt asks for on one side: ``kind`` is "turn", "drift", "wave" or "raise"; ``side`` "left"/"right"."""

    kind: str
    side: str

    @property
    def label(self) -> str:
        """The Bandai Namco content whose physical checks read this side (walk-turn-left, wave-right-hand, ...)."""
        return _LABEL[self.kind].format(self.side)

    def opposite_note(self) -> str:
        """What a take that used the other side did, against the prompt: "it turns right, not left as the prompt
        says"."""
        other = "right" if self.side == "left" else "left"
        return f"it {_DOING[self.kind].format(other)}, not {self.side} as the prompt says"

    def redrawn_note(self, draw: int, used: str | None = "named") -> str:
        """Why a take is a later draw of its seed: "draw 2 of its seed: the first 2 did not turn left as the prompt
        says"; when the draw kept does not use the side either (``used`` "neither"), that it at least does not use
        the other one."""
        asked = _ASKED[self.kind].format(self.side)
        if used == "neither":
            other = _ASKED[self.kind].format("right" if self.side == "left" else "left")
            return (f"draw {draw} of its seed: no draw did {asked} as the prompt says; this one at least does not "
                    f"{other}")
        earlier = "the first" if draw == 1 else f"the first {draw}"
        return f"draw {draw} of its seed: {earlier} did not {asked} as the prompt says"


def _words(prompt: str) -> list[str]:
    return re.findall(r"[a-z]+", str(prompt).lower())


def asked_side(prompt: str) -> SideAsk | None:
    """The side the prompt names and for what, or None (no side, both sides, or nothing a check reads)."""
    words = _words(prompt)
    at = [i for i, w in enumerate(words) if w in _SIDES]
    if len({words[i] for i in at}) != 1:
        return None
    side = words[at[0]]
    following = {words[i + 1] for i in at if i + 1 < len(words)}
    present = set(words)
    turning = {w for i, w in enumerate(words) if w in _TURN_WORDS and (i == 0 or words[i - 1] not in _NEGATIONS)}
    if following & _HAND_WORDS:
        return SideAsk("wave" if present & _WAVE_WORDS else "raise", side)
    if following & _LEG_WORDS:
        return None
    if turning:
        return SideAsk("turn", side)
    if present & _TRAVEL_WORDS:
        return SideAsk("drift", side)
    return None


def side_used(ask: SideAsk, checks: dict) -> str:
    """"named", "opposite" or "neither": the side the take used for ``ask``, from ``checks`` (physical.classify of
    the take)."""
    used = physical.detected_side(checks, ask.label)
    if used in (ask.side, "both"):
        return "named"
    return "opposite" if used in _SIDES else "neither"
