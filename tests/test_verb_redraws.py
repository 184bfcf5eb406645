"""Verb redraws (mld_core.take_fixes.verb_redraw, config verb_redraws): a free take that does not show the checked verb
its prompt names is drawn again from its seed, after the side redraws' draws, and the user is told which draw they got
and why. The tiny model's takes are noise, so whether a take shows its verb is set here per draw."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from mld_core import take_report
from mld_core.checkpoint import check_config
from mld_core.eval import physical, quality
from mld_core.inputs import InputError
from mld_core.take_fixes.order import Takes, fixes_for
from mld_core.data.verbs import verbs_in_order
from mld_core.take_fixes.verb_redraw import VerbRedraw, judge_verb
from mld_core.testing import tiny_config, tiny_pipeline

JUMP = "a person jumps over a puddle"


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    return tiny_pipeline(tmp_path_factory.mktemp("tiny"))


def _draws(pipe, prompt, seconds, seed, ks):
    """{k: the joints of draw k of one seed, made alone (no redraws)}."""
    return {k: pipe(prompt, seconds, seed=seed, draw=k, side_redraws=0, verb_redraws=0).joints[0] for k in ks}


def _shown_by_draw(monkeypatch, draws, shown):
    """Make the verb check read ``shown[k]`` for a take equal to ``draws[k]``; count its calls (verb, draw)."""
    calls = []

    def shows(joints, verb, fps=20.0, result=None):
        for k, d in draws.items():
            if d[: len(joints)].shape == joints.shape and np.allclose(d[: len(joints)], joints, atol=1e-4):
                calls.append((verb, k))
                return shown[k]
        raise AssertionError("a take that is none of the expected draws")

    monkeypatch.setattr(physical, "shows", shows)
    return calls


def test_a_take_is_judged_by_every_verb_its_prompt_names(monkeypatch):
    assert verbs_in_order(JUMP) == ["jump"]
    assert verbs_in_order("a person lies on his side and stands up") == ["on_ground", "stand_up"]
    assert verbs_in_order("a person walks forward") == []
    assert judge_verb("a person walks forward", np.zeros((4, 22, 3)), 20.0) == ((0, 2), True)
    monkeypatch.setattr(physical, "shows", lambda joints, verb, fps=20.0: verb == "stand_up")
    assert judge_verb("a person lies on his side and stands up", np.zeros((4, 22, 3)), 20.0) == ((1, 2), False)


def test_a_take_that_misses_its_verb_is_the_first_later_draw_that_shows_it(pipe, monkeypatch):
    draws = _draws(pipe, JUMP, 2.0, 7, [0, 3, 4])
    calls = _shown_by_draw(monkeypatch, draws, {0: False, 3: False, 4: True})
    out = pipe(JUMP, 2.0, seed=7, verb_redraws=2)  # the side redraws (2 by default) keep draws 1 and 2
    assert calls == [("jump", 0), ("jump", 3), ("jump", 4)]
    assert out.draws == [4] and out.redrawn_for == ["verb"] and out.seeds == [7]
    np.testing.assert_array_equal(out.joints[0], draws[4])
    assert "verb_redraws_s" in out.timings
    assert take_report.side_lines(out) == [
        "note: take 0 (seed 7) is draw 4 of its seed: an earlier one did not show a jump as the prompt says"]


def test_when_no_draw_shows_the_verb_the_first_stays_and_the_user_is_warned(pipe, monkeypatch):
    draws = _draws(pipe, JUMP, 2.0, 9, [0, 3, 4])
    _shown_by_draw(monkeypatch, draws, {0: False, 3: False, 4: False})
    out = pipe(JUMP, 2.0, seed=9, verb_redraws=2)
    assert out.draws == [0] and out.redrawn_for == ["verb missed"]
    np.testing.assert_array_equal(out.joints[0], draws[0])
    [line] = take_report.side_lines(out)
    assert line == ("warning: take 0 (seed 9): no draw of its seed showed a jump as the prompt says; try another "
                    "--seed, more --verb-redraws, or --variants 4 --best 1 (ranking puts such takes last)")
    assert take_report.side_report(JUMP, None, 0, redrawn_for="verb missed") == (
        "warning", "no draw of its seed showed a jump as the prompt says (try another seed, or more variants)")


def test_no_verb_redraw_by_default_when_off_for_a_prompt_naming_no_verb_or_a_directed_take(pipe, monkeypatch):
    from mld_core.take_fixes.constraints import Constraints, Loop

    assert tiny_config().verb_redraws == 0 and pipe.config.verb_redraws == 0
    draws = _draws(pipe, JUMP, 2.0, 3, [0])
    calls = _shown_by_draw(monkeypatch, draws, {0: False})
    assert pipe(JUMP, 2.0, seed=3).draws == [0] and calls == []  # the config's default: none
    assert pipe(JUMP, 2.0, seed=3, verb_redraws=0).redrawn_for in (None, [""]) and calls == []
    walk = "a person walks forward"
    assert pipe(walk, 2.0, seed=3, verb_redraws=2).redrawn_for == [""] and calls == []
    directed = pipe(JUMP, 2.0, seed=3, verb_redraws=2, constraints=Constraints([Loop()], steps=2))
    assert directed.draws == [0] and calls == []


def test_a_batch_with_verb_redraws_equals_its_rows_made_alone(pipe, monkeypatch):
    jump = _draws(pipe, JUMP, 2.0, 4, [0, 3])
    kick = _draws(pipe, "a person kicks a ball", 3.0, 11, [0])
    both = {0: jump[0], 3: jump[3], 10: kick[0]}
    _shown_by_draw(monkeypatch, both, {0: False, 3: True, 10: True})
    out = pipe([JUMP, "a person kicks a ball"], [2.0, 3.0], seed=[4, 11], verb_redraws=2)
    assert out.draws == [3, 0] and out.redrawn_for == ["verb", ""]
    np.testing.assert_allclose(out.joints[0, :40], jump[3], atol=1e-4)
    assert (out.features[0, 40:] == 0).all()
    np.testing.assert_allclose(out.joints[1], kick[0], atol=1e-4)
    alone = pipe(JUMP, 2.0, seed=4, verb_redraws=2)
    np.testing.assert_allclose(alone.joints[0], out.joints[0, :40], atol=1e-4)


def test_the_verb_comes_first_and_the_named_side_breaks_ties(monkeypatch):
    # per row and draw: (shows the verb, side badge); a take's joints hold 10 x its row + its draw
    verdicts = {0: [(False, "named"), (True, "opposite")],  # the verb wins over the side
                1: [(False, "opposite"), (False, "named")],  # neither shows the verb: the side decides
                2: [(True, "neither")]}  # shows the verb: not drawn again for its side

    def verdict(joints):
        return verdicts[int(joints[0, 0, 0]) // 10][int(joints[0, 0, 0]) % 10]

    monkeypatch.setattr(physical, "shows", lambda joints, verb, fps=20.0: verdict(joints)[0])
    monkeypatch.setattr(quality, "side_badge", lambda prompt, joints, fps=20.0: verdict(joints)[1])
    prompts = ["a person jumps and turns left"] * 3
    asked = []

    def redo(rows, k):
        asked.append((rows, k))
        joints = np.stack([np.full((6, 22, 3), 10.0 * r + k, np.float32) for r in rows])
        return SimpleNamespace(prompts=[prompts[r] for r in rows], fps=20, lengths=np.full(len(rows), 6),
                               joints=joints, features=np.full((len(rows), 6, 263), 1.0, np.float32))

    first = np.stack([np.full((6, 22, 3), 10.0 * r, np.float32) for r in range(3)])
    takes = Takes(torch.zeros(3, 1, 4), torch.zeros(3, 1, 4), torch.full((3,), 6), prompts, [0, 0, 0],
                  features=np.zeros((3, 6, 263), np.float32), joints=first)
    out = VerbRedraw(1, redo, after=0).apply(takes, SimpleNamespace(fps=20))
    assert asked == [([0, 1], 1)]
    assert out.draws == [1, 1, 0] and out.redrawn_for == ["verb", "verb missed", ""]
    assert [verdict(j) for j in out.joints] == [(True, "opposite"), (False, "named"), (True, "neither")]


def test_verb_redraws_come_after_the_side_redraws_and_skip_their_draws():
    config = tiny_config()
    call = dict(draft=False, step=False, repair=True, constraints=None, redo=None)
    fixes = fixes_for(config, side_redraws=2, verb_redraws=3, draw=5, **call)
    assert [type(f).__name__ for f in fixes] == ["Decode", "Repair", "SideRedraw", "VerbRedraw"]
    assert (fixes[2].after, fixes[3].after, fixes[3].redraws) == (5, 7, 3)
    assert [type(f).__name__ for f in fixes_for(config, side_redraws=0, verb_redraws=0, **call)] == ["Decode",
                                                                                                     "Repair"]


def test_the_call_bounds_verb_redraws_and_the_config_keeps_them(pipe):
    config = tiny_config()  # the config's bounds: tests/test_side_redraws.py, with the side redraws'
    config.verb_redraws = 2
    check_config(config)
    assert json.loads(json.dumps(config.to_dict()))["verb_redraws"] == 2
    for bad in (9, -1):
        with pytest.raises(InputError, match="verb_redraws must be between 0 and 8"):
            pipe(JUMP, 2.0, verb_redraws=bad)
    with pytest.raises(InputError, match="verb_redraws"):
        pipe(JUMP, 2.0, verb_redraws=True)


def test_the_side_note_is_not_given_for_a_take_its_verb_drew_again():
    turn_jump = "a person jumps and turns left"
    assert take_report.side_report(turn_jump, "named", 3, redrawn_for="verb")[1].startswith(
        "draw 3 of its seed: an earlier one did not show a jump")
    assert "turn left" in take_report.side_report(turn_jump, "named", 1, redrawn_for="side")[1]
    assert "turn left" in take_report.side_report(turn_jump, "named", 1)[1]  # not known: as before, the side's
    assert take_report.side_report(turn_jump, "opposite", 3, redrawn_for="verb")[0] == "warning"  # side first


def test_ranked_variants_put_a_take_that_misses_its_verb_last_and_the_user_sees_it(pipe, monkeypatch):
    alone = {seed: pipe(JUMP, 2.0, seed=seed, side_redraws=0, verb_redraws=0).joints[0] for seed in (5, 6)}
    for missed, kept in ((5, 6), (6, 5)):  # whichever the score puts first, the take that misses the jump goes last
        monkeypatch.setattr(physical, "shows", lambda joints, verb, fps=20.0, result=None, m=alone[missed]:
                            not np.allclose(m[: len(joints)], joints, atol=1e-4))
        ranked = pipe(JUMP, 2.0, seed=5, num_variants=2, rank=True, verb_redraws=0)
        assert ranked.seeds == [kept, missed] and [b.verb for b in ranked.badges] == ["shown", "missed"]
        assert take_report.keep_best(ranked, 2, 1).seeds == [kept]
        assert take_report.badge_table(ranked).splitlines()[3].split()[-1] == "missed"


def test_a_ranked_take_whose_verb_badge_says_missed_is_a_warning_without_redraws(pipe, monkeypatch):
    """With no verb redraws (the bundled model's default), the verb badge still tells the user: generate's line, and
    the add-on's and the batch's report; a take that shows its verbs, or a prompt naming none, gets no such line."""
    draws = _draws(pipe, JUMP, 2.0, 5, [0])
    _shown_by_draw(monkeypatch, draws, {0: False})
    out = pipe(JUMP, 2.0, seed=5, verb_redraws=0, rank=True)
    assert out.badges[0].verb == "missed"
    assert take_report.side_lines(out) == [
        "warning: take 0 (seed 5): it does not show a jump as the prompt says; try another --seed, more "
        "--verb-redraws, or --variants 4 --best 1 (ranking puts such takes last)"]
    assert take_report.side_report(JUMP, "named", 0, verb="missed") == (
        "warning", "it does not show a jump as the prompt says (try another seed, or more variants)")
    two = "a person jumps and kicks"
    assert take_report.side_report(two, None, 0, verb="missed")[1].startswith(
        "it does not show all of a jump and a kick as the prompt says")
    assert take_report.side_report(JUMP, None, 0, verb="shown") == ("", "")
    assert take_report.side_report("a person walks", None, 0, verb="missed") == ("", "")  # names no checked verb
    assert take_report.side_report(JUMP, None, 0, verb=None) == ("", "")  # not badged: nothing said
    # the opposite side is said first; the redraws' own warning is not said twice
    assert "turns right" in take_report.side_report("a person jumps and turns left", "opposite", 0, verb="missed")[1]
    level, text = take_report.side_report(JUMP, None, 0, redrawn_for="verb missed", verb="missed")
    assert level == "warning" and text.startswith("no draw of its seed showed a jump")
    unranked = pipe(JUMP, 2.0, seed=5, verb_redraws=0)  # generate without --best: the verb checked for the line
    assert unranked.badges is None and take_report.side_lines(unranked) == take_report.side_lines(out)
    _shown_by_draw(monkeypatch, draws, {0: True})
    shown = pipe(JUMP, 2.0, seed=5, verb_redraws=0, rank=True)
    assert shown.badges[0].verb == "shown" and take_report.side_lines(shown) == []
    assert take_report.side_lines(pipe(JUMP, 2.0, seed=5, verb_redraws=0)) == []


def test_a_draft_draws_again_as_often_as_its_own_config_says_and_the_final_as_the_models(tmp_path, monkeypatch):
    pipe = tiny_pipeline(tmp_path, draft=True)
    pipe.config.verb_redraws, pipe.config.draft.verb_redraws = 1, 3
    check_config(pipe.config)
    assert json.loads(json.dumps(pipe.config.to_dict()))["draft"]["verb_redraws"] == 3
    monkeypatch.setattr(physical, "shows", lambda joints, verb, fps=20.0: False)  # no draw shows the jump
    seen = []
    real_init = VerbRedraw.__init__

    def counting_init(self, redraws, *args, **kwargs):
        seen.append(redraws)
        real_init(self, redraws, *args, **kwargs)

    monkeypatch.setattr(VerbRedraw, "__init__", counting_init)
    out = pipe(JUMP, 2.0, seed=1, draft=True, side_redraws=0)
    assert out.redrawn_for == ["verb missed"]
    pipe(JUMP, 2.0, seed=1, side_redraws=0, step=False)
    pipe(JUMP, 2.0, seed=1, draft=True, side_redraws=0, verb_redraws=2)  # the call's own wins
    pipe.config.draft.verb_redraws = None  # unset: the Draft draws again as the model does
    pipe(JUMP, 2.0, seed=1, draft=True, side_redraws=0)
    assert seen == [3, 1, 2, 1]
    for bad in (9, -1, True, 1.5):
        pipe.config.draft.verb_redraws = bad
        with pytest.raises(ValueError, match="draft.verb_redraws must be null or a whole number in 0..8"):
            check_config(pipe.config)
