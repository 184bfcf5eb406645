"""Stepping (mld_core.take_fixes.stepping, step_feet): sampled latents refined so that takes step instead of
sliding, keeping their path, facing and stride."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from mld_core.checkpoint import CheckpointError, load_config
from mld_core.eval.quality import foot_skating_ratio
from mld_core.motion.features import features_to_joints
from mld_core.take_fixes.meet_constraints import meet_constraints
from mld_core.take_fixes.repair import repair_rows
from mld_core.take_fixes.stepping import (SteppingConfig, keep_cost, keep_less_skating, slide_cost, sliding_share,
                                         step_feet, stride, facing, valid_frames)
from mld_core.testing import tiny_model

WALK = "dataset-2_walk-turn-left_normal_027"
ON = SteppingConfig(steps=10)


@pytest.fixture
def walk(fixtures):
    joints = np.load(fixtures / "rigs" / "source_takes.npz")[f"{WALK}_joints"]
    return torch.tensor(joints, dtype=torch.float32)[None]  # (1, T, 22, 3)


def _drifted(joints, metres_per_frame=0.03):
    """The whole body drifting sideways: every planted foot slides."""
    out = joints.clone()
    out[..., 0] += metres_per_frame * torch.arange(joints.shape[1], dtype=joints.dtype)[None, :, None]
    return out


def test_a_sliding_foot_costs_and_a_planted_one_hardly(walk):
    valid = valid_frames(torch.tensor([walk.shape[1]]), walk.shape[1])
    real, slid = slide_cost(walk, valid, ON), slide_cost(_drifted(walk), valid, ON)
    assert float(slid) > float(real) + 0.5  # (the real walk's toes also cost a little as they push off and land)
    assert float(sliding_share(_drifted(walk), valid, ON)) > 0.9 > 0.2 > float(sliding_share(walk, valid, ON))
    lifted = walk.clone()
    lifted[:, :, [7, 8, 10, 11], 1] += 0.2  # feet in the air never slide on the floor ...
    lifted[:, 0, [10], 1] -= 0.2  # (the floor is the take's lowest toe: one stays down at frame 0)
    assert float(slide_cost(_drifted(lifted), valid, ON)) < 0.05 * float(slid)


def test_frames_beyond_a_take_are_ignored(walk):
    T = walk.shape[1]
    padded = torch.cat([walk, torch.randn(1, 30, 22, 3)], dim=1)
    valid = valid_frames(torch.tensor([T]), T + 30)
    np.testing.assert_allclose(slide_cost(padded, valid, ON), slide_cost(walk, valid[:, :T], ON), rtol=1e-5)
    np.testing.assert_allclose(keep_cost(padded, padded, valid, ON), keep_cost(walk, walk, valid[:, :T], ON),
                               rtol=1e-5, atol=1e-7)


def _turning(joints, degrees_per_frame=1.0):
    """The take turning on the spot about its first root position, a little more every frame."""
    angle = torch.deg2rad(torch.arange(joints.shape[1], dtype=joints.dtype) * degrees_per_frame)[None, :, None]
    x, z = joints[..., 0] - joints[:, :1, :1, 0], joints[..., 2] - joints[:, :1, :1, 2]
    out = joints.clone()
    out[..., 0] = joints[:, :1, :1, 0] + torch.cos(angle) * x + torch.sin(angle) * z
    out[..., 2] = joints[:, :1, :1, 2] - torch.sin(angle) * x + torch.cos(angle) * z
    return out


def test_keeping_costs_only_a_changed_velocity_turn_or_a_shorter_stride(walk):
    valid = valid_frames(torch.tensor([walk.shape[1]]), walk.shape[1])
    cfg = replace(ON, support_weight=0.0)
    assert abs(float(keep_cost(walk, walk, valid, cfg))) < 1e-6
    only = {name: replace(cfg, **{w: 0.0 for w in ("velocity_weight", "turn_weight", "stride_weight") if w != name})
            for name in ("velocity_weight", "turn_weight", "stride_weight")}
    drifted = _drifted(walk, 0.02)  # 2 cm a frame sideways: (2 cm)^2 off in every frame
    assert float(keep_cost(drifted, walk, valid, only["velocity_weight"])) == pytest.approx(4.0, rel=1e-3)
    assert abs(float(keep_cost(drifted, walk, valid, only["turn_weight"]))) < 1e-6
    turning = _turning(walk, 2.0)  # 2 degrees a frame more: (2 degrees)^2 off in every frame
    assert float(keep_cost(turning, walk, valid, only["turn_weight"])) == pytest.approx(4.0, rel=1e-2)
    across = facing(walk)
    longer, shorter = walk.clone(), walk.clone()
    for joints, scale in ((longer, 1.5), (shorter, 0.5)):  # the legs' fore-aft spread around the pelvis
        joints[:, :, [7, 8]] = walk[:, :, [0]] + scale * (walk[:, :, [7, 8]] - walk[:, :, [0]])
    strides = [float(stride(j, across, valid)) for j in (longer, walk, shorter)]
    assert strides[0] > strides[1] > strides[2]
    assert abs(float(keep_cost(longer, walk, valid, only["stride_weight"]))) < 1e-6
    assert float(keep_cost(shorter, walk, valid, only["stride_weight"])) > 1.0


def _pipe(tmp_path, **stepping):
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained(tiny_model(tmp_path / "m"))
    pipe.config.stepping = SteppingConfig(**{"steps": 10, **stepping})
    return pipe


def _total_cost(pipe, z, lengths):
    cfg = pipe.config.stepping
    with torch.inference_mode():
        feats = torch.tensor(pipe.latents_to_features(z, lengths))
    joints = features_to_joints(feats)
    valid = valid_frames(lengths, joints.shape[1])
    return slide_cost(joints, valid, cfg), joints


@pytest.mark.parametrize("lr, gain", [(0.05, 0.9), (1.0, 1.0)])  # 1.0: too big a step to descend
def test_stepping_lowers_the_cost_and_never_raises_a_takes(tmp_path, lr, gain):
    pipe = _pipe(tmp_path, min_slide_share=0.0, lr=lr, steps=30)
    cfg = pipe.config.stepping
    z = torch.randn(3, 1, 32, generator=torch.Generator().manual_seed(0))
    lengths = torch.tensor([60, 48, 60])
    stepped = step_feet(pipe.decoder, z, lengths, pipe.config.stepping)
    slide_before, sample = _total_cost(pipe, z, lengths)
    slide_after, joints = _total_cost(pipe, stepped, lengths)
    valid = valid_frames(lengths, joints.shape[1])
    before = slide_before + keep_cost(sample, sample, valid, cfg)
    moved = cfg.prior_weight * ((stepped - z) ** 2).mean(dim=(1, 2))
    after = slide_after + keep_cost(joints, sample, valid, cfg) + moved
    assert (after <= before + 1e-6).all(), (before, after)  # each row keeps its best latent, the sample included
    assert after.sum() <= gain * before.sum() + 1e-6
    single = step_feet(pipe.decoder, z[1:2], lengths[1:2], pipe.config.stepping)
    np.testing.assert_allclose(single, stepped[1:2], atol=1e-4)  # a batch equals single runs (to float rounding)


def test_constrained_takes_and_sequence_segments_are_stepped_too(tmp_path):
    from mld_core.take_fixes.constraints import Constraints, RootPath

    pipe = _pipe(tmp_path, min_slide_share=0.0, lr=0.05)
    path = Constraints([RootPath([0, 39], np.array([[0.0, 0.0], [0.0, 1.0]]))], steps=2, feature_steps=2)
    kw = dict(seed=1, num_inference_steps=2, repair=False)
    stepped = pipe("a walk", 2.0, constraints=path, step=True, **kw)
    assert "stepping_s" in stepped.timings
    assert "stepping_s" not in pipe("a walk", 2.0, constraints=path, **kw).timings  # step follows repair
    no_slide = pipe("a walk", 2.0, constraints=replace(path, slide_weight=0.0), step=True, **kw)
    assert not np.allclose(stepped.features, no_slide.features)  # the feet's slide is in the constraints' cost
    segments = [("a walk", 2.0), ("a run", 2.0)]
    on, off = (pipe.sequence(segments, step=s, **kw) for s in (True, False))
    assert not np.allclose(on.features, off.features)
    one = pipe.sequence(segments[:1], step=True, **kw)  # a sequence of one segment is its free take, stepped
    np.testing.assert_array_equal(one.features[0], pipe("a walk", 2.0, step=True, **kw).features[0])


def test_takes_that_hardly_slide_are_left_as_sampled(tmp_path):
    pipe = _pipe(tmp_path, min_slide_share=1.01)
    z = torch.randn(2, 1, 32, generator=torch.Generator().manual_seed(0))
    np.testing.assert_array_equal(step_feet(pipe.decoder, z, torch.tensor([60, 60]), pipe.config.stepping), z)


def test_the_pipeline_steps_free_final_takes_only(tmp_path):
    pipe = _pipe(tmp_path, min_slide_share=0.0, lr=0.05, steps=30)
    kw = dict(seed=[1, 2], num_inference_steps=2)
    on = pipe(["a walk", "a run"], 3.0, **kw)
    assert "stepping_s" in on.timings
    raw = pipe(["a walk", "a run"], 3.0, repair=False, **kw)
    assert "stepping_s" not in raw.timings
    pipe.config.stepping = replace(pipe.config.stepping, steps=0)
    off = pipe(["a walk", "a run"], 3.0, **kw)
    assert "stepping_s" not in off.timings
    assert not np.allclose(on.features, off.features)
    repaired = repair_rows(raw.features, raw.lengths.tolist(), pipe.config.repair)
    np.testing.assert_allclose(off.features, repaired, atol=1e-5)


def _repaired_skating(pipe, features, lengths):
    """Each take's foot skating ratio once the features (not yet repaired) are repaired."""
    n = lengths.tolist()
    joints = pipe.joints_from_features(repair_rows(features, n, pipe.config.repair), n)
    return np.array([foot_skating_ratio(j[:k], pipe.config.fps) for j, k in zip(joints, n)])


