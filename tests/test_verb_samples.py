"""research/v4/verb_samples.py: a model's takes of the train captions naming a checked verb, kept where they show it,
written as a prepared folder that `data merge` joins; the benchmark's prompts never used; a second run goes on where
the first stopped. Tiny seeded model on a hand-made folder; whether a take shows its verb is set here."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from mld_core.cli import main as cli
from mld_core.data import terms
from mld_core.data.dataset import read_captions, split_ids
from mld_core.eval import physical
from mld_core.motion.features import features_to_joints
from mld_core.testing import tiny_model

REPO = Path(__file__).resolve().parents[1]
CLIPS = {  # id: (label, captions, split)
    "01_01": ("jump", ["a person jumps forward", "a person hops in place"], "train"),
    "01_02": ("jump", ["a person jumps over a puddle"], "train"),  # the benchmark's user prompt: never used
    "M01_01": ("jump", ["a person jumps forward"], "train"),  # a mirrored copy: left out
    "02_01": ("crawl", ["someone crawls on all fours"] * 2, "train"),  # a caption listed twice: one candidate
    "02_02": ("crawl", ["a person crawls"], "test"),  # not a train clip
    "03_01": ("walk", ["a person walks"], "train"),  # not a checked verb
}


@pytest.fixture
def samples(monkeypatch):
    monkeypatch.syspath_prepend(str(REPO / "research" / "v4"))
    monkeypatch.syspath_prepend(str(REPO / "scripts"))
    import verb_samples

    return verb_samples


def _folder(root: Path) -> Path:
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (root / sub).mkdir(parents=True)
    rng = np.random.default_rng(0)
    for cid, (_, captions, _) in CLIPS.items():
        np.save(root / "new_joint_vecs" / f"{cid}.npy", rng.normal(size=(60, 263)).astype(np.float32))
        np.save(root / "new_joints" / f"{cid}.npy", rng.normal(size=(60, 22, 3)).astype(np.float32))
        (root / "texts" / f"{cid}.txt").write_text("".join(f"{c}##0.0#0.0\n" for c in captions), encoding="utf-8")
    for split in ("train", "val", "test"):
        ids = [cid for cid, (_, _, s) in CLIPS.items() if s == split]
        (root / f"{split}.txt").write_text("".join(f"{i}\n" for i in ids), encoding="utf-8")
    (root / "all.txt").write_text("".join(f"{i}\n" for i in CLIPS), encoding="utf-8")
    np.save(root / "Mean.npy", np.zeros(263, np.float32))
    np.save(root / "Std.npy", np.ones(263, np.float32))
    labels = {cid: label for cid, (label, _, _) in CLIPS.items()}
    (root / "actions.json").write_text(json.dumps({"classes": sorted(set(labels.values())), "clips": labels}))
    return root


def test_the_candidates_are_train_captions_naming_the_clips_verb_and_never_a_measured_prompt(samples, tmp_path):
    data = _folder(tmp_path / "data")
    cands = samples.candidates(data, samples.measured_prompts(None))
    assert {v: [(c, t) for c, t, _ in items] for v, items in cands.items() if items} == {
        "jump": [("01_01", "a person jumps forward"), ("01_01", "a person hops in place")],
        "crawl": [("02_01", "someone crawls on all fours")]}
    assert samples.plain(" A person jumps over a puddle. ") in samples.measured_prompts(None)
    order = samples.plan(cands, [], per_verb=2)  # at most 4 x 2 tries per verb, the verbs in turn
    assert [(o["verb"], o["seed"]) for o in order[:3]] == [("jump", 0), ("crawl", 0), ("jump", 0)]
    assert sum(o["verb"] == "jump" for o in order) == 8 and sum(o["verb"] == "crawl" for o in order) == 8
    assert [o["seed"] for o in order if o["verb"] == "crawl"] == list(range(8))  # one caption: a seed a round
    twice = {"id": "02_01", "caption": "someone crawls on all fours", "caption_index": 0, "seed": 0, "verb": "crawl",
             "kept": True, "draw": 0}
    out = tmp_path / "out"
    out.mkdir()
    samples.write_index(out, [twice, dict(twice)], ["crawl"])  # a take an older run tried twice is listed once
    assert split_ids(out, "train") == ["S02_01_0_0"]


def test_kept_takes_become_a_folder_that_merges_and_a_second_run_goes_on(samples, tmp_path, monkeypatch, capsys):
    data = _folder(tmp_path / "data")
    terms.write(data, [terms.CMU])
    model = tiny_model(tmp_path / "model")
    shown = {"n": 0}

    def shows(joints, verb, fps=20.0, result=None):  # every other take shows its verb, redraws included
        shown["n"] += 1
        return shown["n"] % 2 == 0

    monkeypatch.setattr(physical, "shows", shows)
    out = tmp_path / "samples"
    argv = ["--data", str(data), "--model", str(model), "--out", str(out), "--per-verb", "1", "--batch", "2",
            "--verb-redraws", "0"]
    assert samples.main(argv) == 0
    progress = [json.loads(line) for line in (out / "progress.jsonl").read_text().splitlines()]
    kept = [p for p in progress if p["kept"]]
    assert kept and split_ids(out, "train") == [f"S{p['id']}_{p['caption_index']}_{p['seed']}" for p in kept]
    assert split_ids(out, "val") == [] and split_ids(out, "test") == []
    for p in kept:
        sid = f"S{p['id']}_{p['caption_index']}_{p['seed']}"
        assert [c.text for c in read_captions(out / "texts" / f"{sid}.txt")] == [p["caption"]]
        features, joints = np.load(out / "new_joint_vecs" / f"{sid}.npy"), np.load(out / "new_joints" / f"{sid}.npy")
        assert features.shape == (60, 263) and joints[..., 1].min() == pytest.approx(0.0, abs=1e-5)  # on the floor
        np.testing.assert_allclose(features_to_joints(features), joints, atol=1e-4)  # the features say the same
        assert json.loads((out / "actions.json").read_text())["clips"][sid] == p["verb"]
    assert {p["verb"] for p in kept} == {"jump", "crawl"}  # one kept take per verb, then the verb stops
    # the takes carry the terms of the data their captions came from and of the model that made them
    assert terms.of_folder(out) == [terms.CMU, terms.unrecorded("model tiny-text")]
    again = len(progress)
    assert samples.main(argv + ["--per-verb", "2"]) == 0  # goes on: tries only what was not tried
    progress = [json.loads(line) for line in (out / "progress.jsonl").read_text().splitlines()]
    tried = [(p["id"], p["caption"], p["seed"]) for p in progress]
    assert len(progress) > again and len(tried) == len(set(tried))
    capsys.readouterr()
    assert cli(["data", "merge", str(data), str(out), "--out", str(tmp_path / "merged")]) == 0
    assert set(split_ids(out, "train")) <= set(split_ids(tmp_path / "merged", "train"))


def test_a_folder_that_is_not_prepared_is_one_line(samples, tmp_path, capsys):
    assert samples.main(["--data", str(tmp_path), "--model", "x", "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.strip() == f"error: {tmp_path} is not a prepared folder (no train.txt)"


def test_bad_arguments_are_one_line_and_write_nothing(samples, tmp_path, capsys):
    data = _folder(tmp_path / "data")
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "mine.txt").write_text("keep")
    model = tiny_model(tmp_path / "model")
    cases = [(["--out", str(data)], "is, holds or sits in --data"),
             (["--out", str(data / "samples")], "is, holds or sits in --data"),
             (["--out", str(tmp_path)], "is, holds or sits in --data"),
             (["--out", str(tmp_path / "a_file")], "is a file"),
             (["--out", str(tmp_path / "other")], "not an earlier run of this script"),
             (["--per-verb", "0"], "--per-verb must be between 1"),
             (["--batch", "0"], "--batch must be between 1"),
             (["--verb-redraws", "9"], "--verb-redraws must be between 0 and 8"),
             (["--minutes", "nan"], "--minutes must be a positive number"),
             (["--minutes", "-1"], "--minutes must be a positive number"),
             (["--model", str(tmp_path / "no_model")], "")]
    for extra, words in cases:
        argv = ["--data", str(data), "--model", str(model), "--out", str(tmp_path / "new"), *extra]
        assert samples.main(argv) == 2, extra
        err = capsys.readouterr().err.strip()
        assert err.startswith("error: ") and words in err and "\n" not in err, (extra, err)
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before
    assert (tmp_path / "other" / "mine.txt").read_text() == "keep" and not (tmp_path / "new").exists()


def test_a_second_run_on_the_same_folder_at_once_is_refused(samples, tmp_path, capsys):
    import fcntl

    data, out = _folder(tmp_path / "data"), tmp_path / "samples"
    out.mkdir()
    (out / samples.PROGRESS).touch()
    with open(out / ".lock", "w") as held:  # another run holds the folder
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        argv = ["--data", str(data), "--model", str(tiny_model(tmp_path / "model")), "--out", str(out)]
        assert samples.main(argv) == 2
    assert "another run is writing" in capsys.readouterr().err
    assert (out / samples.PROGRESS).read_text() == ""


if __name__ == "__main__":
    sys.exit(pytest.main([__file__]))
