"""Where --model auto sends the prompts v4's targets are measured on (mld_core.model_route), without generating.

    python research/v4/auto_routes.py --bandai data/bandai --cmu data/cmu [--json runs/auto_routes.json]

The vocabulary benchmark's prompts (scripts/vocabulary.py: each verb's captions, command and user wording) and the
Bandai physical check's (research/side_accuracy.py as research/v4/targets.py runs it: captions and paraphrases, 16
clips a content) and the Bandai test split's captions (evaluate t2m) are scored by the bundled default's coverage index and routed; the script prints how many of each
go to each model and every prompt that goes against its set (a verb prompt kept by the default, a Bandai prompt
sent away). A Bandai prompt that stays with the default is made exactly as the default makes it, so Auto's Bandai
physical pass is the default's wherever none is sent away.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "scripts"), str(ROOT / "research")]

from mld_core.bundled import DEFAULT_NAME  # noqa: E402
from mld_core.data.verbs import VERBS  # noqa: E402
from mld_core.model_route import model_for  # noqa: E402


def vocabulary_prompts(cmu: Path) -> list[tuple[str, str]]:
    """(verb/wording, prompt) of every prompt scripts/vocabulary.py scores."""
    import vocabulary
    from mld_core.data.cmu_joints import whole_trial_windows

    whole = set(whole_trial_windows(cmu))
    found = []
    for verb in VERBS:
        wordings, _ = vocabulary.prompts_for(cmu, verb, whole, 2)
        found += [(f"{verb}/{wording}", p) for wording, prompts in wordings.items() for p in prompts]
    return found


def bandai_prompts(bandai: Path) -> list[tuple[str, str]]:
    """(content/source, prompt) of every prompt the Bandai physical check generates (targets.py's settings)."""
    import side_accuracy

    clips = side_accuracy.load_clips(bandai, side_accuracy.DEFAULT_CONTENTS, 20.0)
    reqs = side_accuracy.build_requests(clips, ["captions", "paraphrase"], ["clip"], 4, 16, 2.0, 9.8)
    return sorted({(f"{r['content']}/{r['source']}", r["prompt"]) for r in reqs})


def bandai_test_captions(bandai: Path) -> list[tuple[str, str]]:
    """(content/t2m, caption) of every caption of the Bandai test split (what evaluate t2m samples from)."""
    from mld_core.data.dataset import load_split

    return sorted({(f"{c.action}/t2m", cap.text) for c in load_split(bandai, "test") for cap in c.captions})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bandai", type=Path, required=True, help="a folder written by data prepare bandai")
    ap.add_argument("--cmu", type=Path, required=True, help="a folder written by data prepare cmu-joints")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    import torch

    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(1)
    pipe = MLDPipeline.from_pretrained(None)
    report = {}
    for name, prompts, expected_default in (("vocabulary", vocabulary_prompts(args.cmu), False),
                                            ("bandai", bandai_prompts(args.bandai), True),
                                            ("bandai_t2m", bandai_test_captions(args.bandai), True)):
        covs = pipe.coverage([p for _, p in prompts])
        routes = [model_for(c) for c in covs]
        report[name] = {"prompts": len(prompts), "routes": dict(Counter(routes)),
                        "against": [{"set": where, "prompt": p, "verdict": c.verdict, "score": round(c.score, 3),
                                     "model": r}
                                    for (where, p), c, r in zip(prompts, covs, routes)
                                    if (r == DEFAULT_NAME) != expected_default]}
        print(f"{name}: {len(prompts)} prompts, " + ", ".join(f"{m} {n}" for m, n in Counter(routes).items()))
        for row in report[name]["against"]:
            print(f"  {row['set']:28} {row['verdict']:7} {row['score']:.2f} -> {row['model']}: {row['prompt']}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
