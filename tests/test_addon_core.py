"""The add-on's bpy-free parts: request validation, naming, prompt files, the job runner, the model cache,
the pose math of the canonical rig, and importing all of that without bpy."""

from __future__ import annotations

import ast
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from blender_addon.worker import batchfile
from blender_addon import env
from blender_addon.worker import jobs
from blender_addon.worker import model_cache
from blender_addon.worker import naming
from mld_core.rig import canonical_pose as posing
from blender_addon.worker.validation import RequestError, validate_request

REPO = Path(__file__).resolve().parents[1]


# -- request validation -----------------------------------------------------------------------------------------
def test_validate_request_normalises():
    req = validate_request("  a person   walks\tforward ", "4", 7, 50.0, 0, 2, model_dir=" ", device="CPU")
    assert req.prompt == "a person walks forward"
    assert req.seconds == 4.0 and req.frames == 80
    assert (req.seed, req.steps, req.variants) == (7, 50, 2)
    assert req.guidance is None  # 0 means the model's default
    assert req.model_dir is None and req.device == "cpu"
    # seconds are rounded to whole 20 fps frames
    assert validate_request("walk", 3.333).seconds == pytest.approx(3.35)
    assert validate_request("walk", guidance=5).guidance == 5.0


@pytest.mark.parametrize(
    "kwargs, words",
    [
        (dict(prompt=""), "Type a prompt"),
        (dict(prompt="   "), "Type a prompt"),
        (dict(prompt="1234 !!"), "no words"),
        (dict(prompt="x" * 301), "characters"),
        (dict(prompt=None), "must be text"),
        (dict(prompt="walk", seconds=0.2), "between 2 and 9.8 seconds"),
        (dict(prompt="walk", seconds=60), "between 2 and 9.8 seconds"),
        (dict(prompt="walk", seconds=float("nan")), "finite"),
        (dict(prompt="walk", seconds="long"), "must be a number"),
        (dict(prompt="walk", seed=-1), "Seed must be"),
        (dict(prompt="walk", seed=1.5), "whole number"),
        (dict(prompt="walk", steps=0), "Steps must be"),
        (dict(prompt="walk", variants=17), "Variants must be"),
        (dict(prompt="walk", guidance=100), "Guidance must be"),
        (dict(prompt="walk", device="tpu"), "Unknown device"),
        (dict(prompt="walk", threads=-2), "Threads"),
        (dict(prompt="walk", seconds=True), "must be a number"),
    ],
)
def test_validate_request_rejects(kwargs, words):
    with pytest.raises(RequestError, match=words):
        validate_request(**kwargs)


def test_validate_request_uses_model_limits():
    with pytest.raises(RequestError, match="between 2 and 5 seconds"):
        validate_request("walk", 6.0, min_seconds=2, max_seconds=5)
    assert validate_request("walk", 5.0, min_seconds=2, max_seconds=5).seconds == 5.0


# -- naming -------------------------------------------------------------------------------------------------------
def test_action_names():
    assert naming.action_name("A person walks forward, then waves!", 7) == "walks_forward_then_waves_s7"
    assert naming.action_name("someone jumps", 3, variant=1, variants=3) == "jumps_s3_v2"
    assert naming.action_name("!!!", 0) == "motion_s0"
    long = naming.action_name("a person " + "very " * 40 + "slowly walks", 123456)
    assert len(long.encode()) <= naming.MAX_NAME_BYTES - 4 and long.endswith("_s123456")
    assert naming.unique_name("walk_s0", {"walk_s0", "walk_s0.001"}) == "walk_s0.002"
    assert naming.unique_name("walk_s0", set()) == "walk_s0"
    assert len(naming.unique_name("é" * 40, {"é" * 31}).encode()) <= naming.MAX_NAME_BYTES


# -- prompt files ---------------------------------------------------------------------------------------------------
def test_prompt_file_lines(tmp_path):
    path = tmp_path / "prompts.txt"
    path.write_text("# takes\n50 a man kicks with his left leg.\n\n  a person walks backward slowly  \n100 A person is skipping rope.\n")
    lines = batchfile.read_prompt_file(path)
    assert [(l.line, l.text, l.frames) for l in lines] == [
        (2, "a man kicks with his left leg.", 50),
        (4, "a person walks backward slowly", None),
        (5, "A person is skipping rope.", 100),
    ]
    reqs = batchfile.requests_from_lines(lines, default_seconds=3.0, seed=10, steps=5)
    assert [r.seconds for r in reqs] == [2.5, 3.0, 5.0]
    assert [r.seed for r in reqs] == [10, 11, 12]
    assert all(r.steps == 5 for r in reqs)


