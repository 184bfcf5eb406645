"""Two runs of scripts/side_accuracy.py side by side: per content the pass rate and foot skating of each, and
whether the second is at least as good on each (prints a table).

    .venv/bin/python scripts/compare_side_accuracy.py BASE.json NEW.json [--tolerance 0.0]

Both files come from ``side_accuracy.py --json`` with the same prompts (e.g. ``--prompts paraphrase --seeds 8``).
A content is "worse" when NEW's pass rate is lower, or (locomotion contents) its skating higher, by more than
``--tolerance``, or when NEW did not score it; the last line counts them: the gate of a new default model (issue 15)
is none worse.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

LOCOMOTION = ("walk", "run", "dash", "walk-back", "walk-left", "walk-right", "walk-turn-left", "walk-turn-right")


def prompt_sets(path: Path) -> dict:
    """prompt set (e.g. "paraphrase@4s") -> content -> {"pass_rate", "skating", ...} of one side_accuracy run."""
    return {name: run["contents"] for name, run in json.loads(Path(path).read_text())["generated"].items()}


def compare(base: dict, new: dict, tolerance: float = 0.0) -> list[dict]:
    """One row per content both runs scored: the two pass rates and skating ratios, and whether NEW is worse."""
    rows = []
    for content in base:
        if content not in new:
            rows.append({"content": content, "pass": (base[content]["pass_rate"], float("nan")),
                         "skating": (base[content]["skating"], float("nan")), "worse": True})
            continue
        b, n = base[content], new[content]
        worse_pass = n["pass_rate"] < b["pass_rate"] - tolerance
        worse_skate = content in LOCOMOTION and n["skating"] > b["skating"] + tolerance
        rows.append({"content": content, "pass": (b["pass_rate"], n["pass_rate"]), "skating": (b["skating"], n["skating"]),
                     "worse": worse_pass or worse_skate})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("base", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--tolerance", type=float, default=0.0, help="differences this small do not count as worse")
    args = parser.parse_args(argv)
    try:
        base, new = prompt_sets(args.base), prompt_sets(args.new)
    except (OSError, KeyError, TypeError, json.JSONDecodeError) as exc:
        print(f"error: cannot read the side_accuracy JSON files: {exc}", file=sys.stderr)
        return 2
    shared = [name for name in base if name in new]
    if not shared:
        print(f"error: the runs share no prompt set ({', '.join(base)} against {', '.join(new)})", file=sys.stderr)
        return 2
    rows = compare(base[shared[0]], new[shared[0]], args.tolerance)
    print(f"prompt set {shared[0]}")
    print(f"| content | pass {args.base.stem} | pass {args.new.stem} | skating {args.base.stem} | skating {args.new.stem} | worse |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['content']} | {r['pass'][0]:.2f} | {r['pass'][1]:.2f} | {r['skating'][0]:.2f} | {r['skating'][1]:.2f} | "
              f"{'yes' if r['worse'] else ''} |")
    worse = [r["content"] for r in rows if r["worse"]]
    print(f"{len(worse)} of {len(rows)} contents worse" + (f": {', '.join(worse)}" if worse else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
