"""Bad and unusual input to the batch script and the add-on in Blender: each case checks the exit code, a one-line
message without a traceback and the file system after (see tests/test_reliability.py for the other surfaces)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from bpy_util import REPO, requires_bpy, run_bpy_script
from test_reliability import snapshot

pytestmark = [pytest.mark.bpy, requires_bpy]


@pytest.fixture
def work(tmp_path) -> Path:
    (tmp_path / "prompts.txt").write_text("a person walks\n")
    (tmp_path / "garbage.bvh").write_text("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 zero 0\n")
    (tmp_path / "keep.blend").write_bytes(b"a user's file")
    return tmp_path


def batch_refuses(argv, root: Path, capsys, words: str) -> None:
    from blender_addon import batch

    before = snapshot(root)
    code = batch.main(["batch.py", *map(str, argv)])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(lines) == 1 and words.lower() in lines[0].lower(), (argv, err)
    assert "Traceback" not in err and snapshot(root) == before, (argv, err)


def test_batch_checks_every_input_and_output_before_any_work(work, capsys):
    w = work
    cases = [
        (["--prompt", "walk", "--out", w / "x.blend", "--manifest", w / "x.blend"], "same file as --out"),
        (["--prompt", "walk", "--out", w / "x.blend", "--preview", w / "x.blend"], "same file as --out"),
        (["--prompts", w / "prompts.txt", "--out", w / "x.blend", "--manifest", w / "prompts.txt"], "same file"),
        (["--prompt", "walk", "--out", w / "keep.blend"], "exists; pass --overwrite"),
        (["--prompt", "walk", "--out", w / "prompts.txt" / "x.blend"], "is a file, not a folder"),
        (["--prompt", "walk", "--out", w / "x.blend", "--bvh-rig", w / "garbage.bvh", "--bvh-scale", "inf"],
         "--bvh-scale must be a finite number"),
        (["--prompt", "walk", "--out", w / "x.blend", "--bvh-rig", w / "garbage.bvh", "--bvh-scale", "1e-30"],
         "--bvh-scale must be between"),
        (["--prompt", "walk", "--out", w / "x.blend", "--bvh-rig", w / "garbage.bvh"], "not a usable BVH file"),
        (["--prompt", "walk", "--out", w / "x.blend", "--fps", "0"], "fps must be between"),
        (["--prompt", "walk", "--out", w / "x.blend", "--seed", str(2**63)], "Seed must be between"),
        (["--prompt", "!!! ???", "--out", w / "x.blend"], "has no words"),
        (["--prompt", "walk", "--out", w / "x.blend", "--seconds", "1"], "between 2 and 9.8 seconds"),
        (["--prompt", "walk", "--out", w / "x.blend", "--tolerance", "nan"], "finite"),
        (["--prompt", "walk", "--out", w / "x.blend", "--bvh-dir", w / "prompts.txt"], "not a folder"),
        (["--prompt", "walk", "--out", w / "t.blend", "--bvh-dir", w / "t.blend", "--overwrite"],
         "is the file --out"),
        (["--prompt", "walk", "--out", w / "t.blend", "--bvh-dir", w / "t.blend" / "bvh"], "is the file --out"),
        (["--prompt", "walk", "--out", w / "t.blend", "--bvh-dir", w / "t.json"], "is the file --manifest"),
    ]
    for text in ("-5 a person walks", "2.5 a person walks", "100"):
        name = f"bad{len(cases)}.txt"
        (w / name).write_text(text + "\n")
        cases.append((["--prompts", w / name, "--out", w / "x.blend"], "line 1"))
    for argv, words in cases:
        batch_refuses(argv, w, capsys, words)


LINKED = r"""
import sys
sys.path.insert(0, {repo!r})
import bpy, addon_utils
from pathlib import Path
work = Path({work!r})
out = {{}}
# a library file with an armature, and a file with only a cube
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.object.armature_add()
bpy.context.object.name = "LibRig"
bpy.ops.wm.save_as_mainfile(filepath=str(work / "lib.blend"))
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.mesh.primitive_cube_add()
bpy.ops.wm.save_as_mainfile(filepath=str(work / "cube.blend"))

bpy.ops.wm.read_factory_settings(use_empty=True)
addon_utils.enable("blender_addon", default_set=True)
from blender_addon.scene import key_takes as apply
from blender_addon import batch
with bpy.data.libraries.load(str(work / "lib.blend"), link=True) as (src, dst):
    dst.objects = ["LibRig"]
rig = dst.objects[0]
bpy.context.scene.collection.objects.link(rig)
out["linked_problem"] = apply.check_target(rig)
bpy.context.scene.mld_motion.target = rig
out["poll"] = bpy.ops.mld.generate.poll()
prop = bpy.context.scene.mld_motion.bl_rna.properties["seconds"]
out["seconds_range"] = [prop.hard_min, prop.hard_max]
import contextlib, io
err = io.StringIO()
with contextlib.redirect_stderr(err):
    out["batch_cube"] = batch.main(["batch.py", "--prompt", "a person walks", "--out", str(work / "c.blend"),
                                    "--rig", str(work / "cube.blend")])