def test_a_take_keeps_whichever_latent_skates_less_once_repaired(tmp_path):
    pipe = _pipe(tmp_path)
    lengths = torch.tensor([60, 48, 60, 40, 60, 52])
    sampled = torch.randn(6, 1, 32, generator=torch.Generator().manual_seed(0))
    other = sampled + 2.0 * torch.randn(6, 1, 32, generator=torch.Generator().manual_seed(1))
    other[2] = sampled[2]  # a take stepping left as sampled
    kept = keep_less_skating(pipe.decoder, sampled, other, lengths, pipe.config.repair)
    with torch.inference_mode():
        skate = {name: _repaired_skating(pipe, pipe.latents_to_features(z, lengths), lengths)
                 for name, z in (("sampled", sampled), ("other", other), ("kept", kept))}
    took_other = (skate["other"] <= skate["sampled"])
    assert took_other.any() and not took_other.all(), skate  # both outcomes occur in this batch
    for i in range(6):
        np.testing.assert_array_equal(kept[i], other[i] if took_other[i] else sampled[i])
    np.testing.assert_array_equal(skate["kept"], np.minimum(skate["sampled"], skate["other"]))
    single = keep_less_skating(pipe.decoder, sampled[3:5], other[3:5], lengths[3:5], pipe.config.repair)
    np.testing.assert_array_equal(single, kept[3:5])  # a batch equals single runs


