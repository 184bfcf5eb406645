"""Bare commands ("wave your left hand", "kick") generated as typed and worded as sentences ("a person waves their
left hand", config ``commands_as_sentences``), scored by the Bandai Namco contents' physical checks.

    python research/command_wording.py [--model DIR] [--seeds 8] [--seconds 4] [--threads 1] [--json FILE]
        [--anchor-weight W]

Every command is generated with seeds 0..N-1 both ways, so the two columns differ only by the wording the text
encoder reads. ``--anchor-weight 0`` turns the model's content anchor off (which moves a prompt towards the
contents it reads, and so already helps a command on the bundled model). Prints one row per content (pass rate as typed, worded) and the mean over contents. A measurement,
not a test: it asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mld_core.condition.wording import as_sentence  # noqa: E402
from mld_core.eval import physical  # noqa: E402

# Commands as users type them, for each content a physical check describes (none is a training caption's wording).
COMMANDS = {
    "walk": ["walk forward", "walk"],
    "run": ["run forward", "run"],
    "dash": ["sprint forward"],
    "walk-back": ["walk backwards"],
    "walk-turn-left": ["walk forward and turn left"],
    "walk-turn-right": ["walk forward and turn right"],
    "walk-left": ["walk diagonally to the left"],
    "walk-right": ["walk diagonally to the right"],
    "raise-up-left-hand": ["raise your left hand"],
    "raise-up-right-hand": ["raise your right hand"],
    "raise-up-both-hands": ["raise both hands"],
    "wave-left-hand": ["wave your left hand"],
    "wave-right-hand": ["wave your right hand"],
    "wave-both-hands": ["wave both hands"],
    "bye": ["wave goodbye"],
    "byebye": ["wave goodbye with both hands"],
    "bow": ["bow"],
    "kick": ["kick"],
}


def pass_rate(pipe, prompts: list[str], label: str, seeds: int, seconds: float) -> float:
    passed = []
    for prompt in prompts:
        out = pipe([prompt], seconds=seconds, seed=0, num_variants=seeds)
        passed += [physical.passes(out.joints[v, : out.lengths[v]], label) for v in range(len(out.joints))]
    return float(np.mean(passed))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=None, help="a model folder (default: the bundled model)")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--anchor-weight", type=float, default=None, help="the content anchor's weight (default: the "
                    "model's; 0: off)")
    args = ap.parse_args(argv)
    if not 1 <= args.seeds <= 256 or not 1.0 <= args.seconds <= 9.8:
        print("error: --seeds must be in 1..256 and --seconds in 1..9.8", file=sys.stderr)
        return 2
    import torch

    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(args.threads)
    pipe = MLDPipeline.from_pretrained(args.model)
    if args.anchor_weight is not None:
        pipe.config.content_anchor.weight = args.anchor_weight
    start, rows = time.perf_counter(), []
    print(f"model {pipe.model_id}; {args.seeds} seeds x {args.seconds:g} s; content anchor weight "
          f"{pipe.config.content_anchor.weight:g}")
    print(f"{'content':22} {'as typed':>8} {'worded':>7}  commands")
    for label, prompts in COMMANDS.items():
        rates = {}
        for worded in (False, True):
            pipe.config.commands_as_sentences = worded
            pipe.clear_text_cache()
            rates[worded] = pass_rate(pipe, prompts, label, args.seeds, args.seconds)
        rows.append({"content": label, "commands": prompts, "worded_as": [as_sentence(p) for p in prompts],
                     "as_typed": rates[False], "worded": rates[True]})
        print(f"{label:22} {rates[False]:8.2f} {rates[True]:7.2f}  {'; '.join(prompts)}", flush=True)
    typed, worded = (float(np.mean([r[k] for r in rows])) for k in ("as_typed", "worded"))
    print(f"{'mean':22} {typed:8.3f} {worded:7.3f}  ({len(rows)} contents, {time.perf_counter() - start:.0f} s)")
    if args.json:
        args.json.write_text(json.dumps({"model": pipe.model_id, "seeds": args.seeds, "seconds": args.seconds,
                                         "rows": rows, "mean": {"as_typed": typed, "worded": worded}}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
