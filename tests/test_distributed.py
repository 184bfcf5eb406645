"""Training under torchrun (gloo, 2 processes, tiny models): N processes learn what one process learns on the same
total batch, a run resumes exactly and with another number of processes, rank 0 alone writes, and a bad device or
process environment is one error line with nothing written."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from mld_core.cli import main
from test_reliability import refused
from test_training import TINY_DEN, TINY_VAE, folder  # noqa: F401  (the tiny data folder fixture)

CONSTANT_LR = {"decay_start": 1.0}  # the learning rate does not depend on --steps: a run cut short can be resumed
TOLERANCE = 1e-4  # float32 sums in another order, through a few Adam steps (learning rates <= 3e-4; Adam moves a
#                    weight whose gradient is all but 0 by up to the learning rate, whichever way rounding points)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _torchrun_env(rank: int, world: int, port: int) -> dict:
    return {"RANK": str(rank), "WORLD_SIZE": str(world), "LOCAL_RANK": str(rank), "LOCAL_WORLD_SIZE": str(world),
            "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "OMP_NUM_THREADS": "1"}


def _rank(rank: int, world: int, port: int, call: str, argument) -> None:
    """One of the processes (what torchrun starts): its environment, then the CLI (or a function of this module)."""
    os.environ.update(_torchrun_env(rank, world, port))
    if call == "cli":
        code = main(argument)
        if code:
            raise SystemExit(code)
    else:
        globals()[call](**argument)


def _spawn(call: str, argument, world: int = 2, timeout: float = 240) -> None:
    """Run ``world`` processes of _rank and wait for them (failing the test if one fails or they hang)."""
    context = torch.multiprocessing.start_processes(_rank, args=(world, _free_port(), call, argument), nprocs=world,
                                                    join=False, start_method="spawn")
    deadline = time.monotonic() + timeout
    while not context.join(timeout=5):
        if time.monotonic() > deadline:
            for process in context.processes:
                process.kill()
            pytest.fail(f"{world} processes of {call} did not finish in {timeout} s")


def _weights(run: Path) -> dict:
    return torch.load(run / "train_state.pt", map_location="cpu", weights_only=True)["model"]


def _largest_difference(a: dict, b: dict) -> float:
    assert a.keys() == b.keys()
    return max(float((a[k].float() - b[k].float()).abs().max()) for k in a)


def _configs(tmp_path: Path) -> tuple[Path, Path]:
    vae, den = tmp_path / "vae.json", tmp_path / "den.json"
    vae.write_text(json.dumps({**TINY_VAE, **CONSTANT_LR}))
    den.write_text(json.dumps({**TINY_DEN, **CONSTANT_LR, "batch_size": 15}))  # 15 rows: the processes take 8 and 7
    return vae, den


def test_vae_two_processes_under_torchrun_equal_one(folder, tmp_path):
    """The real command line: torchrun --nproc_per_node 2 -m mld_core train vae; rank 0 alone logs."""
    vae_cfg, _ = _configs(tmp_path)
    args = ["train", "vae", "--data", str(folder), "--steps", "4", "--threads", "1", "--config", str(vae_cfg)]
    assert main(args + ["--out", str(tmp_path / "one")]) == 0
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                           "-m", "mld_core", *args, "--out", str(tmp_path / "two")], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("wrote ") == 1  # rank 0 alone reports
    assert _largest_difference(_weights(tmp_path / "one"), _weights(tmp_path / "two")) < TOLERANCE
    log = (tmp_path / "two" / "log.jsonl").read_text().splitlines()
    assert [json.loads(line)["step"] for line in log] == [4]  # one line: rank 0's
    run = json.loads((tmp_path / "two" / "train_config.json").read_text())["run"]
    assert (run["world_size"], run["batch_total"], run["batch_per_process"], run["device"]) == (2, 160, 80, "cpu")


def test_denoiser_two_processes_equal_one_and_resume_with_another_number(folder, tmp_path):
    vae_cfg, den_cfg = _configs(tmp_path)
    assert main(["train", "vae", "--data", str(folder), "--out", str(tmp_path / "vae"), "--steps", "2",
                 "--threads", "1", "--config", str(vae_cfg)]) == 0
    args = ["train", "denoiser", "--data", str(folder), "--vae", str(tmp_path / "vae"), "--threads", "1",
            "--config", str(den_cfg)]
    assert main(args + ["--out", str(tmp_path / "one"), "--steps", "4"]) == 0
    _spawn("cli", args + ["--out", str(tmp_path / "two"), "--steps", "4"])
    assert _largest_difference(_weights(tmp_path / "one"), _weights(tmp_path / "two")) < TOLERANCE
    # 2 steps in two processes, resumed in one to step 4: the run one process makes without a break
    _spawn("cli", args + ["--out", str(tmp_path / "resumed"), "--steps", "2"])
    assert main(args + ["--out", str(tmp_path / "resumed"), "--steps", "4", "--resume"]) == 0
    assert _largest_difference(_weights(tmp_path / "one"), _weights(tmp_path / "resumed")) < TOLERANCE
    run = json.loads((tmp_path / "two" / "train_config.json").read_text())["run"]
    assert (run["world_size"], run["batch_total"], run["batch_per_process"]) == (2, 15, 8)


def test_a_resumed_run_equals_an_uninterrupted_one_exactly(folder, tmp_path):
    """One process, CPU to CPU: every step's batch is keyed by (seed, step), so a break changes nothing at all."""
    vae_cfg, _ = _configs(tmp_path)
    args = ["train", "vae", "--data", str(folder), "--threads", "1", "--config", str(vae_cfg), "--lr", "3e-3"]
    assert main(args + ["--out", str(tmp_path / "whole"), "--steps", "4"]) == 0
    assert main(args + ["--out", str(tmp_path / "cut"), "--steps", "2"]) == 0
    assert main(args + ["--out", str(tmp_path / "cut"), "--steps", "4", "--resume"]) == 0
    whole, cut = _weights(tmp_path / "whole"), _weights(tmp_path / "cut")
    assert all(torch.equal(whole[k], cut[k]) for k in whole)
    assert _largest_difference(whole, _weights_after(tmp_path, args, 3)) > 1e-4  # a step more or less shows