def test_the_pipeline_keeps_a_sample_that_skates_less_only_when_asked(tmp_path):
    pipe = _pipe(tmp_path, min_slide_share=0.0, lr=0.5, steps=30)
    kw = dict(seed=list(range(8)), num_inference_steps=2)
    prompts = ["a walk", "a run", "a dash", "a walk"] * 2
    stepped = pipe(prompts, 3.0, **kw)
    pipe.config.stepping = replace(pipe.config.stepping, keep_if_less_skating=True)
    kept = pipe(prompts, 3.0, **kw)
    sampled = pipe(prompts, 3.0, step=False, **kw)
    skate = {name: np.array([foot_skating_ratio(j[:k], pipe.config.fps) for j, k in zip(o.joints, o.lengths)])
             for name, o in (("stepped", stepped), ("kept", kept), ("sampled", sampled))}  # (repaired takes)
    assert (skate["sampled"] < skate["stepped"]).any() and (skate["stepped"] < skate["sampled"]).any(), skate
    np.testing.assert_allclose(skate["kept"], np.minimum(skate["stepped"], skate["sampled"]), atol=1e-9)
    for i in range(8):
        assert np.allclose(kept.features[i], stepped.features[i]) or np.allclose(kept.features[i], sampled.features[i])


def test_a_stepped_take_left_unrepaired_is_judged_as_its_repairs_would_leave_it(tmp_path):
    pipe = _pipe(tmp_path, min_slide_share=0.0, lr=0.5, steps=30, keep_if_less_skating=True)
    kw = dict(seed=list(range(8)), num_inference_steps=2, repair=False)  # as a sequence's first segment
    prompts = ["a walk", "a run", "a dash", "a walk"] * 2
    kept, sampled = pipe(prompts, 3.0, step=True, **kw), pipe(prompts, 3.0, step=False, **kw)
    pipe.config.stepping = replace(pipe.config.stepping, keep_if_less_skating=False)
    stepped = pipe(prompts, 3.0, step=True, **kw)
    lengths = torch.as_tensor(kept.lengths)
    skate = {name: _repaired_skating(pipe, o.features, lengths)
             for name, o in (("stepped", stepped), ("kept", kept), ("sampled", sampled))}
    assert (skate["sampled"] < skate["stepped"]).any() and (skate["stepped"] < skate["sampled"]).any(), skate
    np.testing.assert_allclose(skate["kept"], np.minimum(skate["stepped"], skate["sampled"]), atol=1e-9)


