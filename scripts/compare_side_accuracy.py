"""Two runs of scripts/side_accuracy.py side by side: per content the pass rate and foot skating of each, and
whether the second is at least as good on each (prints a table).

    .venv/bin/python scripts/compare_side_accuracy.py BASE.json NEW.json [--tolerance 0.0]

Both files come from ``side_accuracy.py --json`` with the same prompts (e.g. ``--prompts both --seeds 16``); each
prompt set both runs scored gets its table. A content is "worse" when NEW's pass rate is lower, or (locomotion
contents) its skating higher, by more than ``--tolerance``, or when NEW did not score it; the last line counts them
over all the shared prompt sets: the gate of a new default model (issue 15) is none worse.
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
    worse, total = [], 0
    for name in shared:
        rows = compare(base[name], new[name], args.tolerance)
        print_table(name, rows, args.base.stem, args.new.stem)
        worse += [r["content"] if len(shared) == 1 else f"{r['content']} ({name})" for r in rows if r["worse"]]
        total += len(rows)
    print(f"{len(worse)} of {total} contents worse" + (f": {', '.join(worse)}" if worse else ""))
    return 0


def print_table(prompt_set: str, rows: list[dict], base_name: str, new_name: str) -> None:
    print(f"prompt set {prompt_set}")
    print(f"| content | pass {base_name} | pass {new_name} | skating {base_name} | skating {new_name} | worse |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['content']} | {r['pass'][0]:.2f} | {r['pass'][1]:.2f} | {r['skating'][0]:.2f} | {r['skating'][1]:.2f} | "
              f"{'yes' if r['worse'] else ''} |")


if __name__ == "__main__":
    raise SystemExit(main())
