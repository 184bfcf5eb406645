"""The add-on's output does not change when its code is reorganised: the F-curves it writes for fixture takes on
the canonical armature (exact road; reduced, Euler, foot lock), Rigify's metarig and a BVH import equal the ones
recorded before (scripts/record_keys.py; re-record only for an intended change of output, and say so)."""

from __future__ import annotations

import sys

import pytest

from bpy_util import REPO, requires_bpy, run_python

pytestmark = [pytest.mark.bpy, requires_bpy]


def test_keys_equal_the_recorded_ones(tmp_path):
    proc = run_python([REPO / "scripts" / "record_keys.py", "--compare", REPO / "tests/fixtures/rigs/keys_reference.npz"],
                      user_dir=tmp_path / "user", timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "largest difference" in proc.stdout and "0 structural differences" in proc.stdout


def test_the_comparison_sees_a_change():
    sys.path.insert(0, str(REPO / "scripts"))
    import numpy as np
    from record_keys import compare

    reference = {"a/co": np.zeros((3, 2), np.float32), "a/interpolation": np.zeros(3, np.int8)}
    assert compare(dict(reference), reference) == (0.0, [])
    worst, problems = compare({"a/co": np.full((3, 2), 1e-3, np.float32), "a/interpolation": np.ones(3, np.int8)},
                              reference)
    assert worst == pytest.approx(1e-3) and problems == ["a/interpolation: interpolation differs"]
    assert compare({}, reference)[1] == ["missing a/co", "missing a/interpolation"]
