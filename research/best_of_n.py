"""Best of N: does ranking N variants by their quality badges pick takes that do what the prompt asks?

    python research/best_of_n.py [--model DIR] [--variants 8] [--seconds 4] [--bases 0] [--timing-prompts 6]
        [--json OUT.json] [--threads 1]

For every hand-written paraphrase of research/side_accuracy.py (20 contents), generates N variants (seeds
base..base+N-1) with ``rank=True`` and scores each by the content's physical checks (mld_core.eval.physical).
Prints the pass rate of: the seed-``base`` take (what N=1 gives), the mean over all N variants (N=1's expected
rate), the ranked first take (N, K=1), the take with the best adherence alone, the best by the physical badges
alone (rank_score without adherence), and the share of prompts where any variant passes (the ceiling of any
ranking); overall and per content. Timing: per-prompt calls with N=1 and with N and ranking,
interleaved in one process, median of ``--timing-prompts`` prompts. A measurement, not a test.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "research"))

from mld_core.eval import physical, quality  # noqa: E402
from side_accuracy import DEFAULT_CONTENTS, PARAPHRASES  # noqa: E402

BADGES = ("adherence", "skating", "float", "penetration_cm", "jitter")
PICKS = ("seed_base", "mean_of_n", "ranked_first", "best_adherence", "best_physical", "any_passes")


def requests() -> list[tuple[str, str]]:
    return [(c, p) for c in DEFAULT_CONTENTS for p in PARAPHRASES.get(c, [])]


def score_groups(pipe, reqs, n: int, seconds: float, base: int, batch: int, per_content: dict) -> dict:
    """{pick: [pass (0/1) per request]} for one seed base; per_content[content][pick] gets the same."""
    picks = defaultdict(list)
    per = max(1, batch // n)
    for a in range(0, len(reqs), per):
        chunk = reqs[a:a + per]
        out = pipe([p for _, p in chunk], seconds=seconds, seed=base, num_variants=n, rank=True)
        for i, (content, _) in enumerate(chunk):
            rows = list(range(i * n, (i + 1) * n))
            passed = {out.seeds[r]: physical.passes(out.joints[r, : int(out.lengths[r])], content) for r in rows}
            adherence = {out.seeds[r]: out.badges[r].adherence for r in rows}
            physical_only = {out.seeds[r]: quality.rank_score(replace(out.badges[r], adherence=None)) for r in rows}
            got = {"seed_base": passed[base], "mean_of_n": float(np.mean(list(passed.values()))),
                   "ranked_first": passed[out.seeds[rows[0]]],
                   "best_adherence": passed[max(adherence, key=lambda s: (adherence[s], -s))],
                   "best_physical": passed[max(physical_only, key=lambda s: (physical_only[s], -s))],
                   "any_passes": any(passed.values())}
            for k, v in got.items():
                picks[k].append(v)
                per_content[content][k].append(v)
            base_row = next(r for r in rows if out.seeds[r] == base)
            picks["badges:seed_base"].append(out.badges[base_row].as_dict())
            picks["badges:ranked_first"].append(out.badges[rows[0]].as_dict())
        print(f"base {base}: {a + len(chunk)}/{len(reqs)} prompts", file=sys.stderr)
    return picks


def timing(pipe, reqs, n: int, seconds: float, count: int) -> dict:
    one, many = [], []
    pipe(reqs[0][1], seconds=seconds, num_variants=n, rank=True)  # warm up (loads the evaluator)
    for _, prompt in reqs[:: max(1, len(reqs) // count)][:count]:
        t0 = time.perf_counter()
        pipe(prompt, seconds=seconds, num_variants=1)
        one.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        pipe(prompt, seconds=seconds, num_variants=n, rank=True)
        many.append(time.perf_counter() - t0)
    return {"n1_s": float(np.median(one)), "nN_ranked_s": float(np.median(many)),
            "ratio": float(np.median(many) / np.median(one))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=None)
    ap.add_argument("--variants", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--bases", default="0", help="comma-separated seed bases (replications)")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--timing-prompts", type=int, default=6)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    import torch

    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(args.threads)
    pipe = MLDPipeline.from_pretrained(args.model)
    reqs = requests()
    results = defaultdict(list)
    per_content = defaultdict(lambda: defaultdict(list))
    for base in (int(b) for b in args.bases.split(",")):
        for k, v in score_groups(pipe, reqs, args.variants, args.seconds, base, args.batch, per_content).items():
            results[k] += v
    times = timing(pipe, reqs, args.variants, args.seconds, args.timing_prompts)
    n = len(results["seed_base"])
    print(f"\n{pipe.model_id}: {len(reqs)} paraphrases x {len(args.bases.split(','))} seed base(s), "
          f"N = {args.variants}, {args.seconds:g} s\n")
    print("| pick | pass rate |\n|---|---|")
    for k in PICKS:
        print(f"| {k} | {np.mean(results[k]):.3f} |")
    diff = np.asarray(results["ranked_first"], float) - np.asarray(results["mean_of_n"], float)
    print(f"\nranked first - expected N=1, paired over prompt groups: {diff.mean():+.3f} "
          f"(95% interval +-{1.96 * diff.std(ddof=1) / np.sqrt(len(diff)):.3f})")
    print("\n| content | groups | " + " | ".join(PICKS) + " |\n|---|---|" + "---|" * len(PICKS))
    for c, picks in per_content.items():
        print(f"| {c} | {len(picks['seed_base'])} | " + " | ".join(f"{np.mean(picks[k]):.2f}" for k in PICKS) + " |")
    print("\n| take | " + " | ".join(BADGES) + " |\n|---|" + "---|" * len(BADGES))
    for name in ("seed_base", "ranked_first"):
        rows = results["badges:" + name]
        print(f"| {name} | " + " | ".join(f"{np.mean([r[k] for r in rows]):.2f}" for k in BADGES) + " |")
    print(f"\n{n} prompt groups; time per prompt ({args.threads} thread(s)): N=1 {times['n1_s']:.2f} s, "
          f"N={args.variants} ranked {times['nN_ranked_s']:.2f} s (x{times['ratio']:.1f})")
    if args.json:
        args.json.write_text(json.dumps({"pass": {k: float(np.mean(results[k])) for k in PICKS},
                                         "timing": times, "groups": n}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