def _met_and_skating(pipe, out, constraints):
    rows = [(sum(ok for *_, ok in constraints.residuals(j[:n])), foot_skating_ratio(j[:n], pipe.config.fps))
            for j, n in zip(out.joints, out.lengths)]
    return np.array([m for m, _ in rows]), np.array([s for _, s in rows])


def test_a_constrained_take_keeps_the_unstepped_one_only_if_it_skates_less_and_meets_as_much(tmp_path):
    from mld_core.take_fixes.constraints import Constraints, Loop, RootPath

    pipe = _pipe(tmp_path, min_slide_share=0.0, lr=0.5, steps=30)
    outcomes = []
    # the contact channels alone hold feet (planted_toe_height_m 0): with this tiny model's low toes held too, none
    # of these 16 unstepped takes skates less than its stepped one, and the rule's other outcome would not occur
    for constraints in (Constraints([Loop()], steps=3, feature_steps=3, planted_toe_height_m=0.0),
                        Constraints([RootPath([0, 59], np.array([[0.0, 0.0], [0.0, 0.3]]))], steps=3,
                                    feature_steps=3, planted_toe_height_m=0.0)):
        kw = dict(seed=list(range(8)), num_inference_steps=2, constraints=constraints)
        prompts = ["a walk", "a run", "a dash", "a walk"] * 2
        stepped = pipe(prompts, 3.0, **kw)
        sampled = pipe(prompts, 3.0, step=False, **kw)
        pipe.config.stepping = replace(pipe.config.stepping, keep_if_less_skating=True)
        kept = pipe(prompts, 3.0, **kw)
        pipe.config.stepping = replace(pipe.config.stepping, keep_if_less_skating=False)
        (met_st, sk_st), (met_sa, sk_sa), (met_k, sk_k) = (_met_and_skating(pipe, o, constraints)
                                                           for o in (stepped, sampled, kept))
        took_sample = (met_sa >= met_st) & (sk_sa < sk_st)
        outcomes += took_sample.tolist()
        for i in range(8):  # each row is its stepped or its unstepped take, by the rule
            np.testing.assert_allclose(kept.features[i], (sampled if took_sample[i] else stepped).features[i],
                                       atol=1e-4)
        assert (met_k >= met_st).all() and (sk_k <= sk_st).all()
    assert any(outcomes) and not all(outcomes), outcomes  # both outcomes occur


