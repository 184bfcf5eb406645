"""Sharded generation (no Blender): shards 0/2 + 1/2 of a prompt file, merged, are the unsharded run's takes; the
merge refuses shards of another model or settings, overlapping and missing shards; a bad --shard is one error line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mld_core.cli import main
from mld_core.testing import tiny_model
from test_reliability import refused

PROMPTS = "a person walks\n60 a person runs\nsomeone waves\n50 a person bows\n# a comment\na person jumps\n"


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("shards")
    tiny_model(root / "tiny")
    tiny_model(root / "other", seed=1)
    (root / "prompts.txt").write_text(PROMPTS)
    return root


def _generate(work: Path, out: str, *extra) -> Path:
    args = ["generate", "--prompts", work / "prompts.txt", "--model", work / "tiny", "--seconds", "2",
            "--variants", "2", "--out", work / out, *extra]
    assert main([str(a) for a in args]) == 0
    return work / out


@pytest.fixture(scope="module")
def whole(work) -> Path:
    return _generate(work, "whole.npz", "--bvh", work / "whole.bvh")


def test_shards_merged_are_the_unsharded_run(work, whole):
    shards = [_generate(work, f"s{i}.npz", "--shard", f"{i}/2", "--bvh", work / "s" / "take.bvh") for i in (1, 0)]
    assert main([str(a) for a in ["merge", *shards, "--out", work / "merged.npz", "--bvh", work / "m.bvh"]]) == 0
    a, b = np.load(whole), np.load(work / "merged.npz")
    assert sorted(a.files) == sorted(b.files)  # the merged file is the unsharded run's (no shard record left)
    assert a["prompts"].tolist() == b["prompts"].tolist() and len(a["prompts"]) == 10  # 5 lines x 2 variants
    assert a["seeds"].tolist() == b["seeds"].tolist() == list(range(10))  # line i, variant v: seed + 2i + v
    for key in ("lengths", "draws", "fps", "model_id", "quality"):
        assert np.array_equal(a[key], b[key]), key
    for key in ("features", "joints"):  # the same takes, batched otherwise: float rounding apart
        assert a[key].shape == b[key].shape
        np.testing.assert_allclose(a[key], b[key], atol=1e-5)
    # shard 1 made lines 1 and 3 (seeds 2, 3, 6, 7); its BVH files are named as in the whole run
    one = np.load(work / "s1.npz")
    assert one["seeds"].tolist() == [2, 3, 6, 7] and one["lines"].tolist() == [1, 1, 3, 3]
    assert json.loads(str(one["shard"]))["index"] == 1
    names = sorted(p.name for p in (work / "s").iterdir())
    assert names == [f"take_{i:03d}.bvh" for i in range(10)]
    from mld_core.motion.bvh import read_bvh

    for i in range(10):
        mine, theirs = read_bvh(work / f"m_{i:03d}.bvh"), read_bvh(work / f"whole_{i:03d}.bvh")
        np.testing.assert_allclose(mine.motion, theirs.motion, atol=1e-2)  # degrees (and metres): rounding apart


def test_the_merge_refuses_shards_that_are_not_one_run(work, whole, capsys):
    for i in (0, 1):
        _generate(work, f"r{i}.npz", "--shard", f"{i}/2")
    _generate(work, "seed9.npz", "--shard", "1/2", "--seed", "9")
    args = ["generate", "--prompts", work / "prompts.txt", "--model", work / "other", "--seconds", "2",
            "--variants", "2", "--shard", "1/2", "--out", work / "other.npz"]
    assert main([str(a) for a in args]) == 0
    _generate(work, "third.npz", "--shard", "2/3")
    merge = ["merge", "--out", work / "m2.npz"]
    refused([*merge, work / "r0.npz"], work, capsys, "shard(s) 1/2 missing")
    refused([*merge, work / "r0.npz", work / "r0.npz"], work, capsys, "are both shard 0/2")
    refused([*merge, work / "r0.npz", work / "seed9.npz"], work, capsys, "different seed")
    refused([*merge, work / "r0.npz", work / "other.npz"], work, capsys, "different model files")
    refused([*merge, work / "r0.npz", work / "third.npz"], work, capsys, "shards of one run have one count")
    refused([*merge, work / "r0.npz", whole], work, capsys, "made without --shard")
    refused([*merge, work / "r0.npz", work / "prompts.txt"], work, capsys, "merge takes generate's .npz shards")
    refused([*merge, work / "r0.npz", work / "r1.npz", "--bvh", work / "x.bvh"], work, capsys, "made without --bvh")
    refused(["merge", work / "r0.npz", work / "r1.npz", "--out", whole], work, capsys, "exists; pass --overwrite")
    refused(["merge", work / "r0.npz", work / "r1.npz", "--out", work / "r0.npz", "--overwrite"], work, capsys,
            "same file as shard 0")


@pytest.mark.parametrize("shard, words", [
    ("3/2", "--shard 3/2: the index must be 0 to 1"),
    ("0/0", "--shard 0/0: the number of shards must be 1 to"),
    ("x", "--shard 'x' is not I/N"),
    ("1/-2", "is not I/N"),
    ("5/6", "there are 5 prompt line(s), so shard 5 has none"),
])
def test_a_bad_shard_is_one_error_line(work, capsys, shard, words):
    refused(["generate", "--prompts", work / "prompts.txt", "--model", work / "tiny", "--out", work / "x.npz",
             "--shard", shard], work, capsys, words)


def test_a_sequence_is_not_sharded(work, capsys):
    (work / "seq.json").write_text(json.dumps([{"prompt": "a person walks", "seconds": 2.0}]))
    refused(["generate", "--sequence", work / "seq.json", "--model", work / "tiny", "--out", work / "x.npz",
             "--shard", "0/2"], work, capsys, "a --sequence is one motion")


# -- the batch's manifests (their merge needs no Blender) -----------------------------------------------------------
def _manifest(work: Path, name: str, index: int, count: int, lines: list[int], **settings) -> Path:
    """A shard's manifest as batch.py writes it, with a BVH file per take in its own folder."""
    folder = work / f"{name}_bvh"
    folder.mkdir(exist_ok=True)
    takes = []
    for line in lines:
        bvh = folder / f"take_line{line}.bvh"
        bvh.write_text(f"BVH of line {line}\n")
        takes.append({"name": f"take_line{line}", "line": line, "seed": line - 1, "bvh": str(bvh)})
    shard_settings = {"seed": 0, "steps": 50, "model_id": "tiny", "model": "abc", "prompts": "def", **settings}
    manifest = {"format": "mld-takes", "version": 1, "blend": f"{name}.blend", "model_id": "tiny",
                "settings": {"seed": 0, "steps": 50, "device": "cuda" if index else "cpu"}, "timing": {"total_s": 1},
                "takes": takes, "shard": {"index": index, "count": count, "lines": 5, "settings": shard_settings}}
    path = work / f"{name}.json"
    path.write_text(json.dumps(manifest))
    return path


