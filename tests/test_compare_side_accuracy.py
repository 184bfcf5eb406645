"""research/compare_side_accuracy.py: the per-content gate between two side_accuracy runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from statistics import NormalDist

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "research"))

from compare_side_accuracy import compare, main, mcnemar_z, paired_z  # noqa: E402


def _run(path: Path, contents: dict) -> Path:
    path.write_text(json.dumps({"generated": {"paraphrase@4s": {"contents": contents}}}))
    return path


def test_a_content_is_worse_by_pass_rate_or_by_locomotion_skating(tmp_path, capsys):
    base = {"walk": {"pass_rate": 0.6, "skating": 0.30}, "wave-left-hand": {"pass_rate": 0.7, "skating": 0.00},
            "bow": {"pass_rate": 0.9, "skating": 0.01}}
    new = {"walk": {"pass_rate": 0.7, "skating": 0.35}, "wave-left-hand": {"pass_rate": 0.6, "skating": 0.00},
           "bow": {"pass_rate": 0.9, "skating": 0.20}}  # bow is no locomotion: its skating does not count
    rows = {r["content"]: r["worse"] for r in compare(base, new)}
    assert rows == {"walk": True, "wave-left-hand": True, "bow": False}
    assert [r["worse"] for r in compare(base, {"walk": new["walk"]}, tolerance=1.0)] == [False, True, True]  # gone
    assert {r["content"]: r["worse"] for r in compare(base, new, tolerance=0.1)} == {
        "walk": False, "wave-left-hand": False, "bow": False}
    assert main([str(_run(tmp_path / "a.json", base)), str(_run(tmp_path / "b.json", new))]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-1] == "2 of 3 contents worse (by more than 0): walk, wave-left-hand"
    assert out[-2] == "paraphrase@4s: mean pass 0.7333 -> 0.7333, mean locomotion skating 0.3000 -> 0.3500"
    (tmp_path / "bad.json").write_text("{}")
    assert main([str(tmp_path / "a.json"), str(tmp_path / "bad.json")]) == 2
    assert capsys.readouterr().err.startswith("error: cannot read")
    (tmp_path / "captions.json").write_text(json.dumps({"generated": {"captions@4s": {"contents": new}}}))
    assert main([str(tmp_path / "a.json"), str(tmp_path / "captions.json")]) == 2  # other prompts: no comparison
    assert "share no prompt set" in capsys.readouterr().err


def test_every_prompt_set_both_runs_scored_is_compared(tmp_path, capsys):
    good, bad = {"walk": {"pass_rate": 0.9, "skating": 0.1}}, {"walk": {"pass_rate": 0.5, "skating": 0.1}}
    (tmp_path / "a.json").write_text(json.dumps({"generated": {"captions@clip": {"contents": good},
                                                               "paraphrase@clip": {"contents": good}}}))
    (tmp_path / "b.json").write_text(json.dumps({"generated": {"captions@clip": {"contents": good},
                                                               "paraphrase@clip": {"contents": bad}}}))
    assert main([str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 0
    out = capsys.readouterr().out
    assert "prompt set captions@clip" in out and "prompt set paraphrase@clip" in out
    assert out.splitlines()[-1] == "1 of 2 contents worse (by more than 0): walk (paraphrase@clip)"


def _takes(passed: list[int], skating: list[float]) -> dict:
    return {"pass_rate": sum(passed) / len(passed), "skating": sum(skating) / len(skating),
            "takes": {"passed": passed, "skating": skating}}


def test_paired_z_counts_only_the_takes_that_changed():
    same = {"passed": [1, 0, 1, 1], "skating": [0.1, 0.2, 0.3, 0.4]}
    assert paired_z(same, same) == (0.0, 0.0)
    # 9 takes lost, 1 won: exact one-sided p = (C(10, 9) + C(10, 10)) / 2^10 = 11 / 1024, as a normal quantile
    base = {"passed": [1] * 9 + [0] + [1] * 10, "skating": [0.1] * 20}
    new = {"passed": [0] * 9 + [1] + [1] * 10, "skating": [0.1 + 0.01 * (k % 2) for k in range(20)]}
    z_pass, z_skate = paired_z(base, new)
    assert abs(z_pass - NormalDist().inv_cdf(1 - 11 / 1024)) < 1e-12 and 2.29 < z_pass < 2.31
    # differences 0, 0.01, 0, 0.01 ...: mean 0.005, sample sd 0.005 * sqrt(20 / 19), z = sqrt(19)
    assert abs(z_skate - 19 ** 0.5) < 1e-9
    assert paired_z(new, base)[0] == -z_pass
    assert paired_z(base, {"passed": base["passed"], "skating": [0.2] * 20})[1] == float("inf")  # all worse alike


def test_with_z_a_content_is_worse_only_beyond_noise(tmp_path, capsys):
    rng = [0.05 * ((7 * k) % 5) for k in range(40)]  # a fixed spread of per-take skating
    base = {"walk": _takes([1] * 30 + [0] * 10, rng), "bow": _takes([1] * 40, [0.0] * 40)}
    slightly = {"walk": _takes([1] * 29 + [0] * 11, [s + (0.01 if k % 3 else -0.02) for k, s in enumerate(rng)]),
                "bow": _takes([1] * 39 + [0], [0.0] * 40)}
    assert [r["worse"] for r in compare(base, slightly)] == [True, True]  # the raw rule counts any drop
    rows = compare(base, slightly, z=1.96)
    assert [r["worse"] for r in rows] == [False, False] and rows[0]["z"][0] == 0.0  # 1 take to 0: p 0.5
    clearly = {"walk": _takes([1] * 20 + [0] * 20, [s + 0.05 for s in rng]), "bow": base["bow"]}
    rows = compare(base, clearly, z=1.96)
    assert [r["worse"] for r in rows] == [True, False] and rows[0]["z"][1] == float("inf")
    more = [s + 0.05 + 0.01 * (k % 2) for k, s in enumerate(rng)]
    skating_only = {"walk": _takes(base["walk"]["takes"]["passed"], more), "bow": base["bow"]}
    assert [r["worse"] for r in compare(base, skating_only, z=1.96)] == [True, False]
    old = {"walk": {"pass_rate": 0.5, "skating": 0.1}, "bow": {"pass_rate": 1.0, "skating": 0.0}}  # no per-take numbers
    rows = compare(base, old, z=1.96)
    assert rows[0]["z"] is None and [r["worse"] for r in rows] == [True, False]
    assert main([str(_run(tmp_path / "a.json", base)), str(_run(tmp_path / "b.json", slightly)), "--z", "1.96"]) == 0
    out = capsys.readouterr().out
    assert "| walk | 0.75 | 0.72 | 0.100 | 0.099 | +0.0 | -0.2 |  |" in out
    assert out.splitlines()[-1] == "0 of 2 contents worse (beyond paired z 1.96)"


def test_mcnemar_z_is_exact_for_few_changed_takes():
    assert mcnemar_z(0, 0) == mcnemar_z(3, 3) == mcnemar_z(1, 0) == 0.0
    assert abs(mcnemar_z(4, 0) - NormalDist().inv_cdf(1 - 1 / 16)) < 1e-12  # 4 to 0: p 0.0625, z 1.53, not 2.0
    assert mcnemar_z(0, 4) == -mcnemar_z(4, 0)
    assert mcnemar_z(6, 0) > 1.96 > mcnemar_z(5, 0)  # 6 to 0: p 0.016; 5 to 0: p 0.031
    assert abs(mcnemar_z(100, 60) - 3.1) < 0.1  # many changed takes: close to (lost - won) / sqrt(n) = 3.16


def test_a_repeated_request_is_paired_once():
    # 6 takes lost, none won: p 1/64, z 2.15; but if they are 3 requests asked twice, 3 takes lost: p 1/8, z 1.15
    base = {"passed": [1] * 6 + [1] * 4, "skating": [0.1] * 10}
    new = {"passed": [0] * 6 + [1] * 4, "skating": [0.1] * 6 + [0.1] * 4}
    assert paired_z(base, new)[0] > 1.96  # without keys every take counts
    keys = ["a", "b", "c", "a", "b", "c", "d", "e", "f", "g"]
    with_keys = paired_z({**base, "keys": keys}, {**new, "keys": keys})[0]
    assert with_keys == mcnemar_z(3, 0) < 1.96
    assert paired_z({**base, "keys": [""] * 10}, {**new, "keys": [""] * 10}) == paired_z(base, new)  # no names
    # runs whose takes were asked differently are not paired: the tolerance rule decides
    mine = {"walk": {"pass_rate": 1.0, "skating": 0.1, "takes": {**base, "keys": keys}}}
    theirs = {"walk": {"pass_rate": 0.4, "skating": 0.1, "takes": {**new, "keys": [k + "!" for k in keys]}}}
    row = compare(mine, theirs, z=1.96)[0]
    assert row["z"] is None and row["worse"]


def test_bad_z_or_tolerance_is_refused(tmp_path, capsys):
    run = _run(tmp_path / "a.json", {"walk": {"pass_rate": 0.5, "skating": 0.1}})
    for flag in (["--z", "nan"], ["--z", "inf"], ["--z=-1"], ["--tolerance", "nan"], ["--tolerance=-0.1"]):
        with pytest.raises(SystemExit) as exc:
            main([str(run), str(run), *flag])
        assert exc.value.code == 2 and "must be a finite number >= 0" in capsys.readouterr().err
