"""Directing a take: poses to hit, a root path, a loop (mld_core.take_fixes.constraints through MLDPipeline), and the
command line's --keys / --path / --loop with their bad-input answers. Tiny seeded model: its motions are noise, but the
constraints must still be met, and the free path must not change."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mld_core.cli import main
from mld_core.inputs import InputError
from mld_core.take_fixes.constraints import Constraints, Loop, PoseKeys, RootPath, bone_stretch, read_keys, read_path
from mld_core.take_fixes.meet_constraints import meet_constraints
from mld_core.motion import skeleton as sk
from mld_core.motion.skeleton import JOINT_NAMES
from mld_core.testing import tiny_model
from test_reliability import refused

REPO = Path(__file__).resolve().parents[1]

J = {n: i for i, n in enumerate(JOINT_NAMES)}
# The tiny model's std is 0.05 everywhere: its features move 20x slower per step than the bundled model's.
TINY = dict(feature_steps=300, feature_lr=0.5)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return tiny_model(tmp_path_factory.mktemp("tiny") / "model")


@pytest.fixture(scope="module")
def pipe(model):
    from mld_core.pipeline import MLDPipeline

    return MLDPipeline.from_pretrained(model)


def test_pose_keys_are_hit_and_the_free_path_is_unchanged(pipe):
    free = pipe("a person walks", seconds=3, seed=1, num_inference_steps=4)
    again = pipe("a person walks", seconds=3, seed=1, num_inference_steps=4, constraints=Constraints([]))
    np.testing.assert_array_equal(free.joints, again.joints)  # no constraint: the plain path, bit for bit
    targets = {10: {"pelvis": [0.2, 0.9, 0.5], "left_wrist": [0.5, 1.4, 0.6]},
               45: {"pelvis": [0.0, 0.85, 1.2], "right_ankle": [-0.1, 0.05, 1.3]}}
    out = pipe("a person walks", seconds=3, seed=1, num_inference_steps=4,
               constraints=Constraints([PoseKeys(targets)], **TINY))
    errors = [np.linalg.norm(out.joints[0, f, J[j]] - p) for f, keyed in targets.items() for j, p in keyed.items()]
    before = [np.linalg.norm(free.joints[0, f, J[j]] - p) for f, keyed in targets.items() for j, p in keyed.items()]
    assert np.mean(errors) < 0.03 < np.mean(before), (errors, before)
    kind, residual, met = out.residuals[0][0]
    assert kind == "PoseKeys" and met and residual == pytest.approx(np.mean(errors), abs=1e-4)


def test_root_path_and_loop(pipe):
    path = RootPath([0, 59], np.array([[0.0, 0.0], [0.0, 2.0]]))  # 2 m straight ahead in 3 s
    out = pipe("a person walks", seconds=3, seed=2, num_inference_steps=4, constraints=Constraints([path], **TINY))
    frames, xz = path.dense()
    assert np.linalg.norm(out.joints[0, frames, 0][:, [0, 2]] - xz, axis=-1).mean() < 0.10
    # TINY's step of 0.5 overshoots a loop on this model: its residual swings with the float rounding (0.001-0.07
    # over seeds 2-4), where 0.1 meets it within 0.0004 on each
    looped = pipe("a person walks", seconds=3, seed=2, num_inference_steps=4,
                  constraints=Constraints([Loop()], feature_steps=300, feature_lr=0.1))
    assert looped.residuals[0][0][1] < 0.02
    free = pipe("a person walks", seconds=3, seed=2, num_inference_steps=4)
    assert Loop().residual(free.joints[0]) > 0.05  # the free take does not loop by itself


def test_a_constrained_batch_equals_single_runs(pipe):
    looped = Constraints([Loop()], steps=3, feature_steps=20)
    kw = dict(seconds=3, num_inference_steps=2, constraints=looped, step=False)
    batch = pipe(["a person walks", "a person runs", "a person waves"], seed=[4, 5, 6], **kw)
    single = pipe("a person runs", seed=5, **kw)
    # the planted feet: per take. 20 Adam steps on the features amplify the float differences of batched and
    # single matrix products (1e-6 before them) to 2e-4 on CPUs with AMX, so the bound is 1e-3; takes differ by 0.19
    np.testing.assert_allclose(single.features[0], batch.features[1], atol=1e-3)
    assert np.abs(single.features[0] - batch.features[0]).max() > 1e-2  # the bound tells takes apart


def test_each_takes_planted_feet_count_on_their_own():
    import torch

    from mld_core.take_fixes.constraints import planted_foot_speed

    joints = torch.randn(2, 10, 22, 3, generator=torch.Generator().manual_seed(0))
    contacts = torch.zeros(2, 10, 4, dtype=torch.bool)
    contacts[0, :, 0] = True  # one foot planted throughout in the first take, all four in the second
    contacts[1] = True
    singles = [planted_foot_speed(joints[i:i + 1], contacts[i:i + 1]) for i in range(2)]
    torch.testing.assert_close(planted_foot_speed(joints, contacts), (singles[0] + singles[1]) / 2)


def test_toes_near_the_floor_are_held_as_well_as_the_planted_channels():
    import torch

    from mld_core.take_fixes.constraints import planted_feet
    from mld_core.motion.features import FOOT_CONTACT, features_to_joints

    features = np.load(REPO / "tests" / "fixtures" / "humanml3d" / "new_joint_vecs_012314.npy").astype(np.float32)
    x = torch.from_numpy(features)[None]  # (1, T, 263)
    channels = planted_feet(x)[0].numpy()  # (T, 4)
    np.testing.assert_array_equal(channels, features[:, FOOT_CONTACT] > 0.5)
    held = planted_feet(x, 0.05)[0].numpy()
    toes = features_to_joints(features)[:, [10, 11], 1]  # (T, 2) left, right toe heights
    low = toes - toes.min() < 0.05
    np.testing.assert_array_equal(held[:, [0, 2]], channels[:, [0, 2]])  # ankles: the channels alone
    np.testing.assert_array_equal(held[:, [1, 3]], channels[:, [1, 3]] | low)
    assert (held & ~channels).any()  # this clip's channels miss some low toe frames


def test_the_feet_slide_weighs_less_with_pose_keys():
    path, keys = RootPath([0, 39], np.array([[0.0, 0.0], [0.0, 1.0]])), PoseKeys({10: {"pelvis": [0.0, 0.9, 0.0]}})
    assert Constraints([path, Loop()]).latent_slide_weight() == Constraints().slide_weight
    assert Constraints([path, keys]).latent_slide_weight() == Constraints().keyed_slide_weight
    assert Constraints([keys], keyed_slide_weight=0.5).latent_slide_weight() == 0.5


def test_constraints_beyond_the_take_are_refused(pipe):
    with pytest.raises(InputError, match="reaches frame 80"):
        pipe("a person walks", seconds=3, num_inference_steps=2, constraints=Constraints([PoseKeys({80: {"head": [0, 1, 0]}})]))
    with pytest.raises(InputError, match="same length"):
        pipe(["walk", "run"], seconds=[2, 3], num_inference_steps=2, constraints=Constraints([Loop()]))


def test_key_and_path_files(tmp_path):
    (tmp_path / "k.json").write_text(json.dumps({"fps": 40, "keys": [{"frame": 80, "joints": {"head": [0, 1.6, 1]}}]}))
    keys = read_keys(tmp_path / "k.json")
    assert keys.targets == {40: {"head": [0.0, 1.6, 1.0]}}  # frame 80 at 40 fps is model frame 40
    (tmp_path / "p.json").write_text(json.dumps({"points": [[0, 0, 0], [20, 0.5, 1.0]]}))
    assert read_path(tmp_path / "p.json").frames == [0, 20]


@pytest.mark.slow
def test_generate_with_keys_path_and_loop(tmp_path, capsys):  # the bundled model
    (tmp_path / "k.json").write_text(json.dumps({"keys": [{"frame": 30, "joints": {"left_wrist": [0.4, 1.5, 0.3]}}]}))
    (tmp_path / "far.json").write_text(json.dumps({"keys": [{"frame": 30, "joints": {"left_wrist": [40, 1.5, 0]}}]}))
    (tmp_path / "p.json").write_text(json.dumps({"fps": 20, "points": [[0, 0, 0], [39, 0.0, 1.5]]}))
    gen = ["generate", "a person waves", "--steps", "10", "--seconds", "2"]
    assert main([*gen, "--keys", str(tmp_path / "k.json"), "--path", str(tmp_path / "p.json"), "--loop",
                 "--out", str(tmp_path / "t.npz")]) == 0
    joints = np.load(tmp_path / "t.npz")["joints"][0]
    assert np.linalg.norm(joints[30, J["left_wrist"]] - [0.4, 1.5, 0.3]) < 0.05
    capsys.readouterr()
    # out of reach: the best effort is written, with one warning naming the residual
    assert main([*gen, "--keys", str(tmp_path / "far.json"), "--out", str(tmp_path / "far.npz")]) == 0
    err = capsys.readouterr().err
    assert "the PoseKeys constraint is off by" in err and "Traceback" not in err
    assert (tmp_path / "far.npz").is_file()


@pytest.mark.parametrize("content, words", [
    ("{broken", "not valid JSON"),
    (json.dumps({"keys": []}), "expected"),
    (json.dumps({"keys": [{"frame": 10, "joints": {"tail": [0, 0, 0]}}]}), "unknown joint 'tail'"),
    (json.dumps({"keys": [{"frame": 10, "joints": {"head": [0, "x", 0]}}]}), "must be a number"),
    (json.dumps({"keys": [{"frame": -1, "joints": {"head": [0, 1, 0]}}]}), "frame must be 0 or more"),
    (json.dumps({"keys": [{"frame": 500, "joints": {"head": [0, 1, 0]}}]}), "reaches frame 500"),
    (json.dumps({"fps": 0, "keys": [{"frame": 5, "joints": {"head": [0, 1, 0]}}]}), "fps must be between"),
], ids=["json", "empty", "joint", "number", "negative", "beyond", "fps"])
def test_generate_refuses_bad_key_files(model, tmp_path, capsys, content, words):
    (tmp_path / "k.json").write_text(content)
    refused(["generate", "a person waves", "--model", model, "--keys", tmp_path / "k.json", "--out",
             tmp_path / "t.npz"], tmp_path, capsys, words)


def test_generate_refuses_bad_paths(model, tmp_path, capsys):
    (tmp_path / "p.json").write_text(json.dumps({"points": [[10, 0, 0], [5, 1, 1]]}))
    refused(["generate", "a walk", "--model", model, "--path", tmp_path / "p.json", "--out", tmp_path / "t.npz"],
            tmp_path, capsys, "frames must increase")
    (tmp_path / "p.json").write_text(json.dumps({"points": [[0, 0, 0], [5, 1, 1]]}))
    refused(["generate", "a walk", "--model", model, "--path", tmp_path / "p.json", "--out", tmp_path / "p.json"],
            tmp_path, capsys, "same file")


def test_a_sequence_is_one_continuous_motion(pipe):
    from mld_core.eval.quality import REAL_JERK_P95, largest_joint_jerk, seam_jerk

    # repair=False: the tiny model's skeleton is noise (hips 0.9 m from the pelvis), which no repair can mend
    out = pipe.sequence([("a person walks", 2.0), ("a person waves", 2.0), ("a person bows", 2.0)], seed=3,
                        num_inference_steps=2, repair=False)
    assert out.joints.shape == (1, 120, 22, 3) and out.lengths.tolist() == [120]
    assert out.timings["segments"] == [0, 30, 70]  # a later segment starts with the previous one's last 0.5 s
    # each seam judged on the joined take, over its fade and 3 / 2 frames around it, not by the Continuation's
    # residual before the fade (which read 2-4 cm on the bundled model while a wrist started 43-65 cm away)
    assert out.residuals is None and [(k, within) for k, _, within in out.seams[0]] == [
        (k, jerk <= REAL_JERK_P95) for k, jerk in ((1, seam_jerk(out.joints[0], 30, 10)),
                                                     (2, seam_jerk(out.joints[0], 70, 10)))]
    jerk = largest_joint_jerk(out.joints[0])
    assert [j for _, j, _ in out.seams[0]] == [jerk[27:42].max(), jerk[67:82].max()]
    step = np.linalg.norm(np.diff(out.joints[0], axis=0), axis=-1).max(-1)  # (T-1,) largest joint step per frame
    for start in (30, 70):  # no jump across a cross-faded seam
        assert step[start - 2:start + 12].max() < 3 * np.median(step) + 0.05
    single = pipe.sequence([("a person walks", 2.0)], seed=3, num_inference_steps=2)
    np.testing.assert_array_equal(single.joints[0], pipe("a person walks", 2.0, seed=3, num_inference_steps=2).joints[0])


def test_a_continuation_smooths_only_its_change_so_the_take_keeps_its_own_motion(pipe):
    import torch

    from mld_core.take_fixes.constraints import Continuation
    from mld_core.motion.features import features_to_joints

    lengths = torch.tensor([40])
    z = torch.randn(1, pipe.config.vae.latent_tokens, pipe.config.vae.latent_dim,
                    generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        decoded = pipe.latents_to_features(z, lengths)[0]  # (T, F)
    met = Continuation(features_to_joints(decoded[:10]))  # the take's own first frames: met as decoded

    def shake(features):  # mean squared acceleration of the features: the motion's own swings
        return float((np.diff(features, 2, axis=0) ** 2).mean())

    kept = {}
    for change_only in (False, True):
        c = Constraints([met], steps=0, feature_steps=60, planted_weight=0.0, bone_weight=0.0,
                        smooth_change_only=change_only)
        kept[change_only] = shake(meet_constraints(pipe.decoder, z, lengths, c)[0]) / shake(decoded)
    assert kept[False] < 0.8  # smoothing the features themselves damps the take's own motion ...
    assert kept[True] > 0.95  # ... smoothing only the change keeps it


def test_only_a_loop_keeps_smoothing_the_features_themselves_by_default():
    path = RootPath([0, 10], np.array([[0.0, 0.0], [0.0, 1.0]]))
    assert Constraints([path]).smooths_change_only()
    assert Constraints([PoseKeys({5: {"pelvis": [0.0, 0.9, 0.0]}})]).smooths_change_only()
    assert not Constraints([Loop()]).smooths_change_only()
    assert not Constraints([path, Loop()]).smooths_change_only()  # a loop on a path: its seam decides
    assert Constraints([Loop()], smooth_change_only=True).smooths_change_only()  # an explicit choice wins
    assert not Constraints([path], smooth_change_only=False).smooths_change_only()


def test_a_loop_in_place_keeps_its_own_motion_and_one_that_travels_does_not():
    import torch

    from mld_core.take_fixes.constraints import root_speed
    from mld_core.motion.features import ROOT_LIN_VEL

    features = torch.zeros(3, 40, 263)
    features[0, :, ROOT_LIN_VEL] = torch.tensor([0.0, 0.06])  # 1.2 m/s straight ahead: a walk cycle
    features[1, :, ROOT_LIN_VEL] = torch.tensor([0.003, 0.004])  # 0.1 m/s: a wave that sways
    speed = root_speed(features)
    np.testing.assert_allclose(speed, [1.2, 0.1, 0.0], rtol=1e-6)
    np.testing.assert_array_equal(Constraints([Loop()]).change_only_rows(speed), [False, True, True])
    path = RootPath([0, 10], np.array([[0.0, 0.0], [0.0, 1.0]]))
    assert Constraints([path]).change_only_rows(speed).all()  # no loop: the change only, whatever the speed
    assert not Constraints([Loop()], smooth_change_only=False).change_only_rows(speed).any()  # an explicit choice
    assert Constraints([Loop()], smooth_change_only=True).change_only_rows(speed).all()  # wins either way


def test_generate_sequence_file(model, tmp_path, capsys):
    (tmp_path / "s.json").write_text(json.dumps([{"prompt": "a walk", "seconds": 2}, {"prompt": "a wave", "seconds": 2}]))
    assert main(["generate", "--sequence", str(tmp_path / "s.json"), "--model", str(model), "--steps", "2",
                 "--out", str(tmp_path / "s.npz")]) == 0
    assert np.load(tmp_path / "s.npz")["joints"].shape[:2] == (1, 80)
    err = capsys.readouterr().err  # this tiny model's seam jerks far beyond real motion: one line says so
    assert 'warning: the seam into segment 2 ("a wave") jerks' in err and "Continuation" not in err
    (tmp_path / "long.json").write_text(json.dumps([{"prompt": "a walk", "seconds": 2}, {"prompt": "a run", "seconds": 9.6}]))
    refused(["generate", "--sequence", tmp_path / "long.json", "--model", model, "--out", tmp_path / "x.npz"], tmp_path,
            capsys, "overlap")
    refused(["generate", "--sequence", tmp_path / "s.json", "--variants", "2", "--model", model, "--out",
             tmp_path / "x.npz"], tmp_path, capsys, "drop --variants")
    (tmp_path / "bad.json").write_text(json.dumps([{"prompt": "!!!", "seconds": 2}]))
    refused(["generate", "--sequence", tmp_path / "bad.json", "--model", model, "--out", tmp_path / "x.npz"], tmp_path,
            capsys, "segment 1: the prompt")


def _bone_sd_mm(joints):
    parents = np.asarray(sk.PARENTS)
    return float(np.linalg.norm(joints[:, 1:] - joints[:, parents[1:]], axis=-1).std(axis=0).max() * 1000)


def test_bone_stretch_is_zero_on_the_reference_skeleton():
    import torch

    joints = torch.zeros(1, 3, 22, 3, dtype=torch.float64)  # (B, T, 22, 3) the reference skeleton at rest
    for k in range(1, 22):
        joints[:, :, k] = joints[:, :, sk.PARENTS[k]] + torch.as_tensor(sk.REFERENCE_OFFSETS[k])
    assert float(bone_stretch(joints)) < 1e-12
    stretched = joints.clone()
    stretched[:, :, 7] += torch.tensor([0.0, -0.1, 0.0], dtype=torch.float64)  # a left shin 10 cm longer
    stretched[:, :, 10] += torch.tensor([0.0, -0.1, 0.0], dtype=torch.float64)  # its foot moves along
    assert float(bone_stretch(stretched)) == pytest.approx(0.1 ** 2 / 21, rel=1e-6)


@pytest.mark.slow
def test_a_walk_on_a_path_keeps_its_legs_and_its_footing():  # the bundled model
    from mld_core.eval.quality import foot_skating_ratio
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained()
    path = RootPath([0, 79], np.array([[0.0, 0.0], [0.0, 4.8]]))  # 1.2 m/s straight ahead for 4 s
    pipe.config.stepping = replace(pipe.config.stepping, steps=0)  # the constraints alone (no stepping): compare with
    free = pipe("a person walks forward", seconds=4, seed=0, num_variants=8)  # free takes sampled the same way
    out = pipe("a person walks forward", seconds=4, seed=0, num_variants=8, constraints=Constraints([path]))
    assert all(met for row in out.residuals for _, _, met in row)
    # without the bone term the planted-feet term stretches the legs: bone SD 57 mm, skating 2.4x free over these 8
    # takes on v3.2, 3.1x on v3.3; with it 1.23x on v3.1, 1.25x on v3.2, 1.68x on v3.3 (the bound was 2.0x then),
    # 1.23x on v3.4 (path 0.210, free 0.171; docs/evaluation.md, "v3.3" and "v3.4"), 1.40x on v3.6 (the bound was
    # 1.5x then); with the toes near the floor held too (Constraints.planted_toe_height_m) 0.20x on v3.6 (path 0.035,
    # free 0.172), 0.62x on seeds 100-107 (1.76x before)
    assert max(_bone_sd_mm(j) for j in out.joints) < 5.0
    skating = np.mean([foot_skating_ratio(j) for j in out.joints])
    assert skating <= np.mean([foot_skating_ratio(j) for j in free.joints])


@pytest.mark.slow
def test_stepped_paths_and_loops_keep_their_feet_planted():  # the bundled model
    from mld_core.eval.quality import foot_skating_ratio
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained()
    bend = RootPath([0, 40, 79], np.array([[0.0, 0.0], [0.0, 2.4], [-2.0, 4.0]]))
    for prompt, seconds, item, bound in (("a person walks forward", 4, bend, 0.05),
                                         ("a person walks forward", 2, Loop(), 0.10),
                                         ("a person runs forward", 2, Loop(), 0.08)):
        out = pipe(prompt, seconds=seconds, seed=0, num_variants=8, constraints=Constraints([item]))
        assert all(met for row in out.residuals for _, _, met in row)
        # the feet's slide in the latent stage's cost (Constraints.slide_weight; research/directed_skating.py): on
        # v3.4, seeds 0-7, the bend skated 0.085 and the walk cycle 0.157 at weight 0.03, 0.006 and 0.054 at 1.0; and the
        # toes near the floor held in the feature stage (Constraints.planted_toe_height_m): on v3.6 the run cycle
        # skated 0.128 with the contact channels alone, 0.064 with them (real runs 0.07)
        assert np.mean([foot_skating_ratio(j) for j in out.joints]) <= bound


@pytest.mark.slow
def test_a_looped_wave_still_waves():  # the bundled model
    from mld_core.eval import physical
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained()
    out = pipe("a person waves the right hand", seconds=3, seed=0, num_variants=8, constraints=Constraints([Loop()]))
    assert all(met for row in out.residuals for _, _, met in row)
    # smoothing the features themselves, as a run cycle's seam needs, flattened the wave: 2 of 8 waved on v3.6 (6 of 8
    # with only the change kept smooth, for takes in place: docs/control.md)
    assert sum(physical.passes(j[:n], "wave-right-hand") for j, n in zip(out.joints, out.lengths)) >= 4


@pytest.mark.slow
def test_a_sequence_segment_may_reverse_the_previous_one():  # the bundled model
    from mld_core.eval import physical
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained()
    out = pipe.sequence([("a person runs forward", 3.0), ("a person walks backwards", 3.0)], seed=0)
    start = out.timings["segments"][1] + 10  # the walk backwards' own frames, after the half-second overlap
    # a continuation that pinned the root to the run's speed, or planted feet, made this segment stand still
    assert physical.passes(out.joints[0, start:], "walk-back")


@pytest.mark.slow
def test_a_wave_after_a_walk_still_waves():  # the bundled model
    from mld_core.eval import physical
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained()
    waved = []
    for seed in range(8):
        out = pipe.sequence([("a person walks forward", 3.0), ("a person waves the right hand", 2.0)], seed=seed)
        start = out.timings["segments"][1] + 10  # the wave's own 2 s, after the half second it repeats
        waved.append(physical.passes(out.joints[0, start:], "wave-right-hand"))
    # smoothing the whole segment in the continuation's feature stage damped the swings: 2 of 8 waved (free 2 s
    # takes of the prompt: 13 of 16); smoothing only the change: 6 of 8
    assert sum(waved) >= 5, waved


def test_python_readers_and_jobs_use_the_one_json_reader(tmp_path):
    """read_keys / read_path from Python take the same limits as the command line, and a job's loop is a real switch."""
    from mld_core.inputs import InputError
    from mld_core.take_fixes import constraints as C

    deep = tmp_path / "deep.json"
    deep.write_text("[" * 5000 + "]" * 5000)
    with pytest.raises(InputError, match="nested more than"):
        C.read_keys(deep)
    huge = tmp_path / "huge.json"
    huge.write_text('{"fps": 20, "keys": [{"frame": 1e308, "joints": {"head": [0, 1.7, 0]}}]}')
    with pytest.raises(InputError, match="finite number"):
        C.read_keys(huge)
    with pytest.raises(InputError, match="loop must be true or false"):
        C.constraints_from_job({"loop": "false"}, "job 1")
    assert C.constraints_from_job({"loop": False}, "job 1").items == []
    assert [type(i).__name__ for i in C.constraints_from_job({"loop": True}, "job 1").items] == ["Loop"]
