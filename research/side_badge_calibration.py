"""How well the side badge (mld_core.eval.named_side) reads the prepared Bandai Namco data.

1. Every caption of every clip (all splits): what ``asked_side`` reads, per content. A sided content should read as
   its own label (bye as a wave, respond and guide as a raised hand, with their side), an unsided one as nothing.
2. Every sided caption of the ``--split`` clips against the clip's own capture: ``side_used`` should say "named"
   (real motion uses the side its caption names), never "opposite".

    python research/side_badge_calibration.py --data data/bandai [--split test] [--json out.json]

Prints both tables per content, and every caption whose own capture used the opposite side.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mld_core.eval import named_side, physical  # noqa: E402

MAX_FRAMES = 196  # as the evaluation crops the clips


def _captions(root: Path, cid: str) -> list[str]:
    path = root / "texts" / f"{cid}.txt"
    lines = path.read_text(encoding="utf-8").splitlines() if path.is_file() else []
    return [line.split("#")[0].strip() for line in lines if line.strip()]


def read_table(root: Path, contents: dict) -> dict:
    """{content: {label read (or "none"): captions}} over every clip's captions."""
    table = collections.defaultdict(collections.Counter)
    for cid, content in contents.items():
        for caption in _captions(root, cid):
            ask = named_side.asked_side(caption)
            table[content][ask.label if ask else "none"] += 1
    return {k: dict(v) for k, v in sorted(table.items())}


def real_table(root: Path, contents: dict, split: str) -> tuple[dict, list]:
    """({content: {side verdict: caption-clip pairs}}, [(clip, caption) used the opposite side])."""
    ids = [s.strip() for s in (root / f"{split}.txt").read_text(encoding="utf-8").splitlines() if s.strip()]
    table, opposite = collections.defaultdict(collections.Counter), []
    for cid in ids:
        asks = [(c, named_side.asked_side(c)) for c in _captions(root, cid)]
        asks = [(c, a) for c, a in asks if a is not None]
        if not asks:
            continue
        checks = physical.classify(np.load(root / "new_joints" / f"{cid}.npy")[:MAX_FRAMES])
        for caption, ask in asks:
            verdict = named_side.side_used(ask, checks)
            table[contents.get(cid, "?")][verdict] += 1
            if verdict == "opposite":
                opposite.append((cid, caption))
    return {k: dict(v) for k, v in sorted(table.items())}, opposite


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="prepared Bandai Namco folder (data prepare bandai)")
    ap.add_argument("--split", default="test", help="clips whose captions are checked against their capture")
    ap.add_argument("--json", type=Path, default=None, help="write both tables here")
    args = ap.parse_args(argv)
    actions = args.data / "actions.json"
    if not actions.is_file():
        print(f"error: {actions} not found: give the folder `data prepare bandai` made", file=sys.stderr)
        return 2
    contents = json.loads(actions.read_text(encoding="utf-8"))["clips"]
    read = read_table(args.data, contents)
    print("1. what each content's captions read as (all splits):")
    for content, counts in read.items():
        print(f"  {content:22s} " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items(), key=lambda kv: -kv[1])))
    real, opposite = real_table(args.data, contents, args.split)
    print(f"2. the side each sided caption's own capture used ({args.split} split):")
    for content, counts in real.items():
        print(f"  {content:22s} " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    total = sum(sum(c.values()) for c in real.values())
    print(f"  opposite: {len(opposite)} of {total} caption-clip pairs")
    for cid, caption in opposite:
        print(f"    {cid}: {caption}")
    if args.json is not None:
        args.json.write_text(json.dumps({"read": read, "real": real, "opposite": opposite}, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
