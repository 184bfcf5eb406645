"""Fewer steps and the Draft mode: what a take keeps and where the time goes (prints a table).

    .venv/bin/python research/steps_table.py [--steps 1,2,4,8,10,20,50,draft1,draft2] [--seeds 2] [--threads 2]
                                            [--repeat 5] [--model DIR]

Rows: N = DDIM with N steps; draftN = the model's Draft denoiser with N consistency steps. For each row: the
physical-check pass rate (mld_core.eval.physical) of the hand-written paraphrases of
research/side_accuracy.py (4 s, --seeds seeds each), the foot skating ratio of the locomotion contents and the mean
joint jerk of all takes (mld_core.eval.quality), and the time of one 4 s prompt at batch 1 split into text,
diffusion, decode and features -> joints (median of --repeat runs, one process): "cold" with a prompt the
pipeline has not seen (the text encoder runs), "warm" with one it has (its embedding is cached: the live preview's
case when seconds or seed change). The last column compares each row's cold total with the first row's. R@3 and FID come from
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
sys.path.insert(0, str(REPO / "research"))

from mld_core.eval import physical  # noqa: E402
from mld_core.eval.quality import foot_skating_ratio, mean_jerk  # noqa: E402
from side_accuracy import PARAPHRASES  # noqa: E402

LOCOMOTION = ("walk", "run", "dash", "walk-back", "walk-left", "walk-right", "walk-turn-left", "walk-turn-right")


def parse_row(row: str) -> tuple[str, int, bool]:
    """"50" -> ("50", 50, False); "draft2" -> ("draft2", 2, True)."""
    draft = row.startswith("draft")
    return row, int(row[5:] if draft else row), draft


def quality(pipe, steps: int, draft: bool, seeds: int) -> dict:
    passed, skating, jerk = [], [], []
    items = [(label, p) for label, prompts in PARAPHRASES.items() for p in prompts]
    prompts = [p for _, p in items]
    for seed in range(seeds):
        out = pipe(prompts, seconds=4.0, seed=seed, num_inference_steps=steps, draft=draft)
        for (label, _), joints in zip(items, out.joints):
            passed.append(physical.passes(joints, label))
            jerk.append(mean_jerk(joints))
            if label in LOCOMOTION:
                skating.append(foot_skating_ratio(joints))
    return {"pass": float(np.mean(passed)), "skating": float(np.mean(skating)), "jerk": float(np.mean(jerk)),
            "takes": len(passed)}


def timings(pipe, rows: list, repeat: int, warm: bool) -> list[dict]:
    """Per row the median time of one 4 s prompt at batch 1 and its parts. The rows take turns, so a machine that
    drifts during the measurement shifts every row alike; each turn first runs its row once untimed (another
    prompt), so the timed run finds that row's weights in the CPU caches as back-to-back prompts of one mode do."""
    from mld_core.motion.features import features_to_joints

    runs = [[] for _ in rows]
    for k in range(repeat):
        for runs_of_row, (_, steps, draft) in zip(runs, rows):
            for timed in (False, True):
                prompt = ("a person walks forward and waves" if warm
                          else f"a person walks forward and waves {k} times{'' if timed else ' again'}")
                if not warm:
                    pipe.clear_text_cache()
                t0 = time.perf_counter()
                out = pipe([prompt], seconds=4.0, seed=k, num_inference_steps=steps, draft=draft)
                total = time.perf_counter() - t0
                t1 = time.perf_counter()
                features_to_joints(out.features[0, : int(out.lengths[0])])
            runs_of_row.append({**out.timings, "total": total, "joints_s": time.perf_counter() - t1})
    return [{k: statistics.median(r.get(k, 0.0) for r in row_runs)
             for k in ("condition_s", "diffusion_s", "decode_s", "repair_s", "joints_s", "total")} for row_runs in runs]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", default="1,2,4,8,10,20,50", help="rows: DDIM step counts and draftN")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--model", default=None, help="model folder (default: the bundled model)")
    parser.add_argument("--no-quality", action="store_true", help="timings only")
    parser.add_argument("--no-timing", action="store_true", help="quality only (many seeds: the timings add nothing)")
    args = parser.parse_args(argv)
    import torch

    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(args.threads)
    pipe = MLDPipeline.from_pretrained(args.model)
    rows = [parse_row(r.strip()) for r in args.steps.split(",")]
    for _, steps, draft in rows:
        pipe(["warm up"], seconds=4.0, num_inference_steps=steps, draft=draft)
    qualities = [{} if args.no_quality else quality(pipe, steps, draft, args.seeds) for _, steps, draft in rows]
    if args.no_timing:
        cold = warm = [None] * len(rows)
    else:
        cold, warm = timings(pipe, rows, args.repeat, False), timings(pipe, rows, args.repeat, True)
    results = [(name, q, c, w) for (name, _, _), q, c, w in zip(rows, qualities, cold, warm)]
    base = results[0][2]["total"] if results[0][2] else None
    print("| row | physical pass | skating (locomotion) | jerk (m/s^3) | text ms | diffusion ms | decode ms | "
          "repair ms | joints ms | total cold ms | total warm ms | cold x first row |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, q, t, w in results:
        qual = (f"{q['pass']:.3f} | {q['skating']:.3f} | {q['jerk']:.1f}" if q else "- | - | -")
        times = (f"{1e3 * t['condition_s']:.1f} | {1e3 * t['diffusion_s']:.1f} | {1e3 * t['decode_s']:.1f} | "
                 f"{1e3 * t['repair_s']:.1f} | {1e3 * t['joints_s']:.1f} | {1e3 * t['total']:.1f} | "
                 f"{1e3 * w['total']:.1f} | {t['total'] / base:.3f}" if t else "- | - | - | - | - | - | - | -")
        print(f"| {name} | {qual} | {times} |")
    if results[0][1]:
        print(f"({results[0][1]['takes']} takes per row)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
