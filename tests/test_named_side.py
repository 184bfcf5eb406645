"""The side badge (mld_core.eval.named_side): which side a prompt names, whether a take used it, and where the user
meets it (the badge table, best-first order, Action properties, the panel's lines, the CLI's warning)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mld_core import take_report
from mld_core.eval import named_side, physical, quality
from mld_core.motion.features import mirror_joints

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("prompt,label", [
    ("a person walks and turns left", "walk-turn-left"),
    ("a person walks ahead, then changes direction to their right", "walk-turn-right"),
    ("the man walks and takes a left turn", "walk-turn-left"),
    ("a woman strolls forward and veers off to the right", "walk-turn-right"),
    ("someone walks forward diagonally to the left without turning", "walk-left"),  # "without turning": a drift
    ("an old person shuffles forward and to the right without turning the body", "walk-right"),
    ("a person waves hello with the right hand", "wave-right-hand"),
    ("the man lifts his left hand and waves it from side to side", "wave-left-hand"),
    ("someone says goodbye by waving the left hand", "wave-left-hand"),
    ("a woman holds her LEFT arm straight up in the air", "raise-up-left-hand"),
    ("a person puts the right hand up to reply", "raise-up-right-hand"),
    ("an elderly person walks forward and waves with the right hand", "wave-right-hand"),
])
def test_the_side_a_prompt_names_and_what_for(prompt, label):
    ask = named_side.asked_side(prompt)
    assert ask is not None and ask.label == label
    assert ask.side == physical.side_of(label)


@pytest.mark.parametrize("prompt", [
    "a person walks forward",  # no side
    "someone waves both hands above the head",
    "a person turns left and waves the right hand",  # two sides: which goes with what is not guessed
    "someone kicks high with the right leg",  # a leg: no check reads which one kicked
    "a person stands on the left",  # a side, but no turn, travel or hand
    "someone tilts the head to the left",  # "head" is the noun here, not "heads left"
    "",
])
def test_prompts_without_one_checkable_side_get_no_badge(prompt):
    assert named_side.asked_side(prompt) is None


@pytest.fixture(scope="module")
def turn_left_clip():
    """The real Bandai Namco walk-turn-left fixture clip (2 s), canonicalised like the prepared data."""
    from mld_core.data import bandai
    from mld_core.motion.features import canonical_joints

    path = REPO / "tests" / "fixtures" / "bandai" / "dataset-2_walk-turn-left_normal_027.bvh"
    if not path.is_file():
        pytest.skip(f"fixture {path.name} missing")
    return canonical_joints(bandai.clip_joints(path.read_bytes()))


def test_a_real_left_turn_uses_the_named_side_and_its_mirror_the_opposite(turn_left_clip):
    left, right = named_side.asked_side("a person walks and turns left"), named_side.asked_side("walks, turns right")
    assert named_side.side_used(left, physical.classify(turn_left_clip)) == "named"
    mirrored = physical.classify(mirror_joints(turn_left_clip))
    assert named_side.side_used(left, mirrored) == "opposite"
    assert named_side.side_used(right, mirrored) == "named"
    still = np.repeat(turn_left_clip[:1], 40, axis=0)  # (T, 22, 3): standing, no turn at all
    assert named_side.side_used(left, physical.classify(still)) == "neither"
    assert left.opposite_note() == "it turns right, not left as the prompt says"


def _badges(adherence, side=None):
    return quality.Badges(adherence, None, 0.0, 0.0, 0.0, 1.0, side)


def test_takes_on_the_opposite_side_rank_last_whatever_their_score():
    b = [_badges(90, "opposite"), _badges(20, "neither"), _badges(60, "named"), _badges(95, None)]
    assert quality.rank_score(b[0]) == quality.rank_score(_badges(90))  # the score itself is unchanged
    assert quality.best_first(b, [0, 1, 2, 3]) == [3, 2, 1, 0]
    assert quality.best_first(b[:1] + [_badges(90, "opposite")], [5, 4]) == [1, 0]  # among them: score, then seed
    assert b[0].as_dict()["side"] == "opposite" and b[3].as_dict()["side"] is None
    table = quality.format_table([7, 8], b[:2]).splitlines()
    assert table[0].split()[-2] == "side" and table[1].split()[-2] == "opposite" and table[2].split()[-2] == "neither"


def test_the_scorer_gives_the_side_badge_from_each_prompt(turn_left_clip):
    scorer = quality.QualityScorer(None, {"jerk_mean": 1.0})  # physical badges only
    clips = [turn_left_clip, mirror_joints(turn_left_clip), turn_left_clip]
    badges = scorer.score(["a person walks and turns left"] * 2 + ["a person walks"], clips)
    assert [b.side for b in badges] == ["named", "opposite", None]
    assert [b.side for b in scorer.score(None, clips[:2])] == [None, None]  # no prompts (actions, unconditional)


def test_where_the_user_meets_an_opposite_take(turn_left_clip):
    from blender_addon.worker.coverage_watch import badge_lines

    props = take_report.custom_properties(None, _badges(40, "opposite"))
    assert props["mld_side"] == "opposite" and props["mld_adherence"] == 40.0
    assert ("Side: opposite", "the side the prompt names: used (named), only the other (opposite), or neither") \
        in badge_lines(props)
    assert take_report.take_record(None, _badges(40, "named"))["badges"]["side"] == "named"
    # the CLI's warning lines: from the badges when ranked, else checked on the joints
    joints = np.stack([turn_left_clip, mirror_joints(turn_left_clip)])  # (2, T, 22, 3)
    out = SimpleNamespace(prompts=["someone walks and turns to the left"] * 2, joints=joints, seeds=[3, 4], fps=20,
                          lengths=np.array([len(turn_left_clip)] * 2), badges=None, draws=None)
    lines = take_report.side_lines(out)
    assert lines == ["warning: take 1 (seed 4): it turns right, not left as the prompt says; try another --seed, or "
                     "--variants 4 --best 1 (ranking puts such takes last)"]
    out.badges = [_badges(10, "opposite"), _badges(10, "named")]
    assert [line.split(":")[1] for line in take_report.side_lines(out)] == [" take 0 (seed 3)"]
    # the add-on's report and the batch: the same words, their own hint
    assert take_report.side_report("a person waves the right hand", "opposite", 0) == \
        ("warning", "it waves the left hand, not right as the prompt says (try another seed, or more variants)")
    assert take_report.side_report("a person waves the right hand", "named", 0) == ("", "")


def test_calibration_script_reads_captions_and_checks_them_on_their_captures(tmp_path, turn_left_clip, capsys):
    import importlib.util
    import json

    path = REPO / "research" / "side_badge_calibration.py"
    spec = importlib.util.spec_from_file_location("side_badge_calibration", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    data = tmp_path / "bandai"
    (data / "texts").mkdir(parents=True)
    (data / "new_joints").mkdir()
    clips = {"turn": ("walk-turn-left", turn_left_clip),
             "mislabelled": ("walk-turn-left", mirror_joints(turn_left_clip)),  # a right turn captioned as a left one
             "walk": ("walk", turn_left_clip)}
    for cid, (content, joints) in clips.items():
        np.save(data / "new_joints" / f"{cid}.npy", joints)
        caption = "a person walks forward." if content == "walk" else "a person turns to the left while walking."
        (data / "texts" / f"{cid}.txt").write_text(f"{caption}#a/DET#0.0#0.0\n")
    (data / "actions.json").write_text(json.dumps({"clips": {k: v[0] for k, v in clips.items()}}))
    (data / "test.txt").write_text("turn\nmislabelled\nwalk\n")
    assert script.main(["--data", str(data), "--json", str(tmp_path / "c.json")]) == 0
    result = json.loads((tmp_path / "c.json").read_text())
    assert result["read"] == {"walk": {"none": 1}, "walk-turn-left": {"walk-turn-left": 2}}
    assert result["real"] == {"walk-turn-left": {"named": 1, "opposite": 1}}
    assert result["opposite"] == [["mislabelled", "a person turns to the left while walking."]]
    assert "opposite: 1 of 2 caption-clip pairs" in capsys.readouterr().out
    assert script.main(["--data", str(tmp_path / "nowhere")]) == 2
