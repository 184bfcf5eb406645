"""Fewer DDIM steps: what a take keeps and where the time goes (a measurement for a Draft mode; prints a table).

    .venv/bin/python scripts/steps_table.py [--steps 1,2,4,8,10,20,50] [--seeds 2] [--threads 2] [--repeat 5]

For each step count: the physical-check pass rate (mld_core.eval.physical) of the hand-written paraphrases of
scripts/side_accuracy.py (4 s, --seeds seeds each), the foot skating ratio of the locomotion contents and the mean
joint jerk of all takes (mld_core.eval.quality), and the time of one 4 s prompt at batch 1 split into text,
diffusion, decode and features -> joints (median of --repeat runs, one process). R@3 and FID come from
``python -m mld_core evaluate t2m --preset reduced --steps N`` (docs/evaluation.md).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from mld_core.eval import physical  # noqa: E402
from mld_core.eval.quality import foot_skating_ratio, mean_jerk  # noqa: E402
from side_accuracy import PARAPHRASES  # noqa: E402

LOCOMOTION = ("walk", "run", "dash", "walk-back", "walk-left", "walk-right", "walk-turn-left", "walk-turn-right")


def quality(pipe, steps: int, seeds: int) -> dict:
    passed, skating, jerk = [], [], []
    items = [(label, p) for label, prompts in PARAPHRASES.items() for p in prompts]
    prompts = [p for _, p in items]
    for seed in range(seeds):
        out = pipe(prompts, seconds=4.0, seed=seed, num_inference_steps=steps)
        for (label, _), joints in zip(items, out.joints):
            passed.append(physical.passes(joints, label))
            jerk.append(mean_jerk(joints))
            if label in LOCOMOTION:
                skating.append(foot_skating_ratio(joints))
    return {"pass": float(np.mean(passed)), "skating": float(np.mean(skating)), "jerk": float(np.mean(jerk)),
            "takes": len(passed)}


def timing(pipe, steps: int, repeat: int) -> dict:
    from mld_core.motion.features import features_to_joints

    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = pipe(["a person walks forward and waves"], seconds=4.0, seed=0, num_inference_steps=steps)
        total = time.perf_counter() - t0
        t1 = time.perf_counter()
        features_to_joints(out.features[0, : int(out.lengths[0])])
        runs.append({**out.timings, "total": total, "joints_s": time.perf_counter() - t1})
    return {k: statistics.median(r[k] for r in runs) for k in ("condition_s", "diffusion_s", "decode_s", "joints_s",
                                                                "total")}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", default="1,2,4,8,10,20,50")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args(argv)
    import torch

    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(args.threads)
    pipe = MLDPipeline.from_pretrained()
    pipe(["warm up"], seconds=4.0)
    rows = []
    for steps in (int(s) for s in args.steps.split(",")):
        rows.append((steps, quality(pipe, steps, args.seeds), timing(pipe, steps, args.repeat)))
    base = rows[-1][2]["total"]
    print("| DDIM steps | physical pass | skating (locomotion) | jerk (m/s^3) | text ms | diffusion ms | decode ms | "
          "joints ms | total ms | x last |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for steps, q, t in rows:
        print(f"| {steps} | {q['pass']:.2f} | {q['skating']:.2f} | {q['jerk']:.1f} | {1e3 * t['condition_s']:.1f} | "
              f"{1e3 * t['diffusion_s']:.1f} | {1e3 * t['decode_s']:.1f} | {1e3 * t['joints_s']:.1f} | "
              f"{1e3 * t['total']:.1f} | {t['total'] / base:.2f} |")
    print(f"({rows[0][1]['takes']} takes per row)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
