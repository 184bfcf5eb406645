"""The take fixes as the pipeline applies them (mld_core.take_fixes.order): their declared order and where each
applies, each fix object doing what its function does, a side redraw's choice of draws, and the timings a call
reports per fix. Tiny seeded model: its motions are noise, the order and the bookkeeping are what is tested."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from mld_core.take_fixes.constraints import Constraints, Loop
from mld_core.take_fixes.meet_constraints import MeetConstraints, meet_constraints, meet_stepped_or_not
from mld_core.take_fixes.order import Decode, Takes, fixes_for
from mld_core.take_fixes.repair import Repair, repair_rows
from mld_core.take_fixes.side_redraw import SideRedraw
from mld_core.take_fixes.stepping import Stepping, SteppingConfig, step_feet
from mld_core.testing import tiny_config, tiny_pipeline

STEPPING = SteppingConfig(steps=10, lr=0.05, min_slide_share=0.0)


def _names(config, **kw) -> list[str]:
    call = dict(draft=False, step=True, repair=True, constraints=None, side_redraws=2, redo=None)
    return [type(fix).__name__ for fix in fixes_for(config, **{**call, **kw})]


def test_the_fixes_come_in_their_declared_order_each_where_it_applies():
    config = tiny_config()
    config.stepping = STEPPING
    loop = Constraints([Loop()])
    assert _names(config) == ["Stepping", "Decode", "Repair", "SideRedraw"]
    assert _names(config, draft=True) == ["Decode", "Repair", "SideRedraw"]  # a Draft is not stepped
    assert _names(config, constraints=loop) == ["Stepping", "MeetConstraints"]  # constraints decode; no repair, redraw
    assert _names(config, constraints=Constraints([])) == _names(config)  # no constraint at all: a free take
    assert _names(config, step=False, repair=False, side_redraws=0) == ["Decode"]
    assert _names(config, step=False, constraints=loop) == ["MeetConstraints"]
    assert fixes_for(config, draft=False, step=True, repair=True, constraints=loop, side_redraws=0,
                     redo=None)[0].constrained  # judged once the constraints are met
    config.stepping = replace(STEPPING, steps=0)
    assert _names(config) == ["Decode", "Repair", "SideRedraw"]  # stepping off in the config
    config.stepping = STEPPING
    config.vae = replace(config.vae, feature_dim=251)
    assert _names(config) == ["Decode", "Repair", "SideRedraw"]  # stepping reads 263-d features only


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    pipe = tiny_pipeline(tmp_path_factory.mktemp("tiny"))
    pipe.config.stepping = STEPPING
    return pipe


def _takes(pipe, rows: int = 2, frames: int = 40) -> Takes:
    z = torch.randn(rows, pipe.config.vae.latent_tokens, pipe.config.vae.latent_dim,
                    generator=torch.Generator().manual_seed(0))
    return Takes(z, z.clone(), torch.full((rows,), frames), ["a walk"] * rows, [0] * rows)


def test_each_fix_does_what_its_function_does(pipe):
    takes, n = _takes(pipe), [40, 40]
    decoded = Decode().apply(takes, pipe.decoder)
    np.testing.assert_array_equal(decoded.features, pipe.latents_to_features(takes.latents, takes.lengths))
    repaired = Repair(pipe.config.repair).apply(decoded, pipe.decoder)
    np.testing.assert_array_equal(repaired.features, repair_rows(decoded.features, n, pipe.config.repair))
    assert not np.array_equal(repaired.features, decoded.features)
    stepped = Stepping(STEPPING, pipe.config.repair).apply(takes, pipe.decoder)
    assert stepped.stepped and stepped.sampled is takes.sampled and not takes.stepped
    np.testing.assert_array_equal(stepped.latents, step_feet(pipe.decoder, takes.latents, takes.lengths, STEPPING))
    assert not torch.equal(stepped.latents, takes.latents)
    loop = Constraints([Loop()], steps=2, feature_steps=2)
    met = MeetConstraints(loop, STEPPING).apply(stepped, pipe.decoder)  # the slide in the latent's cost
    np.testing.assert_array_equal(met.features, meet_constraints(pipe.decoder, stepped.latents, stepped.lengths,
                                                                 loop, STEPPING))
    keep = replace(STEPPING, keep_if_less_skating=True)
    met = MeetConstraints(loop, keep).apply(stepped, pipe.decoder)  # stepped and sampled met in one batch
    np.testing.assert_array_equal(met.features, meet_stepped_or_not(pipe.decoder, takes.sampled, stepped.latents,
                                                                    takes.lengths, loop, keep))


def test_a_side_redraw_keeps_the_first_draw_that_uses_the_side(monkeypatch):
    from mld_core.eval import quality

    # each take's joints hold its draw number; a row's verdict per draw: row 0 uses its side at once, row 1 only on
    # its second redraw (the first at least not on the opposite side), row 2 never
    verdicts = {0: ["named"], 1: ["opposite", "neither", "named"], 2: ["opposite", "opposite", "opposite"]}
    def side(prompt, joints, fps):
        return verdicts[int(prompt[-1])][int(joints[0, 0, 0])]

    monkeypatch.setattr(quality, "side_badge", side)
    prompts, asked = ["row 0", "row 1", "row 2"], []

    def redo(rows, k):  # rows made again from draw k, 4 frames long (a shorter take than the first)
        asked.append((rows, k))
        return SimpleNamespace(prompts=[prompts[r] for r in rows], fps=20, lengths=np.full(len(rows), 4),
                               joints=np.full((len(rows), 4, 22, 3), float(k), np.float32),
                               features=np.full((len(rows), 4, 263), float(k), np.float32))

    def first_draws(prompts):
        return Takes(torch.zeros(3, 1, 4), torch.zeros(3, 1, 4), torch.full((3,), 6), prompts, [0, 0, 0],
                     features=np.full((3, 6, 263), -1.0, np.float32), joints=np.zeros((3, 6, 22, 3), np.float32))

    takes = first_draws(prompts)
    out = SideRedraw(2, redo).apply(takes, SimpleNamespace(fps=20))
    assert asked == [([1, 2], 1), ([1, 2], 2)]
    assert out.draws == [0, 2, 0] and takes.draws == [0, 0, 0]
    np.testing.assert_array_equal(out.features[1], np.concatenate([np.full((4, 263), 2.0), np.zeros((2, 263))]))
    np.testing.assert_array_equal(out.joints[1], np.full((6, 22, 3), 2.0))  # frames past the length repeat
    np.testing.assert_array_equal(out.features[2], np.full((6, 263), -1.0))  # no better draw: the first stays
    asked.clear()
    assert SideRedraw(2, redo).apply(first_draws(["row 0"] * 3), SimpleNamespace(fps=20)).draws == [0, 0, 0]
    assert asked == []  # every take uses its side: nothing drawn again


def test_a_call_times_each_fix_it_applied(pipe):
    kw = dict(seed=1, num_inference_steps=2)
    free = pipe("a walk", 2.0, side_redraws=1, **kw).timings
    assert list(free) == ["condition_s", "diffusion_s", "stepping_s", "decode_s", "repair_s", "side_redraws_s",
                          "total_s"]
    directed = pipe("a walk", 2.0, constraints=Constraints([Loop()], steps=1, feature_steps=1), **kw).timings
    assert list(directed) == ["condition_s", "diffusion_s", "stepping_s", "constraints_s", "decode_s", "total_s"]
    plain = pipe("a walk", 2.0, repair=False, side_redraws=0, **kw).timings
    assert list(plain) == ["condition_s", "diffusion_s", "decode_s", "total_s"]
