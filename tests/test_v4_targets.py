"""research/v4/targets.py: v4's targets judged from the measurements' JSON (synthetic numbers, no model run)."""
import importlib.util
import json
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "research" / "v4" / "targets.py"


def _script():
    spec = importlib.util.spec_from_file_location("v4_targets", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _content(n, pass_rate, skating=0.1, side=None):
    return {"n": n, "pass_rate": pass_rate, "side_n": n if side is not None else 0, "side_accuracy": side,
            "opposite_side": 0.0, "skating": skating, "failed_checks": {}}


def _physical(captions, paraphrases, walk_skate=0.02, turn_side=1.0):
    contents = {"walk": _content(64, captions, walk_skate), "run": _content(64, captions, 0.01),
                "walk-back": _content(64, captions, 0.05), "walk-turn-left": _content(64, 1.0, side=turn_side),
                "walk-turn-right": _content(64, 1.0, side=turn_side)}
    overall = lambda rate: {"all": {"n": 400, "mean_pass_rate": rate}}  # noqa: E731
    return {"real": {"contents": {"walk": _content(16, 1.0, 0.2), "run": _content(16, 1.0, 0.1),
                                  "walk-back": _content(16, 1.0, 0.4)}},
            "generated": {"captions@clip": {"contents": contents, "overall": overall(captions)},
                          "paraphrase@clip": {"contents": {}, "overall": overall(paraphrases)}}}


def _t2m(r3, real_r3):
    return {"rows": {"Real": {"R@3": {"mean": real_r3, "ci": 0.01}}, "M": {"R@3": {"mean": r3, "ci": 0.01}}},
            "order": ["Real", "M"]}


def _results(jump=(0.9, 1.0, 0.85), captions=0.93, paraphrases=0.9, unknown=0, flagged=19, bandai_r3=0.95,
             merged_r3=0.8, walk_skate=0.02, turn_side=1.0):
    vocab = [{"verb": "jump", "wording": w, "ratio": r} for w, r in zip(("caption", "command", "user"), jump)]
    vocab += [{"verb": "crawl", "wording": w, "ratio": 1.0} for w in ("caption", "command", "user")]
    return {"vocabulary": {"rows": vocab},
            "coverage": {"known": 20, "known_unknown": unknown, "absent": 20, "absent_flagged": flagged},
            "physical": _physical(captions, paraphrases, walk_skate, turn_side),
            "t2m_merged": _t2m(merged_r3, 0.8), "t2m_bandai": _t2m(bandai_r3, 0.96)}


def _met(rows):
    return {r["target"]: r["met"] for r in rows}


def test_a_model_meeting_every_bar_is_judged_met_and_each_miss_is_named():
    targets = _script()
    base = _results(captions=0.935, paraphrases=0.915)
    assert all(_met(targets.judge(_results(), base)).values())
    met = _met(targets.judge(_results(jump=(0.9, 0.79, 1.0), unknown=1, flagged=18, bandai_r3=0.93, merged_r3=0.71,
                                      walk_skate=0.11), base))
    assert not met["verb jump"] and met["verb crawl"]
    assert not met["known verbs never unknown"] and not met["absent motions flagged"]
    assert not met["Bandai t2m R@3"] and not met["merged t2m R@3 (x Real)"]
    assert not met["skating walk (x real)"] and met["skating run (x real)"]


def test_bandai_pass_and_turns_are_judged_against_the_baseline_within_noise():
    targets = _script()
    base = _results(captions=0.935, paraphrases=0.915)
    met = _met(targets.judge(_results(captions=0.92, paraphrases=0.80, turn_side=0.80), base))
    assert met["Bandai physical pass, captions"]  # 0.015 under on 400 takes: noise
    assert not met["Bandai physical pass, paraphrases"]  # 0.115 under: beyond it
    assert not met["turns to the named side"]
    assert _met(targets.judge(_results()))["Bandai physical pass, captions"] is None  # no baseline: not decided


def test_within_noise_is_the_95_percent_interval_of_the_difference():
    targets = _script()
    assert targets.within_noise(0.90, 400, 0.93, 400)
    assert not targets.within_noise(0.85, 400, 0.93, 400)
    assert targets.within_noise(0.85, 20, 0.93, 20)  # few takes: a wide interval


def test_the_command_reads_measurements_already_there_and_writes_the_table(tmp_path, capsys):
    targets = _script()
    data = {name: tmp_path / name for name in ("bandai", "cmu", "merged")}
    for folder in data.values():
        folder.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    for name, result in _results().items():
        (out / f"{name}.json").write_text(json.dumps(result))
    argv = ["--bandai", str(data["bandai"]), "--cmu", str(data["cmu"]), "--merged", str(data["merged"]),
            "--out", str(out)]
    assert targets.main(argv) == 0
    printed = capsys.readouterr().out
    assert "verb jump" in printed and "merged t2m R@3" in printed
    assert json.loads((out / "targets.json").read_text())["rows"][0]["target"] == "verb jump"
    base = tmp_path / "base"
    base.mkdir()
    (base / "physical.json").write_text(json.dumps(_results(captions=0.99)["physical"]))  # the only file it reads
    assert targets.main([*argv, "--baseline", str(base)]) == 0
    judged = {r["target"]: r["met"] for r in json.loads((out / "targets.json").read_text())["rows"]}
    assert judged["Bandai physical pass, captions"] is False and judged["Bandai physical pass, paraphrases"] is True
    assert targets.main([*argv, "--baseline", str(tmp_path / "nowhere")]) == 2
    assert "holds no measurements" in capsys.readouterr().err
    assert targets.main([*argv[:-1], str(data["cmu"])]) == 2  # --out a data folder
    assert "is a data folder" in capsys.readouterr().err and not (data["cmu"] / "targets.json").exists()


def test_the_kept_v38_baseline_reads_as_the_readme_gives_it():
    """research/v4/baseline_v38: v3.8's physical checks by this command, kept so a model is judged without measuring
    v3.8 again."""
    targets = _script()
    base = targets.read_measurements(SCRIPT.parent / "baseline_v38", ("physical",))["physical"]
    assert base["model_id"] == "mld-bandai-cpu-v3.8" and base["seeds"] == 4
    rates = targets._physical_rates(base)
    assert round(rates["captions"][0], 3) == 0.951 and round(rates["paraphrases"][0], 3) == 0.911
    assert rates["captions"][1] == 768 and targets._turns(base) == (1.0, 128)
    met = _met(targets.judge(_results(captions=0.951, paraphrases=0.80), {"physical": base}))
    assert met["Bandai physical pass, captions"] and not met["Bandai physical pass, paraphrases"]