@pytest.mark.parametrize(
    "text, words",
    [
        ("", "no prompts"),
        ("# only a comment\n\n", "no prompts"),
        ("walk\n40\n", "line 2: a length"),
        ("2.5 a person walks\n", "whole number of frames"),
        ("0 a person walks\n", "positive"),
    ],
)
def test_prompt_file_errors(text, words):
    with pytest.raises(batchfile.BatchFileError, match=words):
        batchfile.parse_prompt_lines(text, source="p.txt")


def test_prompt_file_bad_length_names_the_line(tmp_path):
    lines = batchfile.parse_prompt_lines("a person walks\n500 a person runs\n")
    with pytest.raises(batchfile.BatchFileError, match=r"line 2: Length must be between"):
        batchfile.requests_from_lines(lines, default_seconds=4, seed=0)
    with pytest.raises(batchfile.BatchFileError, match="not found"):
        batchfile.read_prompt_file(tmp_path / "missing.txt")
    bad = tmp_path / "latin1.txt"
    bad.write_bytes("caf\xe9 walk".encode("latin-1"))
    with pytest.raises(batchfile.BatchFileError, match="not UTF-8"):
        batchfile.read_prompt_file(bad)


# -- job runner -----------------------------------------------------------------------------------------------------
class FakePipeline:
    """Steps through ``total`` steps, calling the callback like MLDPipeline; can block on an event."""

    def __init__(self, total=20, step_seconds=0.0, gate: threading.Event | None = None, fail_at=None):
        self.total, self.step_seconds, self.gate, self.fail_at = total, step_seconds, gate, fail_at
        self.steps_run = 0

    def __call__(self, callback):
        for k in range(self.total):
            if self.gate is not None:
                self.gate.wait(5)
            time.sleep(self.step_seconds)
            self.steps_run += 1
            if self.fail_at is not None and k + 1 == self.fail_at:
                raise RuntimeError("the denoiser produced NaN at step 3")
            if callback(k + 1, self.total) is False:
                # named like mld_core.pipeline.Cancelled: the runner recognises it by name
                raise Cancelled(f"cancelled at step {k + 1}")
        return f"motion after {self.total} steps"


class Cancelled(Exception):
    pass


def _drain(runner, timeout=5.0):
    deadline = time.monotonic() + timeout
    ended = []
    while time.monotonic() < deadline:
        ended += runner.finished()
        if not runner.busy:
            return ended + runner.finished()
        time.sleep(0.005)
    raise AssertionError("the runner did not finish")


def test_runner_runs_jobs_in_order_off_the_main_thread():
    threads = []

    def work(job):
        threads.append(threading.current_thread().name)
        return FakePipeline(total=5)(job.step)

    runner = jobs.JobRunner(work)
    a, b = runner.submit("first"), runner.submit("second")
    ended = _drain(runner)
    assert ended == [a, b]
    assert a.state == b.state == jobs.DONE and a.result == "motion after 5 steps"
    assert a.progress == 1.0 and (a.step_done, a.step_total) == (5, 5)
    assert set(threads) == {"mld-generate"} and threading.current_thread().name not in threads
    assert runner.finished() == []  # handed back once
    runner.shutdown()


def test_runner_cancel_stops_within_one_step():
    gate = threading.Event()
    pipe = FakePipeline(total=1000, gate=gate)
    runner = jobs.JobRunner(lambda job: pipe(job.step))
    job = runner.submit("long")
    gate.set()
    while job.step_done < 3:
        time.sleep(0.001)
    gate.clear()  # hold the pipeline inside a step while we cancel
    done_when_cancelled = job.step_done
    job.cancel()
    gate.set()
    _drain(runner)
    assert job.state == jobs.CANCELLED and job.result is None and job.error == ""
    # the step in flight finishes, its callback answers False, nothing more runs
    assert pipe.steps_run <= done_when_cancelled + 2
    runner.shutdown()


