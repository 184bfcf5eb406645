"""The batch with a JSON job file (a directed take, a loop, a sequence): one Action per job, each job and its
constraints' residuals in the manifest. Tiny model, bpy in a subprocess."""

from __future__ import annotations

import json

import pytest

from bpy_util import REPO, requires_bpy, run_python
from mld_core.testing import tiny_model

pytestmark = [pytest.mark.bpy, requires_bpy]


def test_batch_runs_a_job_file(tmp_path):
    model = tiny_model(tmp_path / "tiny")
    jobs = {"jobs": [
        {"prompt": "a person waves", "seconds": 2, "seed": 7,
         "keys": {"fps": 20, "keys": [{"frame": 20, "joints": {"pelvis": [0.1, 0.9, 0.3]}}]}},
        {"prompt": "a person walks", "seconds": 2, "loop": True, "path": {"points": [[0, 0, 0], [39, 0, 1]]}},
        {"sequence": [{"prompt": "a person walks", "seconds": 2}, {"prompt": "a person bows", "seconds": 2}]},
    ]}
    (tmp_path / "jobs.json").write_text(json.dumps(jobs))
    out = tmp_path / "takes.blend"
    proc = run_python([REPO / "blender_addon" / "batch.py", "--jobs", tmp_path / "jobs.json", "--model", model,
                       "--steps", "2", "--out", out], user_dir=tmp_path / "user", timeout=240)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    takes = json.loads(out.with_suffix(".json").read_text())["takes"]
    assert [t["job"] for t in takes] == jobs["jobs"]
    assert takes[0]["seed"] == 7 and takes[1]["seed"] == 1 and takes[2]["seed"] == 2  # a job's seed wins
    assert [c["kind"] for c in takes[0]["constraints"]] == ["PoseKeys"]
    assert [c["kind"] for c in takes[1]["constraints"]] == ["RootPath", "Loop"]
    assert [c["kind"] for c in takes[2]["constraints"]] == ["Continuation"]
    assert takes[2]["frames"] == 80  # 2 s + 2 s, one motion
