"""Training speed with 1 and N processes (torchrun, gloo on the CPU; NCCL with --device cuda): steps per second of
`train vae` and `train denoiser` at their default architectures, measured from the run's own log after a warm-up.

    python scripts/bench_ddp.py                      # 1 vs 2 processes on the CPU, a synthetic data folder
    python scripts/bench_ddp.py --processes 1 2 4 --device cuda --data data/bandai

Each run trains the same total batch (the stage's batch sizes are totals over the processes), so steps per second
is the speed-up itself. With N processes on a CPU each gets cores / N torch threads (--threads-per-process to set).
Prints one row per (stage, processes): steps/s, samples/s and the speed-up over one process.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
TEXT_ENCODER = {"kind": "minilm-random", "hidden": 384, "layers": 1, "heads": 12, "vocab_path": "builtin"}


def synthetic_folder(root: Path, clips: int = 64) -> Path:
    """A HumanML3D-format folder of ``clips`` walks (the fixture's pose, moved at several speeds and arm swings)."""
    sys.path.insert(0, str(REPO))
    from mld_core.motion.features import joints_to_features, mean_std

    pose = np.load(REPO / "tests" / "fixtures" / "humanml3d" / "new_joints_012314.npy")[0]  # (22, 3)
    rng = np.random.default_rng(0)
    for sub in ("new_joint_vecs", "texts"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    ids, feats = [], []
    for k in range(clips):
        T = int(rng.integers(60, 197))
        joints = np.repeat(pose[None], T, axis=0).copy()
        joints[:, :, 2] += rng.uniform(0.3, 1.5) * np.arange(T)[:, None] / 20.0
        joints[:, 21, 1] += rng.uniform(0, 0.4) * np.sin(np.linspace(0, rng.uniform(2, 8), T))
        f = joints_to_features(joints)
        cid = f"{k:04d}"
        np.save(root / "new_joint_vecs" / f"{cid}.npy", f)
        (root / "texts" / f"{cid}.txt").write_text(f"a person walks, take {k % 8}#a/DET#0.0#0.0\n")
        ids.append(cid)
        feats.append(f)
    mean, std = mean_std(feats)
    np.save(root / "Mean.npy", mean)
    np.save(root / "Std.npy", std)
    (root / "train.txt").write_text("\n".join(ids[4:]))
    (root / "val.txt").write_text("\n".join(ids[:4]))
    return root


def run_stage(stage: str, processes: int, data: Path, work: Path, args, vae_run: Path | None) -> dict:
    """One timed run: (steps/s, samples/s) between the warm-up's log line and the last."""
    out = work / f"{stage}-{processes}"
    steps = args.warmup + args.steps
    threads = args.threads_per_process or max(1, (os.cpu_count() or 1) // processes)
    if stage == "vae":
        config = {"val_every": args.warmup, "val_clips": 2}
        extra = []
    else:
        config = {"save_every": args.warmup, "text_encoder": TEXT_ENCODER}
        extra = ["--vae", str(vae_run)]
    command = ["-m", "mld_core", "train", stage, "--data", str(data), "--out", str(out), "--steps", str(steps),
               "--threads", str(threads), "--device", args.device, "--config", json.dumps(config), *extra]
    if processes > 1:
        command = ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(processes), *command]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "PYTHONPATH": str(REPO)}
    started, load = time.monotonic(), _cpu_snapshot()
    done = subprocess.run([sys.executable, *command], env=env, capture_output=True, text=True, timeout=args.timeout)
    others = _other_cpus(load, _cpu_snapshot())
    if done.returncode != 0:
        raise SystemExit(f"error: {stage} with {processes} process(es) failed:\n{done.stderr[-2000:]}")
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    first, last = log[0], log[-1]
    rate = (last["step"] - first["step"]) / (last["seconds"] - first["seconds"])
    run = json.loads((out / "train_config.json").read_text())["run"]
    return {"stage": stage, "processes": processes, "threads": threads, "steps_per_s": rate,
            "per_s": rate * run["batch_total"], "batch_total": run["batch_total"], "batch_of": run["batch_of"],
            "wall_s": time.monotonic() - started, "other_cpus": others}


def _cpu_snapshot():
    """(the machine's busy CPU seconds, this script's children's CPU seconds, the clock); Linux only."""
    import resource

    try:
        with open("/proc/stat") as fh:
            fields = [int(x) for x in fh.readline().split()[1:]]
    except OSError:
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ((sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK"), children.ru_utime + children.ru_stime,
            time.monotonic())


def _other_cpus(start, end) -> float | None:
    """How many CPUs other processes than the timed run kept busy, on average."""
    if start is None or end is None:
        return None
    return max(0.0, ((end[0] - start[0]) - (end[1] - start[1])) / (end[2] - start[2]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="a HumanML3D-format folder (default: synthetic)")
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--stages", nargs="+", choices=("vae", "denoiser"), default=["vae", "denoiser"])
    parser.add_argument("--steps", type=int, default=40, help="steps timed after the warm-up (default 40)")
    parser.add_argument("--warmup", type=int, default=10, help="steps before the timing starts (default 10)")
    parser.add_argument("--device", default="cpu", help="cpu (gloo) or cuda (NCCL, one GPU per process)")
    parser.add_argument("--threads-per-process", type=int, default=None)
    parser.add_argument("--timeout", type=float, default=1800)
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        data = args.data or synthetic_folder(work / "data")
        vae_run = None
        if "denoiser" in args.stages:  # a VAE to encode the latents with (a few steps: speed only)
            vae_run = work / "vae-for-denoiser"
            subprocess.run([sys.executable, "-m", "mld_core", "train", "vae", "--data", str(data), "--out",
                            str(vae_run), "--steps", "2", "--config", '{"val_clips": 2}'], check=True,
                           capture_output=True, env={**os.environ, "PYTHONPATH": str(REPO)})
        rows = [run_stage(stage, n, data, work, args, vae_run) for stage in args.stages for n in args.processes]
    base = {r["stage"]: r["steps_per_s"] for r in rows if r["processes"] == min(args.processes)}
    print(f"{os.cpu_count()} CPU(s), device {args.device}, {args.steps} steps timed after {args.warmup}, "
          f"data {'synthetic (64 clips)' if args.data is None else args.data}")
    print("| stage | processes | threads each | total batch | steps/s | per second | speed-up | other CPUs busy |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        r["speedup"] = r["steps_per_s"] / base[r["stage"]]
        print(f"| {r['stage']} | {r['processes']} | {r['threads']} | {r['batch_total']} {r['batch_of']} | "
              f"{r['steps_per_s']:.2f} | {r['per_s']:.0f} {r['batch_of']} | {r['speedup']:.2f}x | "
              + ("?" if r["other_cpus"] is None else f"{r['other_cpus']:.1f}") + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