out["batch_cube_err"] = err.getvalue()
emit(out)
"""


def test_linked_armature_is_refused_and_the_panel_range_comes_from_the_model(tmp_path):
    r = run_bpy_script(LINKED.format(repo=str(REPO), work=str(tmp_path)), tmp_path, timeout=180)
    assert "is linked from" in r["linked_problem"] and "library override" in r["linked_problem"]
    assert r["poll"] is False
    limits = json.loads((REPO / "mld_core" / "weights" / "default" / "config.json").read_text())
    assert r["seconds_range"] == pytest.approx([limits["min_frames"] / 20, limits["max_frames"] / 20])
    assert r["batch_cube"] == 2 and not (tmp_path / "c.blend").exists()
    assert "has no armature object" in r["batch_cube_err"] and "Traceback" not in r["batch_cube_err"]



def test_batch_job_files_are_checked_before_any_work(work, capsys):
    import json

    w = work
    bad = {
        "not_json.json": ("{", "not valid JSON"),
        "no_jobs.json": (json.dumps({"jobs": []}), "expected"),
        "both.json": (json.dumps({"jobs": [{"prompt": "a walk", "sequence": [{"prompt": "a", "seconds": 2}]}]}),
                      "not both"),
        "unknown.json": (json.dumps({"jobs": [{"prompt": "a walk", "speed": 3}]}), "only"),
        "joint.json": (json.dumps({"jobs": [{"prompt": "a walk", "keys": {"keys": [{"frame": 1, "joints": {"x": [0, 0, 0]}}]}}]}),
                       "unknown joint"),
        "seq_keys.json": (json.dumps({"jobs": [{"sequence": [{"prompt": "a walk", "seconds": 2}], "loop": True}]}),
                          "takes no keys"),
        "long.json": (json.dumps({"jobs": [{"sequence": [{"prompt": "a walk", "seconds": 2},
                                                         {"prompt": "a run", "seconds": 9.6}]}]}), "segment 2"),
    }
    walk = '{"jobs": [{"prompt": "a walk", %s}]}'
    bad.update({
        "three.json": (walk % '"seconds": "three"', "job 1: seconds must be a number, got 'three'"),
        "nan.json": (walk % '"seconds": NaN', ".jobs[0].seconds must be a finite number"),
        "list.json": (walk % '"seconds": [3]', "job 1: seconds must be a number, got [3]"),
        "huge.json": (walk % '"seconds": 1e999', ".jobs[0].seconds must be a finite number"),
        "short.json": (walk % '"seconds": 1', "job 1: seconds must be between 2 and 9.8"),
        "loop.json": (walk % '"loop": "false"', "job 1: loop must be true or false, got 'false'"),
        "seed.json": (walk % '"seed": 4294967296', "job 1: Seed must be between"),
        "frame.json": (walk % '"keys": {"keys": [{"frame": 1e308, "joints": {"pelvis": [0, 1, 0]}}]}',
                       ".jobs[0].keys.keys[0].frame must be a finite number"),
        "deep.json": ('{"jobs": ' + "[" * 50_000 + "]" * 50_000 + "}", "nested more than 32 levels deep"),
    })
    for name, (text, words) in bad.items():
        (w / name).write_text(text)
        batch_refuses(["--jobs", w / name, "--out", w / "x.blend"], w, capsys, words)


@contextlib.contextmanager
def read_only(folder: Path):
    """``folder`` made read-only (an immutable folder for root, who writes anywhere else), then writable again."""
    folder.mkdir()
    if os.geteuid() == 0:
        if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(folder)]).returncode != 0:
            pytest.skip("running as root on a file system without chattr +i: no folder is read-only to root")
        try:
            yield folder
        finally:
            subprocess.run(["chattr", "-i", str(folder)])
    else:
        folder.chmod(0o555)
        try:
            yield folder
        finally:
            folder.chmod(0o755)


def test_batch_export_flags_are_checked_before_any_work(work, capsys):
    """--export and its flags (docs/game_engines.md): unknown values, exports colliding with the .blend, the
    manifest, --bvh-dir or a file that exists, a file where the folder goes, a read-only folder."""
    w = work
    (w / "walks_s0.fbx").write_bytes(b"an earlier export")
    walk = ["--prompt", "a person walks", "--out", w / "out" / "x.blend"]
    cases = [
        (["--export", "obj"], "--export: unknown value 'obj'; use fbx, glb or bvh"),
        (["--export", "fbx,fbx"], "--export: fbx is named twice"),
        (["--export", "fbx", "--bone-names", "maya"], "--bone-names: unknown value 'maya'"),
        (["--export", "glb", "--root-motion", "sideways"], "--root-motion: unknown value 'sideways'"),
        (["--root-motion", "in-place"], "--root-motion needs --export"),
        (["--export", "fbx", "--root-yaw"], "--root-yaw needs --root-motion in-place or root-bone"),
        (["--export", "fbx", "--manifest", w / "out" / "walks_s0.fbx"],
         "--export fbx (walks_s0) " + str(w / "out" / "walks_s0.fbx") + " is the same file as --manifest"),
        (["--export", "fbx", "--one-file", "--export-dir", w / "out", "--manifest", w / "out" / "x.fbx"],
         "--export fbx (every take) " + str(w / "out" / "x.fbx") + " is the same file as --manifest"),
        (["--export", "bvh", "--bvh-dir", w / "out"], "--export bvh (walks_s0) " + str(w / "out" / "walks_s0.bvh")
         + " is the same file as --bvh-dir file (walks_s0)"),
        (["--export", "fbx", "--export-dir", w], str(w / "walks_s0.fbx") + " exists; pass --overwrite"),
        (["--export", "fbx", "--export-dir", w / "keep.blend"], "--export-dir " + str(w / "keep.blend")
         + " exists and is not a folder"),
    ]
    for argv, words in cases:
        batch_refuses(walk + argv, w, capsys, words)
    with read_only(w / "locked") as locked:
        batch_refuses(walk + ["--export", "fbx", "--export-dir", locked / "engine"], w, capsys,
                      f"--export-dir {locked / 'engine'}: the folder {locked} cannot be written")
