"""What the user is told about prompts and takes: coverage warnings, the best-K cut, badge tables and records.

Shared by ``python -m mld_core generate`` and the Blender add-on (batch manifest, Action custom properties), so
that every place a take appears says the same thing about it.
"""

from __future__ import annotations

from typing import Sequence

from mld_core.condition.coverage import Coverage
from mld_core.eval import named_side
from mld_core.eval.quality import REAL_JERK_P95, Badges, format_table, side_badge, verb_badge


class BeyondModel(ValueError):
    """A prompt the model has not learned, refused under ``strict``."""


CLI_PICK = "--model {name}, or --model auto"  # how a user of generate or the batch picks another bundled model
PANEL_PICK = "choose it, or Auto, as the panel's Model"


def other_model_note(coverage: Coverage, model_id: str, pick: str = CLI_PICK) -> str:
    """'' unless ``coverage`` says the model ``model_id`` has not learned its prompt and the prompt names checked
    verbs that another bundled model is trained on; then that model and how to ``pick`` it."""
    from mld_core.bundled import model_for_verbs
    from mld_core.data.verbs import VERB_SHOWN, verbs_in_order

    verbs = verbs_in_order(coverage.prompt) if coverage.verdict == "unknown" else []
    name = model_for_verbs(verbs, model_id)
    if name is None:
        return ""
    shown = " and ".join(VERB_SHOWN[v] for v in verbs)
    return f"the bundled model {name} is trained to make {shown} ({pick.format(name=name)})"


def check_prompts(pipe, prompts: Sequence[str], *, strict: bool = False, warn=print) -> list[Coverage]:
    """Coverage per unique prompt; one warning line per ``unknown`` prompt through ``warn``, followed by a note when
    another bundled model is trained on the verbs it names; under ``strict`` an unknown prompt raises BeyondModel
    (before anything is generated)."""
    unique = list(dict.fromkeys(prompts))
    found = {c.prompt: c for c in pipe.coverage(unique)}
    unknown = [found[p] for p in unique if found[p].verdict == "unknown"]
    if strict and unknown:
        note = other_model_note(unknown[0], pipe.model_id)
        raise BeyondModel(unknown[0].warning() + (f"; {note}" if note else "") + " (--strict: nothing generated)")
    for c in unknown:
        warn(f"warning: {c.warning()}")
        note = other_model_note(c, pipe.model_id)
        if note:
            warn(f"note: {note}")
    return [found[p] for p in prompts]


def keep_best(out, num_variants: int, best: int | None):
    """The first ``best`` rows of each prompt's group (rows already best first); ``out`` itself when None."""
    if best is None or best >= num_variants:
        return out
    return out.select([i for i in range(len(out.lengths)) if i % num_variants < best])


def badge_table(out) -> str:
    """The badge table of an output generated with rank=True, one block per prompt."""
    blocks = []
    for prompt in dict.fromkeys(out.prompts):
        rows = [i for i, p in enumerate(out.prompts) if p == prompt]
        blocks.append(f"{prompt!r}:\n" + format_table([out.seeds[i] for i in rows], [out.badges[i] for i in rows]))
    return "\n".join(blocks)


def opposite_side_note(prompt: str, side: str | None) -> str:
    """'' unless a take's side badge is "opposite"; then what it did against the prompt ("it turns right, not left
    as the prompt says")."""
    ask = named_side.asked_side(prompt) if side == "opposite" else None
    return "" if ask is None else ask.opposite_note()


def redrawn_note(prompt: str, draw: int, side: str | None = "named") -> str:
    """'' for a seed's first draw; else why the take is a later one ("draw 1 of its seed: the first did not turn
    left as the prompt says"), given the take's side badge ``side``."""
    ask = named_side.asked_side(prompt) if draw else None
    return "" if ask is None else ask.redrawn_note(draw, side)


PANEL_RETRY = " (try another seed, or more variants)"  # the add-on's report and the batch
CLI_RETRY = "; try another --seed, or --variants 4 --best 1 (ranking puts such takes last)"
# what generate says to try when no draw showed the prompt's verbs (ranking puts takes that miss them last too)
CLI_VERB_RETRY = "; try another --seed, more --verb-redraws, or --variants 4 --best 1 (ranking puts such takes last)"


def verb_note(prompt: str, draw: int, redrawn_for: str) -> str:
    """'' unless the verb redraws drew the take (``redrawn_for`` "verb" or "verb missed"); then why it is a later
    draw of its seed, or that no draw showed the verbs its prompt names."""
    from mld_core.data.verbs import VERB_SHOWN, verbs_in_order

    verbs = verbs_in_order(prompt) if redrawn_for in ("verb", "verb missed") else []
    if not verbs:
        return ""
    asked = " and ".join(VERB_SHOWN[v] for v in verbs)
    if redrawn_for == "verb missed":
        return f"no draw of its seed showed {asked} as the prompt says"
    return f"draw {draw} of its seed: an earlier one did not show {asked} as the prompt says"


