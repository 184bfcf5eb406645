"""scripts/compare_side_accuracy.py: the per-content gate between two side_accuracy runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

from compare_side_accuracy import compare, main  # noqa: E402


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
    assert capsys.readouterr().out.splitlines()[-1] == "2 of 3 contents worse: walk, wave-left-hand"
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
    assert out.splitlines()[-1] == "1 of 2 contents worse: walk (paraphrase@clip)"