def test_batch_manifests_merge_into_one_library(tmp_path):
    from mld_core.shards import merge_manifests

    shards = [_manifest(tmp_path, "b1", 1, 2, [2, 4]), _manifest(tmp_path, "b0", 0, 2, [1, 3, 5])]
    out, bvhs = merge_manifests(shards, tmp_path / "library.json", tmp_path / "all_bvh")
    merged = json.loads(out.read_text())
    assert [t["line"] for t in merged["takes"]] == [1, 2, 3, 4, 5]
    assert [t["blend"] for t in merged["takes"]] == ["b0.blend", "b1.blend", "b0.blend", "b1.blend", "b0.blend"]
    assert merged["blends"] == ["b1.blend", "b0.blend"] and "device" not in merged["settings"]
    assert sorted(p.name for p in bvhs) == [f"take_line{i}.bvh" for i in range(1, 6)]
    assert (tmp_path / "all_bvh" / "take_line4.bvh").read_text() == "BVH of line 4\n"
    assert merged["takes"][3]["bvh"] == str(tmp_path / "all_bvh" / "take_line4.bvh")


def test_batch_manifests_of_other_runs_are_refused(tmp_path, capsys):
    a = _manifest(tmp_path, "a", 0, 2, [1, 3, 5])
    b = _manifest(tmp_path, "b", 1, 2, [2, 4], steps=8)
    c = _manifest(tmp_path, "c", 1, 2, [2, 4], model="another")
    merge = ["merge", "--out", tmp_path / "library.json"]
    refused([*merge, a, b], tmp_path, capsys, "different steps")
    refused([*merge, a, c], tmp_path, capsys, "different model files")
    refused([*merge, a], tmp_path, capsys, "shard(s) 1/2 missing")
    refused([*merge, a, a], tmp_path, capsys, "are both shard 0/2")
    (tmp_path / "a_bvh" / "take_line3.bvh").unlink()
    d = _manifest(tmp_path, "d", 1, 2, [2, 4])
    refused([*merge, a, d, "--bvh-dir", tmp_path / "all"], tmp_path, capsys, "take_line3.bvh is missing")
