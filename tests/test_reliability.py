"""Bad and unusual input on every surface without Blender (generate, data prepare, train, evaluate, bench, the
Python API, the output writer): each case checks the exit code (or exception), a one-line message without a
traceback, and that the file system is exactly as before (nothing written, existing files byte-identical).
The batch script and the add-on in Blender: tests/test_reliability_bpy.py. Summary: docs/reliability.md."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from mld_core import inputs
from mld_core.cli import main
from mld_core.fileio import OutputSet
from mld_core.testing import tiny_model

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("tiny") / "model")


def snapshot(root: Path) -> dict:
    """Every file under ``root`` with its bytes, and every folder."""
    return {p.relative_to(root).as_posix(): (None if p.is_dir() else p.read_bytes()) for p in sorted(root.rglob("*"))}


def refused(argv, root: Path, capsys, words: str) -> str:
    """Run the CLI; it must exit 2 with one ``error:`` line naming ``words`` and leave ``root`` unchanged."""
    before = snapshot(root)
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2, (argv, err)
    assert len(lines) == 1 and words.lower() in lines[0].lower(), (argv, err)
    assert "Traceback" not in err, err
    assert snapshot(root) == before, f"{argv} changed the file system"
    return lines[0]


@pytest.fixture
def work(tmp_path) -> Path:
    (tmp_path / "keep.npz").write_bytes(b"user data")
    (tmp_path / "prompts.txt").write_text("a person walks\n")
    (tmp_path / "a_file").write_text("not a folder")
    (tmp_path / "folder").mkdir()
    return tmp_path


# -- generate ------------------------------------------------------------------------------------------------------
GENERATE_CASES = [
    (["--guidance", "nan"], "finite"),
    (["--guidance", "inf"], "finite"),
    (["--guidance", "1e30"], "guidance must be between"),
    (["--guidance", "-1"], "guidance must be between"),
    (["--seed", str(2**63)], "--seed must be between"),
    (["--seed", str(2**70)], "--seed must be between"),
    (["--seed", "-1"], "--seed must be between"),
    (["--threads", "-1"], "--threads must be between"),
    (["--steps", "0"], "--steps must be between"),
    (["--fps", "0"], "--fps must be between"),
    (["--fps", "-5"], "--fps must be between"),
    (["--seconds", "nan"], "finite"),
    (["--seconds", "0.5"], "between 1 and 9.8 seconds"),
    (["--seconds", "100"], "between 1 and 9.8 seconds"),
    (["--variants", "0"], "--variants must be between"),
    (["--variants", "2", "--best", "3"], "--best must be between"),
    (["--side-redraws", "9"], "--side-redraws must be between 0 and 8"),
    (["--side-redraws", "-1"], "--side-redraws must be between 0 and 8"),
    (["--verb-redraws", "9"], "--verb-redraws must be between 0 and 8"),
    (["--verb-redraws", "-1"], "--verb-redraws must be between 0 and 8"),
]


@pytest.mark.parametrize("extra, words", GENERATE_CASES, ids=[" ".join(c[0]) for c in GENERATE_CASES])
def test_generate_refuses_bad_numbers_before_any_work(model, work, capsys, extra, words):
    refused(["generate", "a person walks", "--model", model, "--out", work / "t.npz", *extra], work, capsys, words)


def test_generate_output_paths(model, work, capsys):
    gen = ["generate", "a person walks", "--model", model, "--steps", "1"]
    refused([*gen, "--out", work / "x.npz", "--bvh", work / "x.npz"], work, capsys, "same file")
    refused(["generate", "--prompts", work / "prompts.txt", "--model", model, "--out", work / "prompts.txt"], work,
            capsys, "same file")
    refused([*gen, "--out", work / "keep.npz"], work, capsys, "exists; pass --overwrite")
    refused([*gen, "--out", work / "folder"], work, capsys, "is a folder")
    refused([*gen, "--out", work / "a_file" / "t.npz"], work, capsys, "is a file, not a folder")
    refused([*gen, "--out", work / "t.npz", "--bvh", work / "a_file" / "t.bvh"], work, capsys, "is a file")
    (work / "x_001.bvh").write_text("a user's file")  # the per-variant BVH names are checked too
    refused([*gen, "--variants", "2", "--out", work / "t.npz", "--bvh", work / "x.bvh"], work, capsys,
            "x_001.bvh exists")
    (work / "x_001.bvh").unlink()
    # --overwrite replaces, and missing folders are made for outputs
    assert main([*map(str, gen), "--out", str(work / "keep.npz"), "--overwrite", "--bvh",
                 str(work / "new" / "dir" / "t.bvh")]) == 0
    assert np.load(work / "keep.npz")["joints"].shape[-2:] == (22, 3)
    assert (work / "new" / "dir" / "t.bvh").is_file()
    assert not [p for p in work.rglob(".*") if p.is_file()], "temporary files left"


def test_generate_prompt_text_and_files(model, work, capsys):
    gen = ["--model", model, "--out", work / "t.npz"]
    refused(["generate", "!!! ???", *gen], work, capsys, "has no words")
    refused(["generate", "   ", *gen], work, capsys, "empty prompt")
    for text, words in [("-5 a person walks\n", "positive whole number of frames"),
                        ("2.5 a person walks\n", "positive whole number of frames"),
                        ("100\n", "no prompt text"), ("a walk\n!!!\n", "line 2")]:
        (work / "bad.txt").write_text(text)
        refused(["generate", "--prompts", work / "bad.txt", *gen], work, capsys, words)
    refused(["generate", "a person walks", "--action", "walk", *gen], work, capsys, "needs an action-conditioned")


@pytest.mark.parametrize("edit, words", [
    (lambda c: [c], "expected a JSON object"),
    (lambda c: {**c, "vae": "garbage"}, "vae must be an object"),
    (lambda c: {**c, "fps": 0}, "fps must be a positive whole number"),
    (lambda c: {**c, "std": [math.nan] * len(c["std"])}, "non-finite"),
    (lambda c: {**c, "text_encoder": {"kind": "no-such-encoder"}}, "unknown text encoder kind"),
], ids=["list", "vae-garbage", "fps-0", "nan-std", "unknown-encoder"])
def test_generate_refuses_a_broken_model_config(model, work, capsys, edit, words):
    broken = work / "broken_model"
    shutil.copytree(model, broken)
    config = json.loads((broken / "config.json").read_text())
    (broken / "config.json").write_text(json.dumps(edit(config), allow_nan=True))
    refused(["generate", "a person walks", "--model", broken, "--out", work / "t.npz"], work, capsys, words)


def test_the_same_seed_rule_for_prompt_files_as_the_batch(model, tmp_path):
    (tmp_path / "p.txt").write_text("a person walks\na person runs\n")
    assert main(["generate", "--prompts", str(tmp_path / "p.txt"), "--model", str(model), "--steps", "1",
                 "--seed", "7", "--variants", "2", "--out", str(tmp_path / "t.npz")]) == 0
    assert np.load(tmp_path / "t.npz")["seeds"].tolist() == [7, 8, 9, 10]


# -- the Python API --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def pipe(model):
    from mld_core.pipeline import MLDPipeline

    return MLDPipeline.from_pretrained(model)


@pytest.mark.parametrize("kwargs, words", [
    (dict(prompts=None), "prompts must be a string"),
    (dict(prompts=42), "prompts must be a string"),
    (dict(guidance_scale=float("nan")), "finite"),
    (dict(guidance_scale=float("inf")), "finite"),
    (dict(num_inference_steps=0), "num_inference_steps must be between"),
    (dict(seed=1.7), "whole number"),
    (dict(seed=2**70), "seed must be between"),
    (dict(seed=-3), "seed must be between"),
    (dict(num_variants=0), "num_variants must be between"),
    (dict(seconds=float("nan")), "seconds"),
], ids=lambda v: str(v)[:40])
def test_pipeline_call_rejects_bad_arguments(pipe, kwargs, words):
    kwargs = {"prompts": "a person walks", "num_inference_steps": 1, **kwargs}
    prompts = kwargs.pop("prompts")
    with pytest.raises(ValueError, match=words):
        pipe(prompts, **kwargs)


def test_pipeline_never_returns_non_finite_joints(pipe):
    with pytest.raises(ValueError, match="non-finite"):
        pipe("a person walks", guidance_scale=1e30, num_inference_steps=2)
    out = pipe("a person walks", num_inference_steps=1, seed=np.int64(3))  # numpy integers are fine seeds
    assert np.isfinite(out.joints).all() and out.seeds == [3]


def _keys(targets, **settings):
    from mld_core.take_fixes.constraints import PoseKeys

    return PoseKeys(targets, **settings)


def _path(frames, points):
    from mld_core.take_fixes.constraints import RootPath

    return RootPath(frames, np.asarray(points, np.float64))


def _constraints(items, **settings):
    from mld_core.take_fixes.constraints import Constraints

    return Constraints(items, **settings)


POSE = [0.0, 0.9, 0.0]
CONSTRAINT_CASES = [  # made by the user's own code: refused when made, before any generation
    (lambda: _keys({-3: {"pelvis": POSE}}), "PoseKeys frame must be 0 or more, got -3"),
    (lambda: _keys({2.5: {"pelvis": POSE}}), "PoseKeys frame must be a whole number"),
    (lambda: _keys({True: {"pelvis": POSE}}), "PoseKeys frame must be a number"),
    (lambda: _keys({10: {"nose": POSE}}), "unknown joint 'nose'"),
    (lambda: _keys({10: {"pelvis": [0.0, math.nan, 0.0]}}), "pelvis y must be a finite number"),
    (lambda: _keys({10: {"pelvis": [0.0, 0.9]}}), "pelvis must be (x, y, z)"),
    (lambda: _keys({10: {"pelvis": "0 0.9 0"}}), "pelvis must be (x, y, z)"),
    (lambda: _keys({10: {}}), "at least one joint"),
    (lambda: _keys({}), "targets are empty"),
    (lambda: _keys([(10, {"pelvis": POSE})]), "targets must be a dict"),
    (lambda: _path([10, 5], [[0, 0], [0, 1]]), "frames must increase, got 10 then 5"),
    (lambda: _path([0, 10, 10], [[0, 0], [0, 1], [0, 2]]), "frames must increase, got 10 then 10"),
    (lambda: _path([-5, 10], [[0, 0], [0, 1]]), "RootPath frame must be 0 or more, got -5"),
    (lambda: _path([0, 10], [[0, 0]]), "one (x, z) per frame (2)"),
    (lambda: _path([0, 10], [[0, 0], [math.inf, 1]]), "point 2 x must be a finite number"),
    (lambda: _keys({10: {"pelvis": POSE}}, weight=-1), "PoseKeys weight must be 0 or more"),
    (lambda: _constraints([{"frame": 10, "joints": {"pelvis": POSE}}]), "item 1 is a dict, not a constraint"),
    (lambda: _constraints([[10, POSE]]), "item 1 is a list, not a constraint"),
    (lambda: _constraints(_keys({10: {"pelvis": POSE}})), "takes a list of constraints"),
    (lambda: _constraints([], steps=-1), "Constraints steps must be between 0"),
    (lambda: _constraints([], lr=math.nan), "Constraints lr must be a finite number"),
]


@pytest.mark.parametrize("make, words", CONSTRAINT_CASES, ids=[c[1][:40] for c in CONSTRAINT_CASES])
def test_constraint_objects_check_themselves_when_made(make, words):
    with pytest.raises(inputs.InputError) as caught:
        make()
    assert words in str(caught.value) and "\n" not in str(caught.value)


def test_constraints_the_take_cannot_hold_are_refused_before_sampling(pipe, monkeypatch):
    from mld_core.take_fixes.constraints import Loop

    def no_sampling(*args, **kwargs):
        raise AssertionError("sampled before the constraints were checked")

    monkeypatch.setattr(pipe, "_condition", no_sampling)
    with pytest.raises(inputs.InputError, match="reaches frame 40, but the take has 40 frames"):
        pipe("a person walks", 2.0, constraints=_constraints([_keys({40: {"head": POSE}})]))
    with pytest.raises(inputs.InputError, match="constraints must be a mld_core.take_fixes.constraints.Constraints"):
        pipe("a person walks", 2.0, constraints=[Loop()])
    with pytest.raises(inputs.InputError, match="the same length"):
        pipe(["a person walks", "a person runs"], [2.0, 3.0], constraints=_constraints([Loop()]))


SEQUENCE_CASES = [
    (dict(segments=[(None, 2.0)]), "sequence segment 1: The prompt must be text, not NoneType"),
    (dict(segments=[("a person walks", 2.0), ("!!!", 2.0)]), "sequence segment 2: The prompt '!!!' has no words"),
    (dict(segments=[("a person walks", "three")]), "sequence segment 1: seconds must be a number, got 'three'"),
    (dict(segments=[("a person walks", None)]), "sequence segment 1: seconds must be a number"),
    (dict(segments=[("a person walks", math.nan)]), "sequence segment 1: seconds must be a finite number"),
    (dict(segments=[("a person walks", 2.0, 1)]), "segment 1 must be a (prompt, seconds) pair"),
    (dict(segments=["a person walks"]), "segment 1 must be a (prompt, seconds) pair"),
    (dict(segments=None), "a sequence is a list of (prompt, seconds) segments"),
    (dict(segments="a person walks"), "a sequence is a list of (prompt, seconds) segments"),
    (dict(segments=[]), "at least one (prompt, seconds) segment"),
    (dict(overlap_s=-1), "overlap_s must be at least one frame"),
    (dict(overlap_s=0), "overlap_s must be at least one frame"),
    (dict(overlap_s=math.nan), "overlap_s must be a finite number"),
    (dict(overlap_s="half"), "overlap_s must be a number"),
    (dict(overlap_s=1.5), "overlap_s 1.5 is longer than sequence segment 1 (1 s)"),
    (dict(segments=[("a person walks", 1.0), ("a person runs", 9.5)]),
     "sequence segment 2: length (+ 0.5 s overlap) must be between 1 and 9.8 seconds"),
]


@pytest.mark.parametrize("kwargs, words", SEQUENCE_CASES, ids=[c[1][:40] for c in SEQUENCE_CASES])
def test_a_sequence_is_checked_before_any_segment_is_made(pipe, monkeypatch, kwargs, words):
    def no_generation(*args, **kwargs):
        raise AssertionError("a segment was generated before the sequence was checked")

    monkeypatch.setattr(type(pipe), "__call__", no_generation)
    kwargs = {"segments": [("a person walks", 1.0), ("a person runs", 1.0)], **kwargs}
    with pytest.raises(inputs.InputError) as caught:
        pipe.sequence(kwargs.pop("segments"), **kwargs)
    assert words in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize("prompts, words", [
    ([None], "prompt 1 must be text, not NoneType"), ([42], "prompt 1 must be text, not int"),
    (["a person walks", b"a person runs"], "prompt 2 must be text, not bytes"),
    (None, "prompts must be a string or a list of strings, got NoneType"),
    (42, "prompts must be a string or a list of strings, got int"),
    (b"a person walks", "prompts must be a string or a list of strings, got bytes"),
], ids=["[None]", "[42]", "[text, bytes]", "None", "42", "bytes"])
def test_coverage_refuses_what_is_not_a_prompt(pipe, prompts, words):
    with pytest.raises(inputs.InputError, match=re.escape(words)):
        pipe.coverage(prompts)
    assert [c.prompt for c in pipe.coverage(("a person walks", "a person runs"))] == ["a person walks", "a person runs"]


# -- the output writer: all or none, and one winner of a race --------------------------------------------------------
def test_output_set_commits_all_or_none(tmp_path):
    (tmp_path / "b.txt").write_text("someone else's")
    with pytest.raises(FileExistsError):
        with OutputSet() as out:
            out.stage(tmp_path / "a.txt", lambda t: Path(t).write_text("a"))
            out.stage(tmp_path / "b.txt", lambda t: Path(t).write_text("b"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.txt"]  # a.txt was rolled back, no temporary left
    assert (tmp_path / "b.txt").read_text() == "someone else's"
    with pytest.raises(RuntimeError):
        with OutputSet() as out:
            out.stage(tmp_path / "new" / "c.txt", lambda t: Path(t).write_text("c"))
            raise RuntimeError("a failure after staging")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.txt"]  # the folder it made is gone too


def test_two_runs_racing_for_one_output_one_wins(tmp_path):
    first, second = OutputSet(), OutputSet()
    first.stage(tmp_path / "take.blend", lambda t: Path(t).write_text("first"))
    second.stage(tmp_path / "take.blend", lambda t: Path(t).write_text("second"))
    first.commit()
    with pytest.raises(FileExistsError, match="another run"):
        second.commit()
    assert (tmp_path / "take.blend").read_text() == "first"
    assert [p.name for p in tmp_path.iterdir()] == ["take.blend"]


def test_check_outputs_resolves_paths(tmp_path):
    with pytest.raises(inputs.InputError, match="same file"):
        inputs.check_outputs({"--out": tmp_path / "x" / ".." / "t.npz", "--bvh": tmp_path / "t.npz"})
    with pytest.raises(inputs.InputError, match="same file as --prompts"):
        inputs.check_outputs({"--out": tmp_path / "p.txt"}, {"--prompts": tmp_path / "." / "p.txt"})


# -- data prepare, train, evaluate, bench -------------------------------------------------------------------------
def test_data_prepare_keeps_what_the_user_added(fixtures, tmp_path, capsys):
    src, out = fixtures / "bandai", tmp_path / "prepared"
    assert main(["data", "prepare", "bandai", str(src), "--out", str(out), "--workers", "1", "--quiet"]) == 0
    capsys.readouterr()
    (out / "my_notes.txt").write_text("mine")
    (out / "texts" / "extra.txt").write_text("mine too")
    refused(["data", "prepare", "bandai", src, "--out", out, "--workers", "1", "--quiet"], tmp_path, capsys,
            "did not write")
    (out / "my_notes.txt").unlink()
    (out / "texts" / "extra.txt").unlink()
    assert main(["data", "prepare", "bandai", str(src), "--out", str(out), "--workers", "1", "--quiet"]) == 0
    (tmp_path / "a_file").write_text("x")
    refused(["data", "prepare", "bandai", src, "--out", tmp_path / "a_file" / "out"], tmp_path, capsys,
            "is a file, not a folder")


def _prepare_argv(kind: str, fixtures: Path, root: Path) -> list:
    """``data prepare bandai`` of the fixture clips, or ``data prepare bvh`` of a folder of two of them."""
    if kind == "bandai":
        return ["data", "prepare", "bandai", fixtures / "bandai", "--workers", "1", "--quiet"]
    src = root / "library"
    if not src.exists():
        src.mkdir()
        for name in ("dataset-2_walk-turn-left_normal_027", "dataset-2_wave-right-hand_normal_026"):
            shutil.copy(fixtures / "bandai" / f"{name}.bvh", src / f"{name}.bvh")
    return ["data", "prepare", "bvh", src, "--caption-template", "a person {name}"]


def _complete(out: Path) -> bool:
    """``out`` holds exactly the files its manifest lists."""
    from mld_core.data.bandai import MANIFEST, written_files

    listed = json.loads((out / MANIFEST).read_text())["files"]
    return sorted(set(listed) | {MANIFEST}) == written_files(out)


@pytest.mark.parametrize("kind", ["bandai", "bvh"])
@pytest.mark.parametrize("previous", [False, True], ids=["new", "rerun"])
def test_data_prepare_racing_for_one_out_has_one_winner(fixtures, tmp_path, capsys, monkeypatch, kind, previous):
    import threading

    from mld_core.data import bandai, bvh_library  # bvh_library imported before bandai.swap_into_place is patched

    argv, out = _prepare_argv(kind, fixtures, tmp_path), tmp_path / "prepared"
    if previous:  # a rerun over an output of this command
        assert main([*map(str, argv), "--out", str(out)]) == 0
    swap, barrier, codes = bandai.swap_into_place, threading.Barrier(2, timeout=120), []

    def swap_together(tmp, path, found):  # both runs have checked --out and built their folders: now both swap
        barrier.wait()
        swap(tmp, path, found)

    monkeypatch.setattr(bandai, "swap_into_place", swap_together)
    monkeypatch.setattr(bvh_library, "swap_into_place", swap_together)
    runs = [threading.Thread(target=lambda: codes.append(main([*map(str, argv), "--out", str(out)])))
            for _ in range(2)]
    for r in runs:
        r.start()
    for r in runs:
        r.join()
    err = capsys.readouterr().err
    assert sorted(codes) == [0, 2], (codes, err)
    assert [line for line in err.splitlines() if line.startswith("error:")] == [
        f"error: --out {out} was written by another run meanwhile; this run kept nothing - choose another folder or "
        "run it again"], err
    assert "Traceback" not in err and _complete(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["prepared"] + (["library"] if kind == "bvh" else []))


@pytest.mark.parametrize("kind", ["bandai", "bvh"])
def test_data_prepare_refuses_an_out_another_run_wrote_meanwhile(fixtures, tmp_path, capsys, monkeypatch, kind):
    import threading

    from mld_core.data import bandai, bvh_library  # bvh_library imported before bandai.swap_into_place is patched

    argv, out = _prepare_argv(kind, fixtures, tmp_path), tmp_path / "prepared"
    swap, after = bandai.swap_into_place, {}

    def other_run_first(tmp, path, found):  # between this run's check of --out and its swap, another run writes it
        monkeypatch.setattr(bandai, "swap_into_place", swap)
        monkeypatch.setattr(bvh_library, "swap_into_place", swap)
        other = threading.Thread(target=main, args=([*map(str, argv), "--out", str(out)],))
        other.start()
        other.join()
        after.update((k, v) for k, v in snapshot(tmp_path).items() if not k.startswith(Path(tmp).name))
        swap(tmp, path, found)

    monkeypatch.setattr(bandai, "swap_into_place", other_run_first)
    monkeypatch.setattr(bvh_library, "swap_into_place", other_run_first)
    code = main([*map(str, argv), "--out", str(out)])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(lines) == 1 and "written by another run meanwhile" in lines[0], err
    assert "Traceback" not in err and snapshot(tmp_path) == after and _complete(out)  # the other run's, untouched


def test_data_prepare_refuses_an_out_it_cannot_write(fixtures, tmp_path, capsys, monkeypatch):
    import os

    locked = tmp_path / "locked"
    locked.mkdir()
    access = os.access  # a folder this user may not write in (the tests may run as root, who may write anywhere)
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: Path(p) != locked and access(p, mode, **kw))
    for kind in ("bandai", "bvh"):
        argv = _prepare_argv(kind, fixtures, tmp_path)
        refused([*argv, "--out", locked / "data"], tmp_path, capsys, f"the folder {locked} cannot be written")


def _h3d_folder(root: Path) -> Path:
    (root / "new_joint_vecs").mkdir(parents=True)
    np.save(root / "new_joint_vecs" / "000001.npy", np.zeros((60, 263), np.float32))
    (root / "train.txt").write_text("000001\n")
    (root / "val.txt").write_text("000001\n")
    (root / "texts").mkdir()
    (root / "texts" / "000001.txt").write_text("a person walks forward.#a/DET person/NOUN#0.0#0.0\n")
    np.save(root / "Mean.npy", np.zeros(263, np.float32))
    np.save(root / "Std.npy", np.ones(263, np.float32))
    return root


def test_train_refuses_bad_data_and_settings_and_leaves_no_run_folder(tmp_path, capsys):
    data = _h3d_folder(tmp_path / "data")
    run = tmp_path / "run"
    train = ["train", "vae", "--data", data, "--out", run, "--steps", "1"]
    (tmp_path / "list.json").write_text("[1, 2]")
    (tmp_path / "unknown.json").write_text('{"no_such_setting": 1}')
    refused([*train, "--config", tmp_path / "list.json"], tmp_path, capsys, "JSON object")
    refused([*train, "--config", tmp_path / "unknown.json"], tmp_path, capsys, "unknown setting")
    refused([*train, "--config", '{"bf16": "false"}'], tmp_path, capsys, "bf16 must be true or false, got 'false'")
    refused([*train, "--config", '{"init": "default"}'], tmp_path, capsys, "init is set by --init, not in --config")
    refused(["train", "denoiser", "--data", data, "--vae", "default", "--out", run, "--config",
             '{"seed": 1, "vae": "x"}'], tmp_path, capsys, "seed, vae are set by --seed, --vae")
    refused(["train", "draft", "--data", data, "--out", run, "--config", '{"teacher": "default"}'], tmp_path, capsys,
            "teacher is set by --teacher")
    refused([*train, "--threads", "-1"], tmp_path, capsys, "--threads must be between")
    (tmp_path / "a_file").write_text("x")
    refused(["train", "vae", "--data", data, "--out", tmp_path / "a_file"], tmp_path, capsys, "not a folder")
    (data / "Mean.npy").write_bytes(b"garbage")
    refused(train, tmp_path, capsys, "not a numpy array")
    np.save(data / "Mean.npy", np.zeros(263, np.float32))
    (data / "train.txt").write_text("")
    refused(train, tmp_path, capsys, "names no clip")
    refused(["train", "denoiser", "--data", data, "--vae", tmp_path / "none", "--out", run], tmp_path, capsys,
            "names no clip")
    assert not run.exists()


@pytest.mark.parametrize("argv", [["evaluate", "t2m", "--data", "x", "--threads", "-1"], ["bench", "--threads", "-1"]])
def test_evaluate_and_bench_refuse_negative_threads(tmp_path, capsys, argv):
    refused(argv, tmp_path, capsys, "--threads must be between")


def test_evaluate_refuses_a_bad_side_redraws_count_before_any_work(tmp_path, capsys):
    refused(["evaluate", "t2m", "--data", "x", "--side-redraws", "9"], tmp_path, capsys,
            "--side-redraws must be between 0 and 8")
    refused(["evaluate", "t2m", "--data", "x", "--verb-redraws", "9"], tmp_path, capsys,
            "--verb-redraws must be between 0 and 8")


def test_export_model_never_deletes_what_it_did_not_write(model, tmp_path, capsys):
    import sys

    sys.path.insert(0, str(REPO / "scripts"))
    import export_model

    out = tmp_path / "shipped"
    assert export_model.main([str(model), "--out", str(out)]) == 0
    (out / "my_notes.md").write_text("mine")
    before = snapshot(tmp_path)
    for argv, words in [([str(model), "--out", str(out), "--overwrite"], "my_notes.md"),
                        ([str(model), "--out", str(out)], "pass --overwrite"),
                        ([str(tmp_path / "no_run"), "--out", str(tmp_path / "x")], "model folder not found"),
                        ([str(model), "--out", str(out / "my_notes.md")], "is a file")]:
        capsys.readouterr()
        assert export_model.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err, err
        assert snapshot(tmp_path) == before
    (out / "my_notes.md").unlink()
    assert export_model.main([str(model), "--out", str(out), "--overwrite"]) == 0


# -- the user's JSON files: one reader for --keys, --path, --sequence, --config (and the batch's --jobs) --------------
DEEP = "[" * 100_000 + "]" * 100_000
KEY = '{"keys": [{"frame": %s, "joints": {"pelvis": [%s, 0.9, 0]}}]}'
JSON_CASES = [
    ("--keys", DEEP, "nested more than 32 levels deep"),
    ("--keys", '{"keys": ' + "[" * 40 + "]" * 40 + "}", "nested more than 32 levels deep"),
    ("--keys", KEY % ("1e308", "0"), ".keys[0].frame must be a finite number"),
    ("--keys", KEY % ("9" * 401, "0"), ".keys[0].frame must be a finite number"),
    ("--keys", KEY % ("-" + "9" * 401, "0"), ".keys[0].frame must be a finite number"),
    ("--keys", KEY % ("20", "1e999"), ".keys[0].joints.pelvis[0] must be a finite number"),
    ("--keys", KEY % ("20", "NaN"), "got NaN"),
    ("--keys", '{"fps": 20, "fps": 30, "keys": []}', "gives 'fps' more than once"),
    ("--path", DEEP, "nested more than 32 levels deep"),
    ("--path", '{"points": [[0, 0, 0], [1e308, 1, 1]]}', ".points[1][0] must be a finite number"),
    ("--path", '{"points": [[0, 0, 0], [20, -Infinity, 1]]}', "got -Infinity"),
    ("--sequence", DEEP, "nested more than 32 levels deep"),
    ("--sequence", '[{"prompt": "a person walks", "seconds": 1e999}]', "[0].seconds must be a finite number"),
    ("--config", DEEP, "nested more than 32 levels deep"),
    ("--config", '{"lr": 1e999}', ".lr must be a finite number"),
]


@pytest.mark.parametrize("flag, text, words", JSON_CASES,
                         ids=[f"{c[0]}-{i}" for i, c in enumerate(JSON_CASES)])
def test_every_json_reader_refuses_deep_nesting_and_numbers_out_of_range(model, work, capsys, flag, text, words):
    (work / "in.json").write_text(text)
    if flag == "--config":
        data = _h3d_folder(work / "data")
        argv = ["train", "vae", "--data", data, "--out", work / "run", "--steps", "1", "--config", work / "in.json"]
    elif flag == "--sequence":
        argv = ["generate", "--sequence", work / "in.json", "--model", model, "--out", work / "t.npz"]
    else:
        argv = ["generate", "a person walks", "--model", model, "--out", work / "t.npz", flag, work / "in.json"]
    line = refused(argv, work, capsys, words)
    assert str(work / "in.json") in line  # the file is named


def test_inline_json_and_file_limits(work, capsys, monkeypatch):
    data = _h3d_folder(work / "data")
    train = ["train", "vae", "--data", data, "--out", work / "run", "--steps", "1"]
    refused([*train, "--config", '{"vae": ' + DEEP[:2000] + DEEP[-2000:] + "}"], work, capsys,
            "--config is nested more than 32 levels deep")
    refused([*train, "--config", '{"lr": 1e-4, "lr": 1e-3}'], work, capsys, "gives 'lr' more than once")
    refused(["train", "evaluator", "--data", data, "--out", work / "ev", "--text-encoder", DEEP], work, capsys,
            "--text-encoder is nested more than 32 levels deep")
    monkeypatch.setattr(inputs, "MAX_JSON_BYTES", 64)
    (work / "big.json").write_text('{"keys": [' + ", ".join(["1"] * 40) + "]}")
    refused([*train, "--config", work / "big.json"], work, capsys, "the limit is")
    (work / "latin1.json").write_bytes(b'{"lr": "caf\xe9"}')
    refused([*train, "--config", work / "latin1.json"], work, capsys, "not UTF-8")
    refused([*train, "--config", work / "no_such.json"], work, capsys, "file not found")


def test_the_json_reader_keeps_ordinary_documents_as_they_are():
    text = '{"fps": 30, "keys": [{"frame": 12, "joints": {"pelvis": [0.1, 0.9, -2.5e-3]}}], "on": true, "x": null}'
    assert inputs.parse_json(text, "t") == json.loads(text)
    assert inputs.parse_json("[1e12, -1e12, 999999999999]", "t") == [1e12, -1e12, 999999999999]
    with pytest.raises(inputs.InputError, match=r"\[1\] must be a finite number .*, got 1000000000001$"):
        inputs.parse_json("[0, 1000000000001]", "t")


# -- training, evaluation and benchmark flags --------------------------------------------------------------------
@pytest.mark.parametrize("stage, extra, words", [
    ("vae", ["--steps", "0"], "--steps must be between 1 and"),
    ("vae", ["--steps", "-1"], "--steps must be between 1 and"),
    ("vae", ["--minutes", "-1"], "--minutes must be above 0"),
    ("vae", ["--minutes", "0"], "--minutes must be above 0"),
    ("vae", ["--minutes", "nan"], "--minutes must be a finite number"),
    ("vae", ["--minutes", "inf"], "--minutes must be a finite number"),
    ("vae", ["--lr", "nan"], "--lr must be a finite number"),
    ("vae", ["--layers", "0"], "--layers must be between 1 and 64"),
    ("vae", ["--latent-tokens", "-2"], "--latent-tokens must be between 1 and 64"),
    ("denoiser", ["--steps", "0"], "--steps must be between 1 and"),
    ("denoiser", ["--minutes", "-5"], "--minutes must be above 0"),
    ("draft", ["--minutes", "nan"], "--minutes must be a finite number"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_train_refuses_a_budget_that_would_make_no_step(tmp_path, capsys, stage, extra, words):
    data = _h3d_folder(tmp_path / "data")
    argv = ["train", stage, "--data", data, "--out", tmp_path / "run", *extra]
    if stage == "denoiser":
        argv += ["--vae", tmp_path / "no_vae"]
    refused(argv, tmp_path, capsys, words)
    assert not (tmp_path / "run").exists()


def test_a_time_budget_lets_a_run_make_at_least_one_step():
    from mld_core.training.common import Budget

    budget = Budget(None, 1e-9)  # spent before the first step
    assert not budget.done(0) and budget.done(1)
    resumed = Budget(None, 1e-9)  # a resumed run makes one step of its own too
    assert not resumed.done(500) and resumed.done(501)
    with pytest.raises(ValueError, match="minutes must be above 0"):
        Budget(None, -1)


def test_train_evaluator_refuses_numbers_out_of_range(tmp_path, capsys):
    data = _h3d_folder(tmp_path / "data")
    base = ["train", "evaluator", "--data", data, "--out", tmp_path / "ev"]
    for extra, words in [(["--minutes", "-1"], "--minutes must be 0 (no limit) or more"),
                         (["--minutes", "nan"], "--minutes must be a finite number"),
                         (["--lr", "inf"], "--lr must be a finite number"), (["--epochs", "0"], "--epochs must be"),
                         (["--batch-size", "1"], "--batch-size must be between 2"),
                         (["--hidden", "0"], "--hidden must be between 1")]:
        refused([*base, *extra], tmp_path, capsys, words)


@pytest.fixture
def eval_data(tmp_path) -> Path:
    data = _h3d_folder(tmp_path / "data")
    (data / "test.txt").write_text("000001\n")
    return data


EVALUATE_CASES = [
    (["--batch-size", "0"], "--batch-size must be between 1 and 4096, got 0"),
    (["--mm-texts", "-1"], "--mm-texts must be between 0 and"),
    (["--mm-repeats", "5"], "--mm-repeats must be at least 10"),
    (["--max-pairs", "0"], "--max-pairs must be between 8 and"),
    (["--max-pairs", "7"], "--max-pairs must be between 8 and"),
    (["--replications", "0"], "--replications must be between 1"),
    (["--steps", "0"], "--steps must be between 1 and 500"),
    (["--guidance", "nan"], "--guidance must be a finite number"),
    (["--seed", "5000"], "--seed must be between 0 and"),
]


@pytest.mark.parametrize("extra, words", EVALUATE_CASES, ids=[" ".join(c[0]) for c in EVALUATE_CASES])
def test_evaluate_refuses_numbers_out_of_range_before_any_work(model, eval_data, capsys, extra, words):
    refused(["evaluate", "t2m", "--data", eval_data, "--model", model, *extra], eval_data.parent, capsys, words)


def test_evaluate_max_pairs_minimum_depends_on_the_task(model, eval_data, capsys):
    refused(["evaluate", "vae", "--data", eval_data, "--model", model, "--max-pairs", "1"], eval_data.parent,
            capsys, "--max-pairs must be between 2 and")


BENCH_CASES = [
    (["--prompts", "0"], "--prompts must be between 1"),
    (["--ddpm-prompts", "-1"], "--ddpm-prompts must be between 1"),
    (["--ddpm-timed-steps", "0"], "--ddpm-timed-steps must be between 1"),
    (["--seconds", "nan"], "--seconds (seconds) must be a finite number"),
    (["--seconds", "100"], "--seconds must be between 1 and 9.8 seconds for this model"),
    (["--steps", "0"], "--steps must be between 1 and 500"),
    (["--guidance", "-1"], "--guidance must be between 0"),
]


@pytest.mark.parametrize("extra, words", BENCH_CASES, ids=[" ".join(c[0]) for c in BENCH_CASES])
def test_bench_refuses_numbers_out_of_range_before_any_work(model, work, capsys, extra, words):
    refused(["bench", "--model", model, "--no-progress", *extra], work, capsys, words)


def test_evaluate_and_bench_check_their_json_output_before_the_work(model, eval_data, capsys):
    root = eval_data.parent
    (root / "results").mkdir()
    (root / "a_file").write_text("x")
    for where, words in [(root / "results", "is a folder; name a file"),
                         (root / "a_file" / "r.json", "a_file is a file, not a folder")]:
        refused(["evaluate", "t2m", "--data", eval_data, "--model", model, "--json", where], root, capsys, words)
        refused(["bench", "--model", model, "--json", where], root, capsys, words)


# -- outputs that cannot be written ------------------------------------------------------------------------------
@pytest.fixture
def locked(tmp_path, monkeypatch) -> Path:
    """A folder that reads as not writable. The tests run as root, which may write anywhere, so permissions cannot
    lock it: os.access is made to answer no for it (every writer checks with os.access before any work)."""
    import os

    folder = tmp_path / "locked"
    folder.mkdir()
    real = os.access

    def access(path, mode, *args, **kwargs):
        if Path(path).absolute() == folder and mode & os.W_OK:
            return False
        return real(path, mode, *args, **kwargs)

    monkeypatch.setattr(os, "access", access)
    return folder


def test_an_output_folder_that_cannot_be_written_is_refused_before_any_work(model, fixtures, tmp_path, locked,
                                                                            capsys):
    data = _h3d_folder(tmp_path / "data")
    (data / "test.txt").write_text("000001\n")
    words = "cannot be written"
    refused(["generate", "a person walks", "--model", model, "--out", locked / "t.npz"], tmp_path, capsys, words)
    refused(["generate", "a person walks", "--model", model, "--out", locked / "new" / "t.npz"], tmp_path, capsys,
            words)
    refused(["train", "vae", "--data", data, "--out", locked / "run", "--steps", "1"], tmp_path, capsys, words)
    refused(["data", "prepare", "bandai", fixtures / "bandai", "--out", locked / "data", "--workers", "1"], tmp_path,
            capsys, words)
    refused(["evaluate", "t2m", "--data", data, "--model", model, "--json", locked / "r.json"], tmp_path, capsys,
            words)
    refused(["bench", "--model", model, "--json", locked / "b.json"], tmp_path, capsys, words)
    export = _export_model()
    before = snapshot(tmp_path)
    assert export.main([str(model), "--out", str(locked / "model")]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err and snapshot(tmp_path) == before, err


def _export_model():
    import sys

    sys.path.insert(0, str(REPO / "scripts"))
    import export_model

    return export_model


def test_export_model_checks_its_inputs_and_output_before_writing(model, tmp_path, capsys):
    export = _export_model()
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "latin1.md").write_bytes(b"caf\xe9\n")
    (tmp_path / "empty").mkdir()
    before = snapshot(tmp_path)
    for argv, words in [(["--out", tmp_path / "a_file" / "model"], "a_file is a file, not a folder"),
                        (["--out", tmp_path / "new" / "m", "--notes", tmp_path / "no_notes.md"],
                         "--notes " + str(tmp_path / "no_notes.md") + ": file not found"),
                        (["--out", tmp_path / "new" / "m", "--notes", tmp_path / "latin1.md"], "not UTF-8 text"),
                        (["--out", tmp_path / "new" / "m", "--data", tmp_path / "no_data"], "no such folder"),
                        (["--out", tmp_path / "new" / "m", "--data", tmp_path / "empty"], "--data")]:
        assert export.main([str(model), *map(str, argv)]) == 2, argv
        err = capsys.readouterr().err
        lines = [line for line in err.splitlines() if line.startswith("error:")]
        assert len(lines) == 1 and words in lines[0] and "Traceback" not in err, err
        assert snapshot(tmp_path) == before, argv
    # missing folders above --out are made
    assert export.main([str(model), "--out", str(tmp_path / "new" / "a" / "b" / "model")]) == 0
    assert (tmp_path / "new" / "a" / "b" / "model" / "config.json").is_file()
