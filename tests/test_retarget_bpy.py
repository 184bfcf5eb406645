"""Retargeting checked by Blender itself (bpy in a subprocess, with a timeout and a scratch BLENDER_USER_RESOURCES).

Builds the canonical armature, Rigify's metarig and the rig Rigify generates from it, imports a Bandai clip with
Blender's own BVH importer, detects each bone map, retargets a real clip, keys it (reduced, auto-clamped Bezier)
and reads back what Blender plays (research/retarget_fidelity.py does the work).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = [
    pytest.mark.bpy,
    pytest.mark.slow,
    pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="needs the bpy module (pip install bpy)"),
]


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("retarget_bpy")
    out = tmp / "fidelity.json"
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp / "blender_user"), PYTHONPATH=str(REPO))
    cmd = [sys.executable, str(REPO / "research" / "retarget_fidelity.py"), "--rigify-generated",
           "--take", "dataset-2_walk-turn-left_normal_027", "--json", str(out)]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return {r["rig"]: r for r in json.loads(out.read_text())}


def test_every_rig_is_detected_and_retargeted(rows):
    assert {name: r["preset"] for name, r in rows.items()} == {
        "canonical": "canonical", "rigify_metarig": "rigify_metarig", "rigify": "rigify", "bandai_bvh": "bandai",
    }


@pytest.mark.parametrize("rig", ["canonical", "rigify_metarig", "rigify", "bandai_bvh"])
def test_fidelity_as_blender_plays_it(rows, rig):
    r = rows[rig]
    played = r["blender"]
    # Wrists, ankles and head within 5% of limb length on average, after key reduction, as Blender evaluates.
    for eff in ("left_wrist", "right_wrist", "left_ankle", "right_ankle", "head"):
        assert played[f"{eff}_err"] < 0.05, (eff, played)
    assert played["sink_cm"] < 1.0
    # The walk turns ~90 degrees left; the rig turns the same way by the same amount and walks the same way.
    assert played["turn_src_deg"] > 60
    assert abs(played["turn_rig_deg"] - played["turn_src_deg"]) < 2.0
    assert played["facing_err_deg"] < 2.0
    assert played["travel_angle_deg"] < 2.0


@pytest.mark.parametrize("rig", ["canonical", "rigify_metarig", "rigify", "bandai_bvh"])
def test_numpy_model_agrees_with_blender(rows, rig):
    r = rows[rig]
    # Our FK of the keyed curves vs the bone heads Blender evaluates (pose convention, parents, Rigify's FK
    # controls with the preset's properties): sub-millimetre.
    assert r["fk_vs_blender_max_m"] < 1e-4
    # Our model of Blender's auto-clamped Bezier curves (which the reduction's error bound relies on).
    assert r["fcurve_model_max_err"] < 1e-5
    assert 0.0 < r["reduction_ratio"] < 1.0
