"""How well each verb's physical check reads real motion: hit rate on real CMU windows whose captions ask for that verb,
false-alarm rate on windows whose captions ask for none of the checked verbs (and on plain walks on flat ground);
two more rows read the captions that ask for walking or running with the locomotion check (how often a caption's
walk or run is what the motion does).

    python research/verb_checks.py --data DIR [--values] [--json FILE]

DIR is a folder written by ``python -m mld_core data prepare cmu-joints``. Only windows captioned from the whole
trial are read (a long trial's windows captioned by the detectors themselves would be circular), mirrored copies
included. Prints one row per verb: windows, hit rate, false alarms on other windows and on walks; ``--values`` adds
each check's value percentiles among hits and among the rest (to place a threshold).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mld_core.data.cmu_joints import whole_trial_windows  # noqa: E402
from mld_core.data.dataset import read_captions  # noqa: E402
from mld_core.data.verbs import VERBS, verbs_in  # noqa: E402
from mld_core.eval import physical  # noqa: E402

WALK_WORDS = ("walk", "walks", "walking")
# Captions that ask for walking or running (and for none of the checked verbs): read by the locomotion check.
LOCOMOTION = {"walk": re.compile(r"\b(walk|walks|walking)\b"), "run": re.compile(r"\b(run|runs|running|jogs?|jogging)\b")}
NOT_FLAT = ("terrain", "stairs", "steps", "ladder", "step", "up", "over", "slope")


def measure(data: Path) -> dict:
    ids = whole_trial_windows(data)
    rows = {}
    for cid in ids:
        text = " ".join(c.text for c in read_captions(data / "texts" / f"{cid}.txt"))
        joints = np.load(data / "new_joints" / f"{cid}.npy")
        result = physical.classify(joints)
        asked = verbs_in(text)
        rows[cid] = {"verbs": asked, "walk": _flat_walk(text),
                     "locomotion": [v for v, word in LOCOMOTION.items() if not asked and word.search(text.lower())],
                     "shows": {v: physical.shows(joints, v, result=result) for v in (*VERBS, *LOCOMOTION)},
                     "values": {v: float(result[physical._VERB_SHOWS[v][0]].value) for v in (*VERBS, *LOCOMOTION)}}
    table = {}
    for verb in (*VERBS, *LOCOMOTION):
        hits = [r for r in rows.values() if verb in r["verbs"] or verb in r["locomotion"]]
        rest = [r for r in rows.values() if not r["verbs"]]
        walks = [r for r in rest if r["walk"]]
        table[verb] = {"windows": len(hits), "hit_rate": _rate(hits, verb), "others": len(rest),
                       "false_alarm": _rate(rest, verb), "walks": len(walks), "false_alarm_walks": _rate(walks, verb),
                       "values_hit": _pct([r["values"][verb] for r in hits]),
                       "values_rest": _pct([r["values"][verb] for r in rest])}
    return table


def _flat_walk(text: str) -> bool:
    """A plain walk on flat ground (walking on uneven terrain or up stairs lifts both feet like a jump or a climb)."""
    words = text.lower().replace(",", " ").split()
    return any(w in words for w in WALK_WORDS) and not any(w in words for w in NOT_FLAT)


def _rate(rows: list[dict], verb: str) -> float:
    return float(np.mean([r["shows"][verb] for r in rows])) if rows else float("nan")


def _pct(values: list[float]) -> list[float]:
    return [round(float(np.percentile(values, q)), 3) for q in (5, 25, 50, 75, 95)] if values else []


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, type=Path, help="a folder written by data prepare cmu-joints")
    ap.add_argument("--values", action="store_true", help="print value percentiles (5/25/50/75/95)")
    ap.add_argument("--json", type=Path, default=None, help="also write the table here")
    args = ap.parse_args(argv)
    if not (args.data / "prepare_report.json").is_file():
        print(f"error: {args.data} is not a folder written by data prepare cmu-joints", file=sys.stderr)
        return 2
    table = measure(args.data)
    print(f"{'verb':12} {'windows':>7} {'hit':>6} {'false alarm':>11} {'on walks':>9}")
    for verb, r in table.items():
        print(f"{verb:12} {r['windows']:7d} {r['hit_rate']:6.2f} {r['false_alarm']:11.3f} {r['false_alarm_walks']:9.3f}")
        if args.values:
            print(f"{'':12} hits {r['values_hit']}  rest {r['values_rest']}")
    if args.json:
        args.json.write_text(json.dumps(table, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
