"""Does a model make the motions people ask for? Per verb (jump, get low, on the ground, crawl, reach the floor,
inverted, stand up, climb, kick, throw), prompts worded three ways, scored by the verb's physical check and read
against real CMU motion's pass rate of the same check.

    python scripts/vocabulary.py --data DIR [--model DIR] [--seeds 8] [--seconds 5] [--threads 2] [--json FILE]
        [--verbs jump,crawl,...] [--verb-redraws N] [--vae-recon] [--split test|val|train]

DIR is a folder written by ``python -m mld_core data prepare cmu-joints``. The three wordings per verb:
  caption: test-split captions that ask for the verb (captions written from the whole trial; the first
           ``--captions`` of them in sorted order; from the val split, else the train split, when the test split
           has none: the row says which),
  command: a plain command ("jump", "crawl", "climb a ladder"), read as the pipeline reads it (a model with
           ``commands_as_sentences`` on, the default, encodes "jump" as "a person jumps"),
  user:    a description as a user writes it ("a person jumps over a puddle").
Each prompt is generated with ``--seeds`` seeds (seeds 0..N-1) at ``--seconds``. The real rate is the check's pass
rate on the real test windows of that verb (``--split``'s instead; all splits when it has fewer than 8). Prints one
row per verb and wording: takes, pass rate, the real rate and their ratio (the target is >= 0.8); ``--json`` writes
every take's prompt, seed, pass, draw, lowest joint and foot float. Last, one number for the table: the ratios
summed with each capped at 1 (30 cells for ten verbs, three wordings; ``capped_cells`` in the JSON). The ``low cm`` column is the median over the
row's takes of each take's lowest joint height, in cm (every prepared clip has its lowest joint on the floor, 0: below
0 the take sinks into the floor, above it hovers all take long); ``float`` the mean of their foot float badge (the
share of frames with no toe on the floor outside jumps: ``mld_core.eval.quality.foot_float``); each followed by the
real windows' figure. ``--verb-redraws`` (default: the model's config ``verb_redraws``, with ``--draft`` its ``draft.verb_redraws`` where set) draws a take that misses its prompt's verb again: 0 measures the model alone, as v4's targets do; the model's own count
measures what a user gets, with the share of takes drawn again and the seconds spent on it. ``--vae-recon`` generates nothing: it passes the real windows through the
model's VAE and prints each verb's pass rate before and after (the ceiling a denoiser on that VAE can reach; a
VAE-only run folder works), with the median value of the verb's check before and after (a throw's peak wrist speed
in m/s, a kick's held ankle height in m: ``mld_core.eval.physical``), which moves before a pass rate on a few dozen
windows does. An action-conditioned model (``train denoiser --cond action``) is asked for each verb
by its action label instead, one wording "action". A measurement, not a test: it asserts nothing. The Bandai
contents' table is ``research/side_accuracy.py``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mld_core.data.cmu_joints import whole_trial_windows  # noqa: E402
from mld_core.data.dataset import read_captions, split_ids  # noqa: E402
from mld_core.data.verbs import VERBS, verbs_in  # noqa: E402
from mld_core.eval import physical  # noqa: E402
from mld_core.eval.quality import foot_float  # noqa: E402
from mld_core.inputs import MAX_VERB_REDRAWS  # noqa: E402

COMMANDS = {"jump": "jump", "get_low": "squat down", "on_ground": "lie down on the floor", "crawl": "crawl",
            "reach_floor": "pick something up from the floor", "inverted": "do a cartwheel",
            "stand_up": "get up from the floor", "climb": "climb a ladder", "kick": "kick", "throw": "throw a ball"}
USER = {"jump": "a person jumps over a puddle", "get_low": "a person sits down on a chair",
        "on_ground": "a person collapses to the ground", "crawl": "a person crawls on hands and knees",
        "reach_floor": "a person picks up an object from the ground", "inverted": "a person does a handstand",
        "stand_up": "a person stands up from sitting on the ground", "climb": "a person climbs up a ladder",
        "kick": "a person kicks a ball", "throw": "a person throws a ball"}
MIN_REAL = 8


def windows_of(data: Path, ids: list[str], whole: set[str], verb: str) -> list[tuple[str, list[str]]]:
    out = []
    for cid in ids:
        if cid.startswith("M") or cid not in whole:
            continue
        texts = [c.text for c in read_captions(data / "texts" / f"{cid}.txt")]
        if any(verb in verbs_in(t) for t in texts):
            out.append((cid, [t for t in texts if verb in verbs_in(t)]))
    return out


def prompts_for(data: Path, verb: str, whole: set[str], captions: int, real_split: str = "test") -> tuple[dict, list]:
    """The wordings' prompts for ``verb`` and the real windows its real rate is read on: those of ``real_split``
    (all splits when it has fewer than MIN_REAL)."""
    test = windows_of(data, split_ids(data, "test"), whole, verb)
    for split in ("test", "val", "train"):
        pool = test if split == "test" else windows_of(data, split_ids(data, split), whole, verb)
        if pool:
            break
    chosen = sorted({caps[0] for _, caps in pool})[:captions]
    real = test if real_split == "test" else windows_of(data, split_ids(data, real_split), whole, verb)
    if len(real) < MIN_REAL:
        real = windows_of(data, split_ids(data, "all"), whole, verb)
    return {f"caption ({split})" if split != "test" else "caption": chosen, "command": [COMMANDS[verb]],
            "user": [USER[verb]]}, real


def vae_recon_results(pipe, data: Path, wins: list[tuple[str, list[str]]], verb: str,
                      batch: int = 16) -> list[tuple[bool, float]]:
    """Each real window after the model's VAE encodes and decodes it (at its length): whether it still shows the verb
    (the ceiling a denoiser on that VAE can reach), and its check's value."""
    from mld_core.motion.features import features_to_joints

    max_frames = int(pipe.config.max_frames)
    results = []
    for k in range(0, len(wins), batch):
        feats = [np.load(data / "new_joint_vecs" / f"{cid}.npy")[:max_frames] for cid, _ in wins[k:k + batch]]
        z, lengths = pipe.features_to_latents(feats)
        recon = pipe.latents_to_features(z, lengths)
        for i, n in enumerate(lengths.tolist()):
            results.append(physical.verb_result(features_to_joints(recon[i, :n]), verb))
    return results


