"""Side redraws (mld_core.take_fixes.side_redraw, config side_redraws): a free take that misses the side its prompt
names is drawn again from its seed, and the user is told which draw they got and why."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mld_core import take_report
from mld_core.checkpoint import check_config
from mld_core.eval import quality
from mld_core.testing import tiny_config, tiny_pipeline

TURN_LEFT = "a person walks and turns left"


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    return tiny_pipeline(tmp_path_factory.mktemp("tiny"))


def _draws(pipe, prompt, seconds, seed, n):
    """The joints of draws 0..n-1 of one seed, each made alone (no redraws)."""
    return [pipe(prompt, seconds, seed=seed, draw=k, side_redraws=0).joints[0] for k in range(n)]


def _side_by_draw(monkeypatch, draws, verdicts):
    """Make the side badge read ``verdicts[k]`` for a take equal to ``draws[k]`` (the tiny model's takes are noise,
    so which side they use is set here; a batch equals its single runs to 1e-4); count its calls."""
    calls = []

    def side(prompt, joints, fps=20.0):
        calls.append(prompt)
        for k, d in enumerate(draws):
            if d[: len(joints)].shape == joints.shape and np.allclose(d[: len(joints)], joints, atol=1e-4):
                return verdicts[k]
        raise AssertionError("a take that is none of the expected draws")

    monkeypatch.setattr(quality, "side_badge", side)
    monkeypatch.setattr(take_report, "side_badge", side)
    return calls


def test_draws_of_one_seed_differ_and_each_is_reproducible(pipe):
    a, b = _draws(pipe, TURN_LEFT, 2.0, 5, 2)
    assert not np.allclose(a, b)
    np.testing.assert_array_equal(pipe(TURN_LEFT, 2.0, seed=5, draw=1, side_redraws=0).joints[0], b)


def test_a_take_that_misses_its_side_is_the_seeds_first_draw_that_uses_it(pipe, monkeypatch):
    draws = _draws(pipe, TURN_LEFT, 2.0, 7, 3)
    _side_by_draw(monkeypatch, draws, ["opposite", "neither", "named"])
    out = pipe(TURN_LEFT, 2.0, seed=7)  # the config's default: 2 redraws
    assert out.draws == [2] and out.seeds == [7]
    np.testing.assert_array_equal(out.joints[0], draws[2])
    assert "side_redraws_s" in out.timings
    assert take_report.side_lines(out) == [
        "note: take 0 (seed 7) is draw 2 of its seed: the first 2 did not turn left as the prompt says"]


def test_when_no_draw_uses_the_side_a_neither_beats_an_opposite_and_otherwise_the_first_stays(pipe, monkeypatch):
    draws = _draws(pipe, TURN_LEFT, 2.0, 9, 3)
    _side_by_draw(monkeypatch, draws, ["opposite", "neither", "opposite"])
    assert pipe(TURN_LEFT, 2.0, seed=9).draws == [1]
    assert take_report.side_report(TURN_LEFT, "neither", 1) == (
        "note", "draw 1 of its seed: no draw did turn left as the prompt says; this one at least does not turn right")
    assert take_report.side_report(TURN_LEFT, "named", 1)[0] == "note"
    assert take_report.side_report(TURN_LEFT, "opposite", 2)[0] == "warning"  # still opposite: the warning wins
    _side_by_draw(monkeypatch, draws, ["neither", "opposite", "neither"])
    out = pipe(TURN_LEFT, 2.0, seed=9)
    assert out.draws == [0] and take_report.side_lines(out) == []
    np.testing.assert_array_equal(out.joints[0], draws[0])


def test_no_redraw_when_off_when_no_side_is_named_or_when_the_take_is_directed(pipe, monkeypatch):
    from mld_core.take_fixes.constraints import Constraints, Loop

    draws = _draws(pipe, TURN_LEFT, 2.0, 3, 1)
    calls = _side_by_draw(monkeypatch, draws, ["opposite"])
    assert pipe(TURN_LEFT, 2.0, seed=3, side_redraws=0).draws == [0] and calls == []
    calls = _side_by_draw(monkeypatch, draws, [None])  # a prompt that names no side: one check, no redraw
    assert pipe(TURN_LEFT, 2.0, seed=3).draws == [0] and len(calls) == 1
    calls = _side_by_draw(monkeypatch, [], [])
    assert pipe(TURN_LEFT, 2.0, seed=3, constraints=Constraints([Loop()], steps=2)).draws == [0] and calls == []


def test_a_batch_with_redraws_equals_its_rows_made_alone(pipe, monkeypatch):
    left = _draws(pipe, TURN_LEFT, 2.0, 4, 2)
    other = _draws(pipe, "a person waves the right hand", 3.0, 11, 1)
    _side_by_draw(monkeypatch, left + other, ["opposite", "named", "named"])
    out = pipe([TURN_LEFT, "a person waves the right hand"], [2.0, 3.0], seed=[4, 11])
    assert out.draws == [1, 0]
    np.testing.assert_allclose(out.joints[0, :40], left[1], atol=1e-4)
    assert (out.features[0, 40:] == 0).all()  # zero beyond its length, as every row
    np.testing.assert_array_equal(out.joints[0, 40:], np.repeat(out.joints[0, 39:40], out.joints.shape[1] - 40, 0))
    np.testing.assert_allclose(out.joints[1], other[0], atol=1e-4)


def test_ranking_and_the_best_cut_keep_each_rows_draw(pipe, monkeypatch):
    draws = _draws(pipe, TURN_LEFT, 2.0, 20, 2) + _draws(pipe, TURN_LEFT, 2.0, 21, 1)
    _side_by_draw(monkeypatch, draws, ["opposite", "named", "named"])
    out = pipe(TURN_LEFT, 2.0, seed=20, num_variants=2)  # rows: seed 20 (redrawn once), seed 21
    assert out.draws == [1, 0]
    picked = out.select([1, 0])
    assert picked.seeds == [21, 20] and picked.draws == [0, 1]
    np.testing.assert_array_equal(picked.joints[1], out.joints[0])
    assert take_report.keep_best(out, 2, 1).draws == [1]


@pytest.mark.parametrize("name, default", [("side_redraws", 2), ("verb_redraws", 0)])
def test_the_config_bounds_the_redraws(name, default):
    for bad in (-1, 9, 1.5, True, "2"):
        config = tiny_config()
        setattr(config, name, bad)
        with pytest.raises(ValueError, match=name):
            check_config(config)
    config = tiny_config()
    check_config(config)
    assert getattr(config, name) == default and json.loads(json.dumps(config.to_dict()))[name] == default


def test_the_pipeline_refuses_a_bad_count(pipe):
    from mld_core.inputs import InputError

    with pytest.raises(InputError, match="side_redraws must be between 0 and 8"):
        pipe(TURN_LEFT, 2.0, side_redraws=9)


def test_the_evaluation_samples_with_the_side_redraws_it_is_given(pipe, monkeypatch):
    from dataclasses import replace

    from mld_core.eval.evaluate import EvalSettings, PipelineGenerator

    draws = _draws(pipe, TURN_LEFT, 2.0, 6, 2)
    calls = _side_by_draw(monkeypatch, draws, ["opposite", "named"])
    model = PipelineGenerator(pipe, EvalSettings(), False).text([TURN_LEFT], [40], 6)[0]  # the model's default
    assert len(calls) == 2  # the first draw, then its redraw
    alone = PipelineGenerator(pipe, replace(EvalSettings(), side_redraws=0), False).text([TURN_LEFT], [40], 6)[0]
    assert len(calls) == 2 and not np.allclose(model, alone)