def test_meeting_with_and_without_the_slide_in_one_batch_equals_meeting_each_alone(tmp_path):
    from mld_core.take_fixes.constraints import Constraints, Loop

    pipe = _pipe(tmp_path, min_slide_share=0.0, lr=0.5, steps=30)
    constraints = Constraints([Loop()], steps=4, feature_steps=4)
    z = torch.randn(3, pipe.config.vae.latent_tokens, pipe.config.vae.latent_dim,
                    generator=torch.Generator().manual_seed(0))
    lengths = torch.tensor([40, 40, 40])
    slide = torch.tensor([True, False, True])
    both = meet_constraints(pipe.decoder, z, lengths, constraints, pipe.config.stepping, slide_rows=slide)
    with_slide = meet_constraints(pipe.decoder, z, lengths, constraints, pipe.config.stepping)
    without = meet_constraints(pipe.decoder, z, lengths, constraints)
    assert np.abs(with_slide[1] - without[1]).max() > 1e-3  # the slide changes the take: the mask can fail
    for row in range(3):
        np.testing.assert_allclose(both[row], (with_slide if slide[row] else without)[row], atol=1e-4)


def test_a_stepped_walk_backwards_of_the_bundled_model_skates_less():
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained()
    assert pipe.config.stepping.steps > 0
    prompts = ["a person walks backwards", "a person dashes forward"]
    stepped = pipe(prompts, 4.0, seed=0, num_variants=2)
    pipe.config.stepping = replace(pipe.config.stepping, steps=0)
    sampled = pipe(prompts, 4.0, seed=0, num_variants=2)
    skate = [np.mean([foot_skating_ratio(o.joints[i, : o.lengths[i]]) for i in range(4)]) for o in (stepped, sampled)]
    assert skate[0] < 0.75 * skate[1], skate


@pytest.mark.slow
def test_walks_on_a_path_walk_cycles_and_sequences_of_the_bundled_model_skate_less_stepped():
    from mld_core.take_fixes.constraints import Constraints, Loop, RootPath
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained()
    path = Constraints([RootPath([0, 79], np.array([[0.0, 0.0], [0.0, 4.8]]))])  # 1.2 m/s straight ahead for 4 s
    segments = [("a person walks forward", 3.0), ("a person turns left and walks", 3.0)]
    skate = {}
    for step in (True, False):
        on_path = pipe("a person walks forward", 4.0, seed=0, num_variants=4, constraints=path, step=step)
        cycles = pipe("a person walks forward", 2.0, seed=0, num_variants=4, constraints=Constraints([Loop()]),
                      step=step)
        assert all(met for out in (on_path, cycles) for row in out.residuals for _, _, met in row)
        sequences = [pipe.sequence(segments, seed=seed, step=step).joints[0] for seed in (0, 1)]
        skate[step] = np.array([np.mean([foot_skating_ratio(j) for j in takes])
                                for takes in (on_path.joints, cycles.joints, sequences)])
    assert (skate[True] < 0.8 * skate[False]).all(), skate


@pytest.mark.parametrize("stepping, words", [("on", "JSON object"), ({"steps": 2.5}, "whole number"),
                                             ({"steps": -1}, "whole number"), ({"lr": 0}, "above 0"),
                                             ({"prior_weight": float("nan")}, ">= 0"), ({"feet": 1}, "feet"),
                                             ({"keep_if_less_skating": "yes"}, "true or false")])
def test_a_bad_stepping_entry_is_a_checkpoint_error(tmp_path, stepping, words):
    model = tiny_model(tmp_path / "m")
    config = json.loads((model / "config.json").read_text())
    (model / "config.json").write_text(json.dumps({**config, "stepping": stepping}))
    with pytest.raises(CheckpointError, match=words):
        load_config(model)


def test_a_model_folder_without_a_stepping_entry_does_not_step(tmp_path):
    model = tiny_model(tmp_path / "m")
    config = json.loads((model / "config.json").read_text())
    config.pop("stepping", None)
    (model / "config.json").write_text(json.dumps(config))
    assert load_config(model).stepping.steps == 0