def real_joints(data: Path, wins: list[tuple[str, list[str]]]) -> list[np.ndarray]:
    return [np.load(data / "new_joints" / f"{cid}.npy") for cid, _ in wins]


def real_results(joints: list[np.ndarray], verb: str) -> list[tuple[bool, float]]:
    return [physical.verb_result(j, verb) for j in joints]


def lowest_cm(joints) -> float:
    """The lowest joint's height over a take (T, 22, 3), in cm: 0 on the floor, below it sunk in, above it hovering."""
    return 100.0 * float(np.asarray(joints)[..., 1].min())


def real_floor(joints: list[np.ndarray]) -> tuple[float, float]:
    """The real windows' median lowest joint (cm) and mean foot float (nan for none)."""
    if not joints:
        return float("nan"), float("nan")
    return float(np.median([lowest_cm(j) for j in joints])), float(np.mean([foot_float(j) for j in joints]))


def rate_and_median(results: list[tuple[bool, float]]) -> tuple[float, float]:
    """The pass rate and the median check value of (pass, value) results (nan for none)."""
    if not results:
        return float("nan"), float("nan")
    return float(np.mean([ok for ok, _ in results])), float(np.median([v for _, v in results]))


def capped_cells(rows: list[dict]) -> float:
    """The sum over rows (a verb and a wording each) of the generated-to-real ratio capped at 1: one number for the
    whole table, which a verb far over its bar cannot pad (rows without a real rate count 0)."""
    return float(sum(min(1.0, r["ratio"]) for r in rows if np.isfinite(r["ratio"])))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, type=Path, help="a folder written by data prepare cmu-joints")
    ap.add_argument("--model", default=None, help="a model folder, a bundled model's name, or auto: each prompt by "
                    "the bundled model it goes to (mld_core.model_route; default: the bundled default)")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--captions", type=int, default=2, help="test captions per verb (default 2)")
    ap.add_argument("--verbs", default=",".join(VERBS), help="comma-separated verbs (default: all)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--verb-redraws", type=int, default=None, metavar="N",
                    help="draws of a take beyond its first when it misses its prompt's verb (default: the model's (a Draft's own where set) "
                         "config verb_redraws; 0: the model alone)")
    ap.add_argument("--draft", action="store_true", help="the model's Draft (docs/draft.md) instead of its Final")
    ap.add_argument("--vae-recon", action="store_true",
                    help="only the real windows through the model's VAE (works on a VAE-only run folder)")
    ap.add_argument("--split", default="test", choices=("test", "val", "train"),
                    help="the split whose real windows set the real rate (default test; train shows whether a VAE "
                         "reproduces the clips it trained on)")
    args = ap.parse_args(argv)
    if not (args.data / "prepare_report.json").is_file():
        print(f"error: {args.data} is not a folder written by data prepare cmu-joints", file=sys.stderr)
        return 2
    verbs = [v.strip() for v in args.verbs.split(",") if v.strip()]
    unknown = [v for v in verbs if v not in VERBS]
    if unknown or not 1 <= args.seeds <= 256:
        print(f"error: unknown verbs {unknown} (known: {', '.join(VERBS)}) or --seeds outside 1..256",
              file=sys.stderr)
        return 2
    if args.verb_redraws is not None and not 0 <= args.verb_redraws <= MAX_VERB_REDRAWS:
        print(f"error: --verb-redraws must be between 0 and {MAX_VERB_REDRAWS}, got {args.verb_redraws}",
              file=sys.stderr)
        return 2
    import torch

    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(args.threads)
    from mld_core.bundled import DEFAULT_NAME
    from mld_core.model_route import ModelRouter, is_auto

    router = ModelRouter(MLDPipeline.from_pretrained) if is_auto(args.model) else None
    pipe = router.pipe(DEFAULT_NAME) if router else MLDPipeline.from_pretrained(args.model)
    whole = set(whole_trial_windows(args.data))
    rows, takes, start, redraw_s = [], [], time.perf_counter(), 0.0
    if args.vae_recon:
        print(f"model {pipe.model_id}: the real windows through its VAE")
        print(f"{'verb':12} {'windows':>7} {'real':>6} {'recon':>6} {'median value real':>18} {'recon':>6}")
        for verb in verbs:
            _, real_wins = prompts_for(args.data, verb, whole, args.captions, args.split)
            real, real_value = rate_and_median(real_results(real_joints(args.data, real_wins), verb))
            recon, recon_value = rate_and_median(vae_recon_results(pipe, args.data, real_wins, verb))
            rows.append({"verb": verb, "real_windows": len(real_wins), "real": real, "vae_recon": recon,
                         "real_median_value": real_value, "vae_recon_median_value": recon_value})
            print(f"{verb:12} {len(real_wins):7d} {real:6.2f} {recon:6.2f} {real_value:18.2f} {recon_value:6.2f}",
                  flush=True)
        if args.json:
            args.json.write_text(json.dumps({"model": pipe.model_id, "rows": rows}, indent=1) + "\n")
        return 0
    by_action = pipe.config.denoiser is not None and pipe.config.denoiser.cond == "action"
    missing = [v for v in verbs if v not in pipe.config.actions] if by_action else []
    if missing:
        print(f"error: this action-conditioned model has no label {', '.join(missing)}", file=sys.stderr)
        return 2
    redraws = pipe.default_verb_redraws(args.draft) if args.verb_redraws is None else args.verb_redraws
    model = "auto" if router else pipe.model_id
    print(f"model {model}{' (Draft)' if args.draft else ''}; {args.seeds} seeds x {args.seconds:g} s"
          + (" (action labels)" if by_action else "")
          + (f"; verb redraws {redraws}" if redraws and not by_action else ""))
    print(f"{'verb':12} {'wording':15} {'takes':>5} {'pass':>6} {'real':>6} {'ratio':>6} {'low cm':>7} {'real':>5} "
          f"{'float':>5} {'real':>5}")
    for verb in verbs:
        wordings, real_wins = prompts_for(args.data, verb, whole, args.captions, args.split)
        if by_action:
            wordings = {"action": [verb]}
        joints = real_joints(args.data, real_wins)
        real = rate_and_median(real_results(joints, verb))[0]
        real_low, real_float = real_floor(joints)
        for wording, prompts in wordings.items():
            passed, lows, floats = [], [], []
            for prompt in prompts:
                actions = {"actions": [prompt]} if by_action else {}
                maker = router.pipe_for([prompt])[1] if router else pipe
                out = maker([prompt], seconds=args.seconds, seed=0, num_variants=args.seeds, draft=args.draft,
                            **actions,
                            verb_redraws=args.verb_redraws)  # None: the maker's own (a Draft's where set)
                redraw_s += out.timings.get("verb_redraws_s", 0.0)
                for v in range(len(out.joints)):
                    joints = out.joints[v, : out.lengths[v]]
                    ok = physical.shows(joints, verb)
                    passed.append(ok)
                    lows.append(lowest_cm(joints))
                    floats.append(foot_float(joints, out.fps))
                    draw = int(out.draws[v]) if out.draws else 0
                    takes.append({"verb": verb, "wording": wording, "prompt": prompt, "model": maker.model_id,
                                  "seed": v, "pass": bool(ok),
                                  "draw": draw, "lowest_cm": round(lows[-1], 2), "float": round(floats[-1], 4)})
            rate = float(np.mean(passed)) if passed else float("nan")
            ratio = rate / real if real > 0 else float("nan")
            low = float(np.median(lows)) if lows else float("nan")
            flt = float(np.mean(floats)) if floats else float("nan")
            rows.append({"verb": verb, "wording": wording, "prompts": prompts, "takes": len(passed), "pass": rate,
                         "real": real, "real_windows": len(real_wins), "ratio": ratio, "lowest_cm": low,
                         "real_lowest_cm": real_low, "float": flt, "real_float": real_float})
            print(f"{verb:12} {wording:15} {len(passed):5d} {rate:6.2f} {real:6.2f} {ratio:6.2f} {low:7.1f} "
                  f"{real_low:5.1f} {flt:5.2f} {real_float:5.2f}", flush=True)
    redrawn = float(np.mean([t["draw"] > 0 for t in takes])) if takes else 0.0
    print(f"the {len(rows)} cells, each capped at 1: {capped_cells(rows):.2f}")
    print(f"{len(takes)} takes in {time.perf_counter() - start:.0f} s"
          + (f"; {redrawn:.2f} of them a later draw, {redraw_s:.0f} s spent drawing again" if redraws else ""))
    if args.json:
        args.json.write_text(json.dumps({"model": model, "draft": args.draft, "seeds": args.seeds,
                                         "seconds": args.seconds,
                                         "verb_redraws": redraws, "redrawn": redrawn, "redraw_s": redraw_s,
                                         "capped_cells": capped_cells(rows), "rows": rows, "takes": takes},
                                        indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