def _weights_after(tmp_path: Path, args: list, steps: int) -> dict:
    run = tmp_path / f"steps{steps}"
    assert main(args + ["--out", str(run), "--steps", str(steps)]) == 0
    return _weights(run)


def test_draft_and_draft_text_two_processes_equal_one(folder, tmp_path):
    from mld_core.testing import tiny_model

    teacher = tiny_model(tmp_path / "teacher")  # a 2-layer text encoder: the 1-layer student differs from it
    draft_cfg = json.dumps({"batch_size": 9, "save_every": 10, "crops_per_clip": 2, **CONSTANT_LR})
    text_cfg = json.dumps({"batch_size": 8, "save_every": 10, "init_layers": [1], "val_texts": 4, **CONSTANT_LR})
    for stage, config in (("draft", draft_cfg), ("draft-text", text_cfg)):
        args = ["train", stage, "--data", str(folder), "--teacher", str(teacher), "--steps", "3", "--threads", "1",
                "--config", config]
        assert main(args + ["--out", str(tmp_path / f"{stage}1")]) == 0
        _spawn("cli", args + ["--out", str(tmp_path / f"{stage}2")])
        one, two = _weights(tmp_path / f"{stage}1"), _weights(tmp_path / f"{stage}2")
        assert _largest_difference(one, two) < TOLERANCE, stage


def _train_evaluator(data: str, out: str) -> None:
    from mld_core.eval.evaluator import EvaluatorConfig
    from mld_core.eval.train import EvaluatorTrainConfig, train_evaluator
    from mld_core.models.text_encoder import load_text_encoder

    encoder = load_text_encoder({"kind": "minilm-random", "hidden": 32, "layers": 1, "heads": 2,
                                 "vocab_path": "builtin"})
    model = EvaluatorConfig(hidden=32, ff_dim=64, layers=1, dropout=0.0, text_encoder={"kind": "minilm-random"})
    train_evaluator(EvaluatorTrainConfig(data=data, out=out, epochs=2, batch_size=5, minutes=None), model,
                    text_encoder=encoder, progress=False, log=lambda *_: None)


def test_evaluator_two_processes_equal_one(folder, tmp_path):
    """The contrastive loss sees the whole batch in every process (embeddings gathered with their gradients)."""
    _train_evaluator(str(folder), str(tmp_path / "one"))
    _spawn("_train_evaluator", {"data": str(folder), "out": str(tmp_path / "two")})
    one = torch.load(tmp_path / "one" / "train_state.pt", weights_only=True)
    two = torch.load(tmp_path / "two" / "train_state.pt", weights_only=True)
    assert one["step"] == two["step"] > 0
    assert _largest_difference(one["model"], two["model"]) < TOLERANCE


