"""Calibrate and check the prompt-coverage thresholds on two hand-written prompt sets.

    python research/coverage_calibration.py [--model DIR] [--verbose] [--sweep]

tests/fixtures/coverage_known.txt holds paraphrases of contents the bundled model knows ("content | prompt"),
tests/fixtures/coverage_absent.txt prompts of motions absent from its training data. Prints, for the thresholds
in mld_core.condition.coverage (and with --sweep for others), the share of each set per verdict against the targets:
<= 5% of the known set ``unknown``, >= 95% of the absent set ``unknown`` or ``near``. Also checks that adding
side or style words to every prompt changes no verdict, and times one prompt's check (what the panel runs as the
user types).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mld_core.condition import coverage  # noqa: E402
from mld_core.motion.features import mirror_text  # noqa: E402

FIXTURES = REPO / "tests" / "fixtures"
# Side and style words added to (or swapped in) every prompt: none may change a verdict.
DECORATIONS = {
    "tired after the first word": lambda p: _insert(p, "tired"),
    "elderly after the first word": lambda p: _insert(p, "elderly"),
    "'happily' at the end": lambda p: p + " happily",
    "left <-> right swapped": lambda p: mirror_text(p),
    "'left' after the first word": lambda p: _insert(p, "left"),
}


def _insert(prompt: str, word: str) -> str:
    first, _, rest = prompt.partition(" ")
    return f"{first} {word} {rest}".strip()


def read_set(path: Path) -> list[str]:
    lines = [s.strip() for s in path.read_text(encoding="utf-8").splitlines()]
    return [s.split("|", 1)[-1].strip() for s in lines if s and not s.startswith("#")]


def rates(scores: np.ndarray, known_min: float, near_min: float) -> dict:
    verdicts = [coverage.verdict_for(s, known_min, near_min) for s in scores]
    return {v: verdicts.count(v) / len(verdicts) for v in ("known", "near", "unknown")}


def row(name: str, scores: np.ndarray, known_min: float, near_min: float) -> str:
    r = rates(scores, known_min, near_min)
    return (f"| {name} | {len(scores)} | {r['known']:.2f} | {r['near']:.2f} | {r['unknown']:.2f} | "
            f"{np.min(scores):.2f} / {np.median(scores):.2f} / {np.max(scores):.2f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=None)
    ap.add_argument("--verbose", action="store_true", help="every prompt with its score and nearest caption")
    ap.add_argument("--sweep", action="store_true", help="also the rates for other thresholds")
    args = ap.parse_args(argv)
    import torch

    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(1)
    pipe = MLDPipeline.from_pretrained(args.model)
    sets = {"known": read_set(FIXTURES / "coverage_known.txt"), "absent": read_set(FIXTURES / "coverage_absent.txt")}
    results = {k: pipe.coverage(v) for k, v in sets.items()}
    if any(not c.available for cs in results.values() for c in cs):
        print(f"{pipe.model_id} has no coverage index", file=sys.stderr)
        return 2
    scores = {k: np.array([c.score for c in cs]) for k, cs in results.items()}
    if args.verbose:
        for k, cs in results.items():
            for c in sorted(cs, key=lambda c: c.score):
                print(f"{k:6s} {c.score:.3f} {c.verdict:7s} {c.prompt!r:60s} ~ {c.nearest[0][0]!r}")
    print(f"model {pipe.model_id}, thresholds known >= {coverage.KNOWN_MIN}, near >= {coverage.NEAR_MIN}\n")
    print("| set | prompts | known | near | unknown | score min / median / max |")
    print("|---|---|---|---|---|---|")
    for k in sets:
        print(row(k, scores[k], coverage.KNOWN_MIN, coverage.NEAR_MIN))
    known_unknown = rates(scores["known"], coverage.KNOWN_MIN, coverage.NEAR_MIN)["unknown"]
    absent_flagged = 1.0 - rates(scores["absent"], coverage.KNOWN_MIN, coverage.NEAR_MIN)["known"]
    print(f"\nknown set flagged unknown: {known_unknown:.3f} (target <= 0.05); "
          f"absent set flagged unknown or near: {absent_flagged:.3f} (target >= 0.95)")
    flips = 0
    for k, prompts in sets.items():
        for deco in DECORATIONS.values():
            decorated = pipe.coverage([deco(p) for p in prompts])
            flips += sum(a.verdict != b.verdict for a, b in zip(results[k], decorated))
    total = len(DECORATIONS) * sum(len(v) for v in sets.values())
    print(f"verdicts changed by adding side/style words ({'; '.join(DECORATIONS)}): {flips} of {total}")
    times = []
    for prompt in sets["known"] + sets["absent"]:  # one prompt at a time, as the panel asks while the user types
        t0 = time.perf_counter()
        pipe.coverage(prompt)
        times.append(time.perf_counter() - t0)
    print(f"one prompt's coverage (text encoder + index, {torch.get_num_threads()} thread): median "
          f"{np.median(times) * 1000:.1f} ms, max {np.max(times) * 1000:.1f} ms over {len(times)} prompts")
    if args.sweep:
        print("\n| known >= | near >= | known set unknown | absent set known | absent set unknown |")
        print("|---|---|---|---|---|")
        for known_min in (0.75, 0.80, 0.85):
            for near_min in (0.55, 0.60, 0.65, 0.68, 0.70, 0.72):
                a = rates(scores["known"], known_min, near_min)["unknown"]
                b = rates(scores["absent"], known_min, near_min)
                print(f"| {known_min:.2f} | {near_min:.2f} | {a:.3f} | {b['known']:.3f} | {b['unknown']:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
