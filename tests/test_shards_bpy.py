"""The batch script sharded (bpy module, tiny model): shards 0/2 + 1/2 merged with --merge are the unsharded
run's library (the same takes, seeds and BVH files); a bad --shard is one error line with nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bpy_util import REPO, requires_bpy, run_python
from test_reliability import snapshot

pytestmark = [pytest.mark.bpy, requires_bpy]

RUN_ONLY = ("time_s", "key_s", "generate_s", "created", "bvh")  # about the run that made a take, not the take


def _batch(tmp_path: Path, model: Path, out: str, *extra) -> dict:
    proc = run_python([REPO / "blender_addon" / "batch.py", "--prompts", tmp_path / "prompts.txt", "--model", model,
                       "--seconds", "2", "--steps", "2", "--out", tmp_path / out, *extra],
                      user_dir=tmp_path / "blender_user", timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads((tmp_path / out).with_suffix(".json").read_text())


def _main(batch, *args) -> int:
    return batch.main(["batch.py", *map(str, args)])


def test_batch_shards_merged_are_the_unsharded_library(tmp_path, capsys):
    from blender_addon import batch
    from mld_core.testing import tiny_model

    model = tiny_model(tmp_path / "tiny")
    (tmp_path / "prompts.txt").write_text("a person walks\nsomeone waves\n# a comment\n50 a person bows\n")
    whole = _batch(tmp_path, model, "whole.blend", "--bvh-dir", tmp_path / "whole_bvh")
    shards = [_batch(tmp_path, model, f"s{i}.blend", "--bvh-dir", tmp_path / f"s{i}_bvh", "--shard", f"{i}/2")
              for i in (0, 1)]
    assert [t["line"] for t in shards[0]["takes"]] == [1, 4] and [t["line"] for t in shards[1]["takes"]] == [2]
    assert _main(batch, "--merge", tmp_path / "s1.json", tmp_path / "s0.json", "--out", tmp_path / "library.json",
                 "--bvh-dir", tmp_path / "library_bvh") == 0
    library = json.loads((tmp_path / "library.json").read_text())
    assert [t["blend"] for t in library["takes"]] == [str(tmp_path / n) for n in ("s0.blend", "s1.blend", "s0.blend")]
    assert len(library["takes"]) == len(whole["takes"]) == 3
    for mine, theirs in zip(library["takes"], whole["takes"]):  # the same takes: seeds, names, keys, badges
        assert {k: v for k, v in mine.items() if k not in RUN_ONLY + ("blend",)} == \
               {k: v for k, v in theirs.items() if k not in RUN_ONLY}
        assert Path(mine["bvh"]).read_bytes() == Path(theirs["bvh"]).read_bytes()  # one take per line: exact

    # bad shards: one error line, nothing written
    for shard, words in (("3/2", "the index must be 0 to 1"), ("0/0", "number of shards must be 1"),
                         ("x", "is not I/N"), ("3/4", "so shard 3 has none")):
        before = snapshot(tmp_path)
        assert _main(batch, "--prompts", tmp_path / "prompts.txt", "--model", model, "--out", tmp_path / "x.blend",
                     "--shard", shard) == 2
        err = capsys.readouterr().err
        lines = [line for line in err.splitlines() if line.startswith("error:")]
        assert len(lines) == 1 and words in lines[0] and "Traceback" not in err, err
        assert snapshot(tmp_path) == before
    before = snapshot(tmp_path)
    assert _main(batch, "--merge", tmp_path / "s0.json", "--out", tmp_path / "y.json") == 2
    assert "shard(s) 1/2 missing" in capsys.readouterr().err and snapshot(tmp_path) == before
