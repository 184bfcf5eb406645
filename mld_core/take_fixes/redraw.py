"""The loop the redraw fixes share: a free take that misses what its prompt asks is drawn again from its seed's next
draws, and replaced by a later draw that a judge scores higher."""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

# judge(prompt, joints (T, 22, 3), fps) -> (score, complete): a take scores higher the more of its prompt's ask it
# meets; an incomplete one is drawn again.
Judge = Callable[[str, object, float], tuple]


def redraw_missed(takes, decoder, redo: Callable, draws_to_try: range, judge: Judge, reason: str):
    """``takes`` with each incomplete row drawn again, draw k of ``draws_to_try`` at a time, until it is complete: a
    draw replaces the take kept so far when ``judge`` scores it higher (``redo(rows, k)``: those rows made again
    from draw k of their seeds, an MLDOutput). A replaced row's ``draws`` entry says which draw it is and its
    ``redrawn_for`` entry says ``reason``; a row no draw completed says ``reason`` + " missed". The draws tried
    depend on the call, never on the other rows, so a batch equals its rows made alone."""
    n = takes.lengths.tolist()
    joints = takes.joints if takes.joints is not None else decoder.joints(takes.features, n)
    features, draws = takes.features, list(takes.draws)
    reasons = list(takes.redrawn_for) if takes.redrawn_for is not None else [""] * len(n)
    verdicts = [judge(takes.prompts[r], joints[r, : n[r]], decoder.fps) for r in range(len(n))]
    missed = [r for r, (_, complete) in enumerate(verdicts) if not complete]
    for k in draws_to_try:
        rows = [r for r, (_, complete) in enumerate(verdicts) if not complete]
        if not rows:
            break
        again = redo(rows, k)
        for j, r in enumerate(rows):
            verdict = judge(again.prompts[j], again.joints[j, : int(again.lengths[j])], again.fps)
            if verdict[0] > verdicts[r][0]:
                m = again.features.shape[1]  # (B', T', F): T' <= these takes' T
                features[r] = 0.0
                features[r, :m] = again.features[j]
                joints[r, :m] = again.joints[j]
                joints[r, m:] = again.joints[j, int(again.lengths[j]) - 1]  # (frames past the length repeat)
                draws[r], verdicts[r], reasons[r] = k, verdict, reason
    for r in missed:
        if not verdicts[r][1]:
            reasons[r] = f"{reason} missed"
    return replace(takes, features=features, joints=joints, draws=draws, redrawn_for=reasons)
