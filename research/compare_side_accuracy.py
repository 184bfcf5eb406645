"""Two runs of research/side_accuracy.py side by side: per content the pass rate and foot skating of each, and
whether the second is at least as good on each (prints a table).

    .venv/bin/python research/compare_side_accuracy.py BASE.json NEW.json [--tolerance 0.0] [--z 1.96]

Both files come from ``side_accuracy.py --json`` with the same prompts (e.g. ``--prompts both --seeds 16``); each
prompt set both runs scored gets its table. A content is "worse" when NEW's pass rate is lower, or (locomotion
contents) its skating higher, by more than ``--tolerance``, or when NEW did not score it; the last line counts them
over all the shared prompt sets: the gate of a new default model is none worse.

With ``--z``, a content is worse only when NEW is worse beyond noise: both runs hold each take (same prompts, same
seeds, same order, the same per-take keys), so the test is paired, each distinct request once. Pass: McNemar's
exact test over the takes that pass in one run only, as a z; skating: the mean per-take difference over its
standard error. Positive z = NEW worse. Contents without per-take numbers (JSON from before they were written) or
whose takes were asked differently fall back to ``--tolerance``. The last lines also give each prompt set's mean pass
rate and mean locomotion skating, the gate's aggregate part.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from statistics import NormalDist

LOCOMOTION = ("walk", "run", "dash", "walk-back", "walk-left", "walk-right", "walk-turn-left", "walk-turn-right")


def prompt_sets(path: Path) -> dict:
    """prompt set (e.g. "paraphrase@4s") -> content -> {"pass_rate", "skating", ...} of one side_accuracy run."""
    return {name: run["contents"] for name, run in json.loads(Path(path).read_text())["generated"].items()}


def paired_z(base_takes: dict, new_takes: dict) -> tuple[float, float]:
    """(pass z, skating z) of NEW against BASE over the same takes, each distinct request once; + = NEW worse."""
    keep = distinct_takes(base_takes, new_takes)
    base_passed, new_passed = [base_takes["passed"][i] for i in keep], [new_takes["passed"][i] for i in keep]
    lost = sum(b and not n for b, n in zip(base_passed, new_passed))
    won = sum(n and not b for b, n in zip(base_passed, new_passed))
    z_pass = mcnemar_z(lost, won)
    d = [new_takes["skating"][i] - base_takes["skating"][i] for i in keep]
    mean = sum(d) / len(d)
    sd = math.sqrt(sum((x - mean) ** 2 for x in d) / (len(d) - 1)) if len(d) > 1 else 0.0
    z_skate = mean / (sd / math.sqrt(len(d))) if sd > 1e-9 else (math.inf if mean > 1e-9 else 0.0)  # rounding
    return z_pass, z_skate


def distinct_takes(base_takes: dict, new_takes: dict) -> list[int]:
    """Indices of the takes to pair: the first of each key (prompt | seconds | seed | variant), since a repeated
    request is the same take and would count twice; every take where the runs hold no keys (older JSON)."""
    keys = base_takes.get("keys") or new_takes.get("keys")
    if not keys:
        return list(range(len(base_takes["passed"])))
    first: dict[str, int] = {}
    for i, key in enumerate(keys):
        first.setdefault(key or f"#{i}", i)  # an empty key names nothing: never merged
    return sorted(first.values())


def mcnemar_z(lost: int, won: int) -> float:
    """McNemar's exact test as a z: the one-sided binomial p of so uneven a split of the takes that changed
    (``lost`` passed only in BASE, ``won`` only in NEW), mapped through the normal quantile; + = NEW worse, 0 when
    p >= 0.5. Exact because a few changed takes (4 to 0: p 0.06) make the (lost - won) / sqrt(n) form overstate."""
    n, k = lost + won, max(lost, won)
    if n == 0 or lost == won:
        return 0.0
    p = sum(math.comb(n, i) for i in range(k, n + 1)) / 2 ** n
    z = NormalDist().inv_cdf(1.0 - max(p, 1e-15)) if p < 0.5 else 0.0
    return z if lost > won else -z


def _paired(b: dict, n: dict) -> bool:
    """Both runs hold per-take numbers for the same takes (equal keys where both have them)."""
    bt, nt = b.get("takes"), n.get("takes")
    if not (bt and nt) or not len(bt["passed"]) == len(nt["passed"]) == len(bt["skating"]) == len(nt["skating"]) > 0:
        return False
    return not (bt.get("keys") and nt.get("keys")) or bt["keys"] == nt["keys"]


def compare(base: dict, new: dict, tolerance: float = 0.0, z: float | None = None) -> list[dict]:
    """One row per content both runs scored: the two pass rates and skating ratios, the paired z of each (None
    without per-take numbers) and whether NEW is worse: beyond ``z`` where given and paired, else by ``tolerance``."""
    rows = []
    for content in base:
        if content not in new:
            rows.append({"content": content, "pass": (base[content]["pass_rate"], float("nan")),
                         "skating": (base[content]["skating"], float("nan")), "z": None, "worse": True})
            continue
        b, n = base[content], new[content]
        locomotion = content in LOCOMOTION
        zs = paired_z(b["takes"], n["takes"]) if _paired(b, n) else None
        if z is not None and zs is not None:
            worse_pass, worse_skate = zs[0] > z, locomotion and zs[1] > z
        else:
            worse_pass = n["pass_rate"] < b["pass_rate"] - tolerance
            worse_skate = locomotion and n["skating"] > b["skating"] + tolerance
        rows.append({"content": content, "pass": (b["pass_rate"], n["pass_rate"]), "skating": (b["skating"], n["skating"]),
                     "z": zs, "worse": worse_pass or worse_skate})
    return rows


def aggregate(rows: list[dict]) -> dict:
    """The prompt set's mean pass rate over contents and mean skating over locomotion contents, base and new."""
    both = [r for r in rows if not math.isnan(r["pass"][1])]
    loco = [r for r in both if r["content"] in LOCOMOTION]
    return {"pass": tuple(_mean([r["pass"][k] for r in both]) for k in (0, 1)),
            "skating": tuple(_mean([r["skating"][k] for r in loco]) for k in (0, 1))}


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs) if xs else float("nan")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("base", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--tolerance", type=float, default=0.0, help="differences this small do not count as worse")
    parser.add_argument("--z", type=float, default=None,
                        help="worse only beyond this paired z (e.g. 1.96), where both runs hold per-take numbers")
    args = parser.parse_args(argv)
    if args.z is not None and not (math.isfinite(args.z) and args.z >= 0):
        parser.error(f"--z must be a finite number >= 0 (e.g. 1.96), got {args.z}")
    if not (math.isfinite(args.tolerance) and args.tolerance >= 0):
        parser.error(f"--tolerance must be a finite number >= 0, got {args.tolerance}")
    try:
        base, new = prompt_sets(args.base), prompt_sets(args.new)
    except (OSError, KeyError, TypeError, json.JSONDecodeError) as exc:
        print(f"error: cannot read the side_accuracy JSON files: {exc}", file=sys.stderr)
        return 2
    shared = [name for name in base if name in new]
    if not shared:
        print(f"error: the runs share no prompt set ({', '.join(base)} against {', '.join(new)})", file=sys.stderr)
        return 2
    worse, total, means = [], 0, {}
    for name in shared:
        rows = compare(base[name], new[name], args.tolerance, args.z)
        print_table(name, rows, args.base.stem, args.new.stem)
        worse += [r["content"] if len(shared) == 1 else f"{r['content']} ({name})" for r in rows if r["worse"]]
        total += len(rows)
        means[name] = aggregate(rows)
    for name, m in means.items():
        print(f"{name}: mean pass {m['pass'][0]:.4f} -> {m['pass'][1]:.4f}, "
              f"mean locomotion skating {m['skating'][0]:.4f} -> {m['skating'][1]:.4f}")
    rule = f"beyond paired z {args.z:g}" if args.z is not None else f"by more than {args.tolerance:g}"
    print(f"{len(worse)} of {total} contents worse ({rule})" + (f": {', '.join(worse)}" if worse else ""))
    return 0


def print_table(prompt_set: str, rows: list[dict], base_name: str, new_name: str) -> None:
    print(f"prompt set {prompt_set}")
    print(f"| content | pass {base_name} | pass {new_name} | skating {base_name} | skating {new_name} | z pass | "
          f"z skating | worse |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        zp, zs = (f"{r['z'][0]:+.1f}", f"{r['z'][1]:+.1f}") if r["z"] is not None else ("-", "-")
        print(f"| {r['content']} | {r['pass'][0]:.2f} | {r['pass'][1]:.2f} | {r['skating'][0]:.3f} | "
              f"{r['skating'][1]:.3f} | {zp} | {zs} | {'yes' if r['worse'] else ''} |")


if __name__ == "__main__":
    raise SystemExit(main())