# -- bad input: one error line, nothing written --------------------------------------------------------------------
@pytest.mark.parametrize("env, words", [
    ({"WORLD_SIZE": "x", "RANK": "0", "LOCAL_RANK": "0"}, "WORLD_SIZE='x' is not a whole number"),
    ({"WORLD_SIZE": "0", "RANK": "0", "LOCAL_RANK": "0"}, "WORLD_SIZE=0 is not a number of processes"),
    ({"WORLD_SIZE": "2", "RANK": "2", "LOCAL_RANK": "0"}, "do not fit WORLD_SIZE=2"),
    ({"WORLD_SIZE": "2", "RANK": "1"}, "LOCAL_RANK=''"),
    ({"WORLD_SIZE": "2", "RANK": "1", "LOCAL_RANK": "1"}, "MASTER_ADDR and MASTER_PORT not set"),
])
def test_a_process_environment_that_is_not_torchrun_s_is_refused(folder, tmp_path, capsys, monkeypatch, env, words):
    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(name, raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    refused(["train", "vae", "--data", folder, "--out", tmp_path / "run", "--steps", "1"], tmp_path, capsys, words)
    refused(["train", "evaluator", "--data", folder, "--out", tmp_path / "ev"], tmp_path, capsys, words)


def test_a_batch_too_small_for_the_processes_is_refused(folder, tmp_path, capsys, monkeypatch):
    """Every process needs rows of each batch: checked before the process group starts or anything is written, so
    a run cannot be resumed with more processes than its batch has rows either."""
    vae_cfg, _ = _configs(tmp_path)
    assert main(["train", "vae", "--data", str(folder), "--out", str(tmp_path / "run"), "--steps", "1",
                 "--threads", "1", "--config", str(vae_cfg)]) == 0  # a run of one process ...
    capsys.readouterr()
    for name, value in _torchrun_env(0, 8, _free_port()).items():
        monkeypatch.setenv(name, value)
    for args in (["--out", tmp_path / "new"], ["--out", tmp_path / "run", "--resume"]):  # ... resumed by 8
        refused(["train", "vae", "--data", folder, "--steps", "2", "--config", vae_cfg, *args], tmp_path, capsys,
                "fewer than the 8 processes")
    refused(["train", "evaluator", "--data", folder, "--out", tmp_path / "ev", "--batch-size", "4"], tmp_path, capsys,
            "at least the 8 processes")


@pytest.mark.parametrize("device, words", [
    ("gpu", "--device 'gpu' is not a device: use cpu, cuda, mps or auto"),
    ("cuda", "--device cuda:"),
    ("mps", "--device mps: Metal (MPS) is not available on this machine"),
])
def test_a_device_this_machine_lacks_is_refused(folder, tmp_path, capsys, device, words):
    if device == "cuda" and torch.cuda.is_available() or device == "mps" and torch.backends.mps.is_available():
        pytest.skip(f"this machine has {device}")
    data = ["--data", folder]
    for argv in (["train", "vae", *data, "--out", tmp_path / "run"], ["train", "denoiser", *data, "--vae", folder,
                                                                         "--out", tmp_path / "run"],
                 ["train", "draft", *data, "--out", tmp_path / "run"],
                 ["train", "draft-text", *data, "--out", tmp_path / "run"],
                 ["train", "evaluator", *data, "--out", tmp_path / "run"],
                 ["generate", "a person walks", "--out", tmp_path / "a.npz"],
                 ["evaluate", "t2m", *data], ["bench"]):
        refused([*argv, "--device", device], tmp_path, capsys, words)


def test_the_help_says_batches_are_totals(capsys):
    with pytest.raises(SystemExit):
        main(["train", "denoiser", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "totals over all processes" in help_text and "--device" in help_text


def test_runtime_rows_and_shares_make_one_batch():
    """Process r takes rows r, r + N, ...; the rows' shares weight each process's mean loss."""
    from mld_core.inputs import World
    from mld_core.training.distributed import Runtime

    runtimes = [Runtime(torch.device("cpu"), World(r, 3, r)) for r in range(3)]
    rows = [rt.rows(10).tolist() for rt in runtimes]
    assert rows == [[0, 3, 6, 9], [1, 4, 7], [2, 5, 8]]
    assert sum(rt.share(10) for rt in runtimes) == pytest.approx(3.0)  # DDP averages: the mean of the whole batch
    losses = torch.arange(10.0)
    assert sum(rt.share(10) * losses[rt.rows(10)].mean() for rt in runtimes) / 3 == pytest.approx(losses.mean())