def test_runner_cancel_before_start_and_after_last_step():
    gate = threading.Event()
    runner = jobs.JobRunner(lambda job: FakePipeline(total=3, gate=gate)(job.step))
    first, queued = runner.submit("a"), runner.submit("b")
    queued.cancel()
    gate.set()
    _drain(runner)
    assert first.state == jobs.DONE and queued.state == jobs.CANCELLED and queued.started_at is not None

    def work(job):
        job.cancel()  # cancel arriving after the pipeline returned: the result is dropped
        return "late"

    late = jobs.JobRunner(work).run_now("x")
    assert late.state == jobs.CANCELLED and late.result is None
    runner.shutdown()


def test_runner_errors_become_messages():
    runner = jobs.JobRunner(lambda job: FakePipeline(total=10, fail_at=3)(job.step))
    job = runner.submit("bad")
    _drain(runner)
    assert job.state == jobs.FAILED
    assert job.error == "the denoiser produced NaN at step 3"
    assert "Traceback" in job.details and "Traceback" not in job.error
    # the worker survives and runs the next job
    runner._work = lambda job: "ok"
    nxt = runner.submit("next")
    _drain(runner)
    assert nxt.state == jobs.DONE and nxt.result == "ok"
    runner.shutdown()


def test_a_job_shows_as_ended_only_once_its_error_is_written(monkeypatch):
    """The main thread's timer polls job.ended: a failed job must never read as ended with an empty message."""
    jobs_seen = []

    def message(exc):
        jobs_seen.append(jobs_seen[0].ended)  # what the main thread would see while the message is being made
        return "boom"

    def fail(job):
        raise ValueError("boom")

    monkeypatch.setattr(jobs, "user_message", message)
    runner = jobs.JobRunner(fail)
    jobs_seen.append(runner.submit("bad"))
    _drain(runner)
    job = jobs_seen[0]
    assert jobs_seen[1:] == [False]
    assert job.state == jobs.FAILED and job.error == "boom" and "ValueError" in job.details
    assert job.ended_at is not None
    runner.shutdown()


def test_user_messages():
    err = ModuleNotFoundError("No module named 'torch'", name="torch")
    assert "Install dependencies" in jobs.user_message(err) and "torch" in jobs.user_message(err)
    assert jobs.user_message(KeyError("x")) == "KeyError: 'x'"
    assert jobs.user_message(ValueError("Length must be 1 to 9.8 s")) == "Length must be 1 to 9.8 s"
    assert "/m/x" in jobs.user_message(FileNotFoundError(2, "No such file", "/m/x"))


def test_run_now_runs_on_the_calling_thread():
    runner = jobs.JobRunner(lambda job: threading.current_thread())
    job = runner.run_now("x")
    assert job.state == jobs.DONE and job.result is threading.current_thread()
    assert runner.finished() == [] and not runner.busy


# -- model cache ----------------------------------------------------------------------------------------------------
def test_pipeline_cache_loads_once_per_folder(tmp_path):
    calls = []

    def loader(model_dir, device):
        calls.append((model_dir, device))
        return object()

    cache = model_cache.PipelineCache(loader)
    a = cache.get(str(tmp_path), "cpu")
    assert cache.get(str(tmp_path / "." ), "cpu") is a  # same folder, spelled differently
    b = cache.get(None, "cpu")
    assert b is not a and cache.get(None, "cpu") is b
    assert len(calls) == 2 and cache.loads == 2
    cache.clear()
    assert not cache.loaded and cache.get(None, "cpu") is not b


def test_default_loader_reports_missing_folder(tmp_path):
    with pytest.raises(model_cache.ModelLoadError, match="Model folder not found"):
        model_cache.default_loader(str(tmp_path / "nope"), "cpu")
    (tmp_path / "file").write_text("x")
    with pytest.raises(model_cache.ModelLoadError, match="not a folder"):
        model_cache.default_loader(str(tmp_path / "file"), "cpu")


