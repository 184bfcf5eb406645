"""Prompt coverage, take-quality badges and best-of-N ranking (mld_core.condition.coverage, mld_core.eval.quality), and
the generate CLI's --strict / --best."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mld_core.condition import coverage
from mld_core.checkpoint import DEFAULT_MODEL_DIR, CheckpointError
from mld_core.eval import quality
from mld_core.motion import skeleton as sk

FPS = 20


# -- synthetic motions with known answers ---------------------------------------------------------------------------
def standing(frames: int = 41) -> np.ndarray:
    """The reference skeleton standing still, lowest toe on the floor (y = 0): (T, 22, 3)."""
    pose = np.zeros((22, 3))
    for j, parent in enumerate(sk.PARENTS):
        if parent >= 0:
            pose[j] = pose[parent] + sk.REFERENCE_OFFSETS[j]
    pose[:, 1] -= pose[[10, 11], 1].min()
    return np.repeat(pose[None], frames, axis=0)


def test_a_body_sliding_for_half_the_take_skates_half_the_frame_pairs():
    joints = standing(41)
    x = np.minimum(np.arange(41), 20) / FPS * 1.0  # 1 m/s over frame pairs 0-19, then still
    joints[:, :, 0] += x[:, None]
    assert quality.foot_skating_ratio(joints, FPS) == pytest.approx(20 / 40)
    slow = standing(41)
    slow[:, :, 0] += (np.arange(41) / FPS * 0.4)[:, None]  # 0.4 m/s: below the 0.5 m/s threshold
    assert quality.foot_skating_ratio(slow, FPS) == 0.0
    lifted = joints.copy()
    lifted[:, 10, 1] += 0.2  # one toe in the air: the other still skates
    assert quality.foot_skating_ratio(lifted, FPS) == pytest.approx(0.5)
    both = joints.copy()
    both[:, [10, 11], 1] += 0.06  # the floor is the take's lowest toe: raising both toes throughout changes nothing
    assert quality.foot_skating_ratio(both, FPS) == pytest.approx(0.5)


def test_a_body_lifted_10_cm_floats_and_a_body_sunk_3_cm_penetrates():
    still = standing()
    assert quality.foot_float(still, FPS) == 0.0 and quality.ground_penetration_cm(still) == 0.0
    lifted = still + np.array([0.0, 0.10, 0.0])
    assert quality.foot_float(lifted, FPS) == 1.0
    assert quality.ground_penetration_cm(lifted) == 0.0
    assert quality.foot_skating_ratio(lifted, FPS) == 0.0  # skating measures from the take's lowest toe
    sunk = still - np.array([0.0, 0.03, 0.0])
    assert quality.ground_penetration_cm(sunk) == pytest.approx(3.0)
    assert quality.foot_float(sunk, FPS) == 0.0


def test_a_real_jump_is_not_floating_but_hovering_as_long_is():
    joints = standing(40)
    t = np.arange(40) / FPS
    flight = (t >= 0.5) & (t < 1.1)  # 0.6 s in the air, a ballistic arc (peak 0.44 m)
    tau = t - 0.5
    height = np.where(flight, 9.81 / 2 * tau * (0.6 - tau), 0.0)
    jump = joints + height[:, None, None] * np.array([0.0, 1.0, 0.0])
    assert quality.foot_float(jump, FPS) == 0.0
    hover = joints + np.where(flight, 0.08, 0.0)[:, None, None] * np.array([0.0, 1.0, 0.0])
    assert quality.foot_float(hover, FPS) == pytest.approx(flight.mean())
    short = joints + np.where((t >= 0.5) & (t < 0.7), 0.08, 0.0)[:, None, None] * np.array([0.0, 1.0, 0.0])
    assert quality.foot_float(short, FPS) == 0.0  # a running stride's flight


def test_jitter_is_mean_jerk_over_the_reference():
    joints = standing(30)
    assert quality.mean_jerk(joints, FPS) == 0.0
    shaky = joints.copy()
    shaky[::2, :, 2] += 0.001  # 0, 1, 0, 1 mm ...: each third difference is 1 + 3 = 4 mm per frame^3
    assert quality.mean_jerk(shaky, FPS) == pytest.approx(0.004 * FPS ** 3)
    badges = quality.physical_badges(shaky, FPS, reference_jerk=0.002 * FPS ** 3)
    assert badges["jitter"] == pytest.approx(2.0)
    with pytest.raises(ValueError, match=r"\(T, 22, 3\)"):
        quality.foot_float(np.zeros((10, 21, 3)))


# -- ranking ------------------------------------------------------------------------------------------------------
def _badges(adherence, skating=0.0, flt=0.0, pen=0.0, jitter=1.0):
    return quality.Badges(adherence, None, skating, flt, pen, jitter)


def test_ranking_is_deterministic_and_documented():
    b = [_badges(50), _badges(90, skating=0.6), _badges(70), _badges(50), _badges(80, pen=3.0)]
    seeds = [10, 11, 12, 13, 14]
    assert quality.rank_score(b[1]) == pytest.approx(0.9 - 0.3)
    assert quality.rank_score(b[4]) == pytest.approx(0.8 - 0.15)
    # jitter counts both ways: half or twice the capture's jerk cost the same
    assert quality.rank_score(_badges(50, jitter=0.5)) == pytest.approx(quality.rank_score(_badges(50, jitter=2.0)))
    assert quality.rank_score(_badges(50, jitter=0.5)) == pytest.approx(0.5 - 0.25 * np.log(2))
    order = quality.best_first(b, seeds)
    assert order == [2, 4, 1, 0, 3]  # equal scores: the lower seed first
    perm = [3, 1, 4, 0, 2]
    again = quality.best_first([b[i] for i in perm], [seeds[i] for i in perm])
    assert [perm[i] for i in again] == order
    assert quality.percentile(0.5, [0.0, 0.5, 1.0]) == 50.0 and quality.percentile(2.0, [0.0, 1.0]) == 100.0


def test_rank_output_orders_rows_by_their_badges(tmp_path):
    from mld_core.testing import tiny_pipeline

    pipe = tiny_pipeline(tmp_path / "m")
    pipe._quality = quality.QualityScorer(None, {"jerk_mean": 1.0})  # physical badges only: fast
    plain = pipe(["a person walks", "a person waves"], seconds=1.5, seed=[3, 7], num_variants=3, num_inference_steps=2)
    ranked = pipe(["a person walks", "a person waves"], seconds=1.5, seed=[3, 7], num_variants=3,
                  num_inference_steps=2, rank=True)
    assert sorted(ranked.seeds[:3]) == [3, 4, 5] and sorted(ranked.seeds[3:]) == [7, 8, 9]
    for row, seed in enumerate(ranked.seeds):
        src = plain.seeds.index(seed)
        np.testing.assert_array_equal(ranked.joints[row], plain.joints[src])
        assert ranked.prompts[row] == plain.prompts[src]
    for group in (slice(0, 3), slice(3, 6)):
        scores = [quality.rank_score(b) for b in ranked.badges[group]]
        assert scores == sorted(scores, reverse=True)
    assert plain.badges is None


# -- coverage -------------------------------------------------------------------------------------------------------
def test_normalise_drops_side_and_style_words():
    assert coverage.normalise("A tired man waves his LEFT hand, happily.") == "a man waves his hand"
    assert coverage.normalise("a happy person jumps left") == coverage.normalise("a person jumps")


def test_normalise_gives_a_command_its_subject():
    assert coverage.normalise("Crawl!") == "a person crawl"
    assert coverage.normalise("slowly squat down") == "a person squat down"  # a style word first, then the command
    assert coverage.normalise("he jumps") == "he jumps" and coverage.normalise("Someone kicks") == "someone kicks"
    assert coverage.normalise("") == "" and coverage.normalise("left, happily") == ""


@pytest.fixture(scope="module")
def bundled_index():
    index = coverage.load_for_model(DEFAULT_MODEL_DIR)
    if index is None:
        pytest.skip("the bundled model has no coverage_index.npz")
    return index


def test_bundled_model_coverage_verdicts(bundled_index, minilm):
    prompts = ["a person walks forward", "someone waves goodbye with both hands", "someone swims freestyle in the water",
               "a person sits down on a chair", "a person jumps up and down", "someone dances ballet on tiptoe"]
    found = bundled_index.query(prompts, minilm)
    assert [c.verdict for c in found] == ["known", "known", "unknown", "unknown", "unknown", "near"]
    assert found[0].score == pytest.approx(1.0, abs=1e-3) and found[2].score < 0.45
    assert len(found[2].nearest) == 3 and found[2].nearest[0][1] >= found[2].nearest[2][1]
    assert len(found[0].known_contents) == 24 and "walk-turn-left" in found[0].known_contents
    assert found[3].warning().startswith('this model has not learned "a person sits down on a chair"')
    assert found[0].warning() == ""
    # side and style words alone never change a verdict
    styled = bundled_index.query(["a tired person walks forward", "someone swims freestyle in the water happily",
                                  "a person sits down on a chair with the left leg first"], minilm)
    assert [c.verdict for c in styled] == ["known", "unknown", "unknown"]
    assert styled[1].score == pytest.approx(found[2].score, abs=1e-6)
    # the prompts that pass 0 of 4 physical checks on the default model
    beyond = ["sits down on a chair", "crouches down low", "lies down on the floor", "climbs up a ladder",
              "does a cartwheel", "jumps up and down in place"]
    fragments = bundled_index.query(beyond, minilm)
    assert [c.verdict for c in fragments][:5] == ["unknown"] * 5 and fragments[5].verdict != "known"
    # a fragment without a subject scores as its sentence does
    sentences = bundled_index.query([f"a person {b}" for b in beyond], minilm)
    assert [c.score for c in fragments] == pytest.approx([c.score for c in sentences], abs=1e-6)


def test_bundled_model_coverage_of_commands(bundled_index, minilm):
    """A command scores as its sentence does: "run" was 'unknown' (0.54) when it met "a person runs" without a
    subject; a command of an absent motion stays unknown."""
    commands = ["run", "bow", "Walk forward!", "swim freestyle", "sit down on a chair"]
    found = bundled_index.query(commands, minilm)
    assert [c.verdict for c in found] == ["known", "known", "known", "unknown", "unknown"]
    sentences = bundled_index.query(["a person runs", "a person bows"], minilm)
    for command, sentence in zip(found, sentences):
        assert command.score == pytest.approx(sentence.score, abs=0.15)


def test_bundled_index_is_small():
    path = DEFAULT_MODEL_DIR / coverage.INDEX_NAME
    if not path.exists():
        pytest.skip("the bundled model has no coverage_index.npz")
    assert path.stat().st_size <= 5e6


def tiny_index(model_dir):
    """A coverage index for a tiny model (its random sentence encoder puts every pair of sentences at cosine
    0.8-0.9, hence its own thresholds): "a person walks" is known, "a person juggles" (0.86) unknown."""
    from mld_core.models.text_encoder import load_text_encoder
    from mld_core.testing import TINY_TEXT_ENCODER

    index = coverage.build_index(["a person walks.", "the zebra"], ["walk", "run"], load_text_encoder(TINY_TEXT_ENCODER))
    index.thresholds = (0.97, 0.9)
    index.save(model_dir / coverage.INDEX_NAME)
    return index


def test_index_round_trip_and_folder_without_index(tmp_path):
    from mld_core.pipeline import MLDPipeline
    from mld_core.testing import tiny_model

    model = tiny_model(tmp_path / "m")
    pipe = MLDPipeline.from_pretrained(model)
    (none,) = pipe.coverage("a person walks")
    assert none.verdict == "unavailable" and not none.available and none.warning() == ""
    index = tiny_index(model)
    loaded = coverage.CoverageIndex.load(model / coverage.INDEX_NAME)
    assert loaded.captions == index.captions and loaded.contents == index.contents
    np.testing.assert_array_equal(loaded.embeddings, index.embeddings)
    assert loaded.thresholds == (0.97, 0.9) and loaded.known_contents == ["run", "walk"]
    pipe = MLDPipeline.from_pretrained(model)
    walk, juggle = pipe.coverage(["A person walks.", "a person juggles"])
    assert walk.verdict == "known" and walk.nearest[0][0] == "a person walks."
    assert juggle.verdict == "unknown" and juggle.score < 0.9
    (collapse,) = pipe.coverage("a person collapses in a heap")  # a verb of no known content: unknown
    assert collapse.verdict == "unknown" and pipe.coverage_index.contents_named("a person collapses") == []
    index.known_contents = ["on_ground", "run", "walk"]  # a model that knows falls: named by its verb, near at least
    index.save(model / coverage.INDEX_NAME)
    pipe = MLDPipeline.from_pretrained(model)
    (collapse,) = pipe.coverage("a person collapses in a heap")
    assert collapse.verdict == "near" and collapse.score < 0.9 and collapse.warning() == ""
    assert pipe.coverage("a person juggles")[0].verdict == "unknown"
    (model / coverage.INDEX_NAME).write_bytes(b"not an index")
    with pytest.raises(CheckpointError, match="cannot read the coverage index"):
        MLDPipeline.from_pretrained(model)


# -- the generate CLI -----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def model_with_index(tmp_path_factory):
    from mld_core.testing import tiny_model

    model = tiny_model(tmp_path_factory.mktemp("tiny") / "model")
    tiny_index(model)
    return model


def test_generate_warns_and_strict_refuses_an_unknown_prompt(model_with_index, tmp_path, capsys):
    from mld_core.cli import main

    out = tmp_path / "take.npz"
    args = ["generate", "a person juggles", "--model", str(model_with_index), "--seconds", "1.5", "--steps", "2",
            "--out", str(out)]
    assert main(args + ["--strict"]) == 2
    err = capsys.readouterr().err
    assert 'this model has not learned "a person juggles"' in err and "--strict" in err
    assert not out.exists() and not list(tmp_path.iterdir())
    assert main(args) == 0
    warning = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning:")]
    assert len(warning) == 1 and "the closest it knows:" in warning[0]
    records = json.loads(str(np.load(out)["quality"]))
    assert records[0]["coverage"]["verdict"] == "unknown"
    assert main(["generate", "a person walks", "--model", str(model_with_index), "--seconds", "1.5", "--steps", "2",
                 "--out", str(tmp_path / "walk.npz"), "--strict"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_generate_best_keeps_the_top_k_with_a_table(model_with_index, tmp_path, capsys):
    from mld_core.cli import main

    out = tmp_path / "best.npz"
    rc = main(["generate", "a person walks", "--model", str(model_with_index), "--seconds", "1.5", "--steps", "2",
               "--variants", "4", "--best", "2", "--seed", "5", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "adherence" in text and "skating" in text and "jitter" in text
    data = np.load(out)
    assert data["joints"].shape[0] == 2 and set(data["seeds"].tolist()) <= {5, 6, 7, 8}
    records = json.loads(str(data["quality"]))
    scores = [quality.rank_score(quality.Badges(**r["badges"])) for r in records]
    assert scores[0] >= scores[1] and records[0]["coverage"]["verdict"] == "known"
    assert main(["generate", "a person walks", "--model", str(model_with_index), "--variants", "2", "--best", "3",
                 "--out", str(out)]) == 2


# -- the panel's watcher (bpy-free part) ---------------------------------------------------------------------------
def test_coverage_watcher_checks_only_the_last_edit_off_the_main_thread():
    import threading
    import time

    from blender_addon.worker.coverage_watch import CoverageWatcher, badge_lines, coverage_line

    seen = []

    def check(text, key):
        seen.append((text, key, threading.current_thread().name))
        if text == "boom":
            raise RuntimeError("no model")
        return coverage.Coverage(text, 0.5, "unknown", [("a person walks.", 0.5, "walk")])

    watcher = CoverageWatcher(check, debounce_s=0.05)
    for typed in ("a p", "a pe", "a person swims"):  # keystrokes faster than the debounce
        watcher.request(typed, "model")
    deadline = time.monotonic() + 10
    while watcher.pending and time.monotonic() < deadline:
        time.sleep(0.01)
    assert seen == [("a person swims", "model", "mld-coverage")]
    assert watcher.result("a p", "model") is None and watcher.result("a person swims", "other model") is None
    found = watcher.result("a person swims", "model")
    assert coverage_line(found) == ("ERROR", "Not learned by this model (0.50): closest 'a person walks'")
    watcher.request("a person swims", "model")  # answered from the cache: no second check
    watcher.request("boom", "model")
    while watcher.pending and time.monotonic() < deadline:
        time.sleep(0.01)
    assert [s[0] for s in seen] == ["a person swims", "boom"]
    assert coverage_line(watcher.result("boom", "model")) is None  # a failed check shows nothing
    assert badge_lines({"mld_skating": 0.25, "mld_adherence": 61.7}) == [
        ("Adherence: 62", "match to the prompt: percentile of real clips"),
        ("Foot skating: 0.25", "planted toes sliding (real walks: 0.2)")]


def test_export_model_ships_the_run_index(tmp_path):
    import sys

    from conftest import REPO
    from mld_core.testing import tiny_model

    sys.path.insert(0, str(REPO / "scripts"))
    import export_model

    run = tiny_model(tmp_path / "run")
    assert export_model.main([str(run), "--out", str(tmp_path / "bare")]) == 0
    assert not (tmp_path / "bare" / coverage.INDEX_NAME).exists()  # nothing to copy, no --data: unavailable
    tiny_index(run)
    assert export_model.main([str(run), "--out", str(tmp_path / "shipped")]) == 0
    shipped = coverage.CoverageIndex.load(tmp_path / "shipped" / coverage.INDEX_NAME)
    assert shipped.captions == ["a person walks.", "the zebra"] and shipped.thresholds == (0.97, 0.9)