def missed_verb_note(prompt: str, verb: str | None) -> str:
    """'' unless a take's verb badge ``verb`` is "missed" (mld_core.eval.quality.verb_badge); then what the prompt
    asked for that the take does not show."""
    from mld_core.data.verbs import VERB_SHOWN, verbs_in_order

    verbs = verbs_in_order(prompt) if verb == "missed" else []
    if not verbs:
        return ""
    asked = VERB_SHOWN[verbs[0]] if len(verbs) == 1 else "all of " + " and ".join(VERB_SHOWN[v] for v in verbs)
    return f"it does not show {asked} as the prompt says"


def side_report(prompt: str, side: str | None, draw: int, retry: str = PANEL_RETRY,
                redrawn_for: str | None = None, verb: str | None = None) -> tuple[str, str]:
    """What the user is told about a take's side and verbs, from its side badge ``side``, its ``draw``,
    ``redrawn_for`` (MLDOutput.redrawn_for's entry; None when not known, read as the side redraws') and its verb
    badge ``verb`` (None: not badged): ("warning", what it did against the prompt + ``retry``) when it used only the
    opposite side, when the verb redraws found no draw that shows the prompt's verbs, or when its verb badge says it
    misses them; ("note", why it is a later draw of its seed) when a redraw drew it again; else ("", "")."""
    note = opposite_side_note(prompt, side)
    if note:
        return "warning", note + retry
    verb_retry = CLI_VERB_RETRY if retry == CLI_RETRY else retry
    redrawn = verb_note(prompt, draw, redrawn_for or "")
    if redrawn and redrawn_for == "verb missed":
        return "warning", redrawn + verb_retry
    missed = missed_verb_note(prompt, verb)
    if missed:
        return "warning", missed + verb_retry
    if redrawn:
        return "note", redrawn
    note = redrawn_note(prompt, draw, side) if not (redrawn_for or "").startswith("verb") else ""
    return ("note", note) if note else ("", "")


def side_lines(out) -> list[str]:
    """``generate``'s line per take of ``out`` that used the opposite side, does not show the verbs its prompt names
    (by its redraws or its verb badge), or is a later draw (side_report); each take's side and verb badges its own when
    ranked, else checked here."""
    lines = []
    for row, prompt in enumerate(out.prompts):
        if out.badges is not None:
            side, verb = out.badges[row].side, out.badges[row].verb
        else:
            joints = out.joints[row, : int(out.lengths[row])]
            side, verb = side_badge(prompt, joints, out.fps), verb_badge(prompt, joints, out.fps)
        reason = out.redrawn_for[row] if getattr(out, "redrawn_for", None) else None
        level, text = side_report(prompt, side, out.draws[row] if out.draws else 0, CLI_RETRY, reason, verb)
        if level:
            joint = " is" if level == "note" else ":"  # "take 0 (seed 41) is draw 1 ...", "take 0 (seed 41): it turns"
            lines.append(f"{level}: take {row} (seed {out.seeds[row]}){joint} {text}")
    return lines


def seam_lines(seams: Sequence | None, prompts: Sequence[str]) -> list[str]:
    """One line per seam of a sequence that jerks more than real motion (``MLDOutput.seams``: (segment, largest
    joint jerk, within real)); ``prompts`` the segments' prompts in order."""
    return [f'the seam into segment {k + 1} ("{prompts[k]}") jerks {jerk:,.0f} m/s^3, {jerk / REAL_JERK_P95:.1f}x '
            f"real motion's 95th percentile: check it, or try another seed"
            for k, jerk, within in seams or [] if not within]


def seam_records(seams: Sequence | None) -> list[dict]:
    """``MLDOutput.seams`` as JSON-able records (batch manifests); segments counted from 1."""
    return [{"segment": int(k) + 1, "jerk": round(float(jerk), 1), "within_real": bool(within)}
            for k, jerk, within in seams or []]


def take_record(coverage: Coverage | None, badges: Badges | None) -> dict:
    """A JSON-able record of one take's coverage and badges (batch manifest, .npz)."""
    record = {}
    if coverage is not None:
        record["coverage"] = coverage.as_dict()
    if badges is not None:
        record["badges"] = badges.as_dict()
    return record


BADGE_PROPERTIES = {"adherence": "adherence", "similarity": "similarity", "skating": "skating",
                    "float": "foot_float", "penetration_cm": "penetration_cm", "jitter": "jitter", "side": "side",
                    "verb": "verb"}


def custom_properties(coverage: Coverage | None, badges: Badges | None, prefix: str = "mld_") -> dict:
    """Flat numbers and strings for an Action's custom properties (mld_coverage_verdict, mld_adherence, ...);
    values that are missing are left out."""
    props = {}
    if coverage is not None:
        props.update(coverage_verdict=coverage.verdict, coverage_score=float(coverage.score))
        if coverage.nearest:
            props["coverage_nearest"] = coverage.nearest[0][0]
    if badges is not None:
        for key, value in badges.as_dict().items():
            if value is not None:
                props[BADGE_PROPERTIES[key]] = value if isinstance(value, str) else float(value)
    return {prefix + k: v for k, v in props.items()}


def records_for(out, coverages: Sequence[Coverage] | None) -> list[dict]:
    """Per row of ``out``: its prompt's coverage and its badges."""
    by_prompt = {c.prompt: c for c in (coverages or [])}
    badges = out.badges or [None] * len(out.lengths)
    return [take_record(by_prompt.get(p), b) for p, b in zip(out.prompts, badges)]