# -- pose math --------------------------------------------------------------------------------------------------------
def _random_motion(T=25, seed=0):
    from mld_core.motion import skeleton as sk

    rng = np.random.default_rng(seed)
    q = rng.normal(size=(T, 22, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    root = rng.normal(size=(T, 3)) * 0.3 + [0, 0.9, 0]
    offsets = getattr(sk, "REST_OFFSETS", sk.REFERENCE_OFFSETS)
    return q, posing.forward_kinematics(q, root, offsets, sk.PARENTS)


def _rest(seed=1):
    names, parents, heads, _ = posing.canonical_rig()
    mats = posing.quat_to_matrix(np.random.default_rng(seed).normal(size=(22, 4)))  # any bone orientations
    return posing.RigRest(names, parents, heads, mats)


def test_pose_channels_put_joints_exactly_on_target():
    q, joints = _random_motion()
    rest = _rest()
    for exact in (True, False):
        ch = posing.pose_channels(q, joints, rest, exact=exact)
        assert ch.quaternions.shape == (25, 22, 4) and ch.locations.shape == (25, 22, 3)
        err = np.abs(posing.evaluate_pose(ch, rest) - posing.to_blender(joints)).max()
        assert err < 1e-5, (exact, err)
    assert posing.pose_channels(q, joints, rest, exact=False).keyed_locations == (0,)
    # joints off the rigid skeleton (bone-length jitter): only exact mode follows them
    jitter = joints + np.random.default_rng(5).normal(scale=0.02, size=joints.shape)
    exact = posing.pose_channels(q, jitter, rest, exact=True)
    loose = posing.pose_channels(q, jitter, rest, exact=False)
    assert np.abs(posing.evaluate_pose(exact, rest) - posing.to_blender(jitter)).max() < 1e-5
    assert np.abs(posing.evaluate_pose(loose, rest) - posing.to_blender(jitter)).max() > 0.01


def test_pose_channels_match_mld_core_fk():
    from mld_core.motion.rotations import fk

    q, joints = _random_motion(T=6, seed=3)
    np.testing.assert_allclose(fk(q, joints[:, 0]), joints, atol=1e-9)


def test_pose_channels_resample_to_scene_fps():
    q, joints = _random_motion(T=21)  # 1 s at 20 fps
    rest = _rest()
    ch = posing.pose_channels(q, joints, rest, src_fps=20, dst_fps=30)
    assert ch.frames == 31 and ch.fps == 30
    # frame k at 30 fps is source position k * 2/3: even frames land on source frames exactly
    heads = posing.evaluate_pose(ch, rest)
    np.testing.assert_allclose(heads[3], posing.to_blender(joints[2]), atol=1e-5)
    np.testing.assert_allclose(heads[30], posing.to_blender(joints[20]), atol=1e-5)
    mid = posing.to_blender((joints[0] + joints[1]) / 2)  # linear joints in between (1.5 frames at 30 fps)
    assert np.abs(posing.resample_positions(posing.to_blender(joints), np.array([0.5]))[0] - mid).max() < 1e-9
    # consecutive quaternions never flip hemisphere (clean F-curve interpolation)
    dots = np.sum(ch.quaternions[1:] * ch.quaternions[:-1], axis=-1)
    assert (dots > 0).all()


def test_quaternion_helpers():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    m = posing.quat_to_matrix(q)
    back = posing.matrix_to_quat(m)
    np.testing.assert_allclose(np.abs(np.sum(back * q, -1)), 1.0, atol=1e-9)
    np.testing.assert_allclose(posing.quat_to_matrix(posing.quat_mul(q[:-1], q[1:])), m[:-1] @ m[1:], atol=1e-9)
    half = posing.slerp(q[:-1], q[1:], np.full(49, 0.5))
    np.testing.assert_allclose(posing.quat_to_matrix(posing.slerp(q[:-1], q[1:], np.zeros(49))), m[:-1], atol=1e-9)
    # the halfway rotation is equally far from both ends
    d0 = np.abs(np.sum(half * q[:-1], -1))
    d1 = np.abs(np.sum(half * q[1:], -1))
    np.testing.assert_allclose(d0, d1, atol=1e-9)


def test_canonical_rig_stands_on_the_floor():
    names, parents, heads, tails = posing.canonical_rig()
    assert len(names) == 22 and names[0] == "pelvis" and parents[0] == -1
    assert heads[:, 2].min() == pytest.approx(0.0)
    assert 0.8 < heads[0, 2] < 1.1  # pelvis height of a ~1.7 m body, Z up
    assert heads[names.index("left_hip"), 0] > 0  # left is +X
    assert heads[names.index("left_foot"), 1] < heads[names.index("left_ankle"), 1]  # feet point to -Y (front)
    assert (np.linalg.norm(tails - heads, axis=1) >= posing.MIN_BONE_LENGTH - 1e-9).all()


# -- generation with the real tiny pipeline ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    from mld_core.testing import tiny_model

    return tiny_model(tmp_path_factory.mktemp("tiny") / "model")


def test_generation_work_with_tiny_pipeline(tiny_dir):
    from blender_addon.worker.generation import make_work

    cache = model_cache.PipelineCache()
    runner = jobs.JobRunner(make_work(cache))
    request = validate_request("a person walks forward", 2.0, 5, 3, 0, 2, model_dir=str(tiny_dir))
    job = runner.submit(request)
    assert job.wait(60)
    _drain(runner)
    assert job.state == jobs.DONE, job.error
    takes = job.result.takes
    assert sorted(t.seed for t in takes) == [5, 6]  # best first (ranked): either order
    assert sorted((t.seed, t.variant) for t in takes) == [(5, 0), (6, 1)]
    assert sorted(t.name for t in takes) == ["walks_forward_s5_v1", "walks_forward_s5_v2"]
    by_seed = {t.seed: t for t in takes}
    assert takes[0].joints.shape == (40, 22, 3) and takes[0].local_quats.shape == (40, 22, 4)
    prov = by_seed[6].provenance()
    assert prov["mld_prompt"] == "a person walks forward" and prov["mld_seed"] == 6 and prov["mld_steps"] == 3
    assert prov["mld_model_id"] == "tiny-text" and prov["mld_addon_version"] == env.ADDON_VERSION_STRING
    assert prov["mld_guidance"] > 0  # the model's default, recorded
    # what the weights that made it may be used for: the tiny model records no training data, so unknown terms
    assert prov["mld_weights_use"] == "use as its training data's terms allow"
    # the model is cached: a second job does not load again; same seed = same motion
    job2 = runner.submit(request.with_(variants=1))
    assert job2.wait(60)
    _drain(runner)
    assert cache.loads == 1 and job2.result.load_s == 0.0
    np.testing.assert_allclose(job2.result.takes[0].joints, by_seed[5].joints, atol=1e-4)  # batch of 2 vs 1
    # cancel with the real pipeline: stops at the next step callback
    job3 = runner.submit(request.with_(steps=500, variants=1))
    while job3.step_done < 2 and not job3.ended:
        time.sleep(0.001)
    job3.cancel()
    assert job3.wait(30)
    _drain(runner)
    assert job3.state == jobs.CANCELLED and job3.step_done < 500
    # a missing model folder is a message, not a traceback
    job4 = runner.submit(request.with_(model_dir=str(tiny_dir) + "_missing"))
    assert job4.wait(30)
    _drain(runner)
    assert job4.state == jobs.FAILED and "Model folder not found" in job4.error
    runner.shutdown()


# -- packaging facts --------------------------------------------------------------------------------------------------
def test_versions_agree():
    manifest = tomllib.loads((REPO / "blender_addon" / "blender_manifest.toml").read_text())
    tree = ast.parse((REPO / "blender_addon" / "__init__.py").read_text())
    bl_info = next(
        ast.literal_eval(node.value)
        for node in tree.body
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "bl_info"
    )
    assert manifest["version"] == env.ADDON_VERSION_STRING == ".".join(map(str, bl_info["version"]))
    assert manifest["id"] == env.ADDON_ID
    assert tuple(bl_info["blender"]) == (4, 2, 0) and manifest["blender_version_min"] == "4.2.0"


def test_pip_command_and_missing_modules(tmp_path):
    cmd = env.pip_install_command(tmp_path, python="/blender/python", cpu_only=True)
    assert cmd[:4] == ["/blender/python", "-m", "pip", "install"]
    assert "--target" in cmd and cmd[cmd.index("--target") + 1] == str(tmp_path)
    assert any(p.startswith("torch") for p in cmd)
    assert env.missing_modules(("numpy", "surely_not_a_module_xyz")) == ["surely_not_a_module_xyz"]
    assert "Install dependencies" in env.dependency_message(["torch"])
    assert env.dependency_message([]) == ""


def test_installer_runs_commands_and_reports_failure():
    from blender_addon.installer import DependencyInstaller

    inst = DependencyInstaller()
    done = []
    assert inst.start([[sys.executable, "-c", "print('step one')"], [sys.executable, "-c", "print('step two')"]], done.append)
    assert inst.wait(30) and not inst.failed and inst.last_line == "step two" and done == [inst]
    assert inst.start([[sys.executable, "-c", "import sys; print('boom'); sys.exit(3)"]])
    assert inst.wait(30) and inst.failed and "exit 3" in inst.message and "boom" in inst.message


BPY_FREE = (  # the add-on's worker and mld_core.rig: plain Python that never reaches into the Blender layer
    *(f"blender_addon.worker.{m}" for m in ("validation", "jobs", "model_cache", "naming", "batchfile", "generation",
                                             "coverage_watch", "dependencies", "export_plan")),
    *(f"mld_core.rig.{m}" for m in ("bone_maps", "retarget", "keyframes", "canonical_pose", "keying", "root_motion",
                                    "engine_export")),
)


def test_bpy_free_modules_import_without_bpy_or_the_blender_layer():
    code = (
        "import sys; sys.modules['bpy'] = None; sys.modules['mathutils'] = None\n"
        "import importlib\n"
        f"for name in {BPY_FREE!r}:\n"
        "    importlib.import_module(name)\n"
        "layer = sorted(m for m in sys.modules  # (the package's __init__ sets import paths with env: allowed)\n"
        "               if m.startswith(('blender_addon.ui', 'blender_addon.scene', 'blender_addon.installer')))\n"
        "import blender_addon.env, blender_addon.installer  # paths and pip: bpy-free too\n"
        "try:\n"
        "    import blender_addon.scene.write_action\n"
        "except ImportError:\n"
        "    print('keys needs bpy')\n"
        "print('ok', 'torch' in sys.modules, layer)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["keys", "needs", "bpy", "ok", "False", "[]"]  # no torch, no Blender layer


# -- Live Preview's scheduling --------------------------------------------------------------------------------------
class _Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_live_preview_waits_for_the_edits_to_pause_and_runs_only_the_newest():
    from blender_addon.worker.live import LivePreview

    runner = jobs.JobRunner(lambda job: time.sleep(0.2) or job.request)
    clock = _Clock()
    live = LivePreview(runner.submit, debounce_s=0.3, clock=clock)
    assert not live.waiting and live.seconds_to_wait() == 0.0
    for k in range(20):  # typing: an edit every 50 ms
        live.edited()
        clock.now += 0.05
        assert live.seconds_to_wait() == pytest.approx(0.25)
    clock.now += 0.25
    assert live.seconds_to_wait() == 0.0
    first = live.fire("prompt 1")
    live.edited()
    clock.now += 0.3
    second = live.fire("prompt 2")  # the first is cancelled: at most one runs and one waits
    assert first.cancel_requested and not second.cancel_requested and live.cancelled == 1
    assert second.wait(5) and second.state == jobs.DONE and second.result == "prompt 2"
    assert first.wait(5) and first.state == jobs.CANCELLED
    assert live.submitted == 2
    live.stop()
    assert live.job is None and not live.waiting
    runner.shutdown()


def test_a_draft_request_reaches_the_pipeline_with_its_own_steps(tmp_path):
    from blender_addon.worker.generation import generate
    from mld_core.testing import tiny_pipeline

    pipe = tiny_pipeline(tmp_path / "m", draft=True)
    request = validate_request("a person walks", 2.0, 3, 50, None, 1, draft=True,
                               model_dir=tmp_path / "m").with_(extra={"rank": False})
    result = generate(pipe, request)
    take = result.takes[0]
    assert take.steps == 2 and take.provenance()["mld_draft"] is True and take.badges is None
    same = pipe("a person walks", 2.0, seed=3, draft=True)
    assert np.allclose(take.joints, same.joints[0], atol=1e-6)
