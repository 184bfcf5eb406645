"""Quality badges on real and generated motions, per content (and the badges' real-data reference).

    python scripts/quality_table.py --data DIR [--model DIR] [--write-reference] [--json OUT.json]
        [--max-clips 0] [--batch 32] [--threads 1] [--real-only]

Real: every test-split clip of the prepared Bandai folder (joints from new_joints/, features from
new_joint_vecs/, at most 196 frames as the evaluator reads them): the physical badges of mld_core.eval.quality
and the evaluator similarity of every (clip, own caption) pair. ``--write-reference`` writes the similarity
percentiles of those pairs and the mean jerk of the clips to the evaluator folder's quality_reference.json
(the adherence percentile and jitter reference). Generated: one motion per test clip from its first caption at the
clip's own length (clamped to the model's range), seed 0, scored the same way. Prints a markdown table of the
mean badges per content, real vs generated. A measurement, not a test.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mld_core.eval import quality  # noqa: E402

KEYS = ("adherence", "skating", "float", "penetration_cm", "jitter")


def load_test(root: Path, max_clips: int, max_frames: int = 196) -> list[dict]:
    from mld_core.data.dataset import read_actions, read_captions, split_ids

    labels = (read_actions(root) or {}).get("clips", {})
    clips = []
    for cid in split_ids(root, "test"):
        caps = [c.text for c in read_captions(root / "texts" / f"{cid}.txt")]
        if not caps:
            continue
        joints = np.load(root / "new_joints" / f"{cid}.npy").astype(np.float32)[:max_frames]
        feats = np.load(root / "new_joint_vecs" / f"{cid}.npy").astype(np.float32)[:max_frames]
        clips.append({"id": cid, "content": labels.get(cid, "?"), "captions": caps, "joints": joints,
                      "features": feats[: len(joints)]})
    if max_clips:
        clips = clips[:: max(1, len(clips) // max_clips)][:max_clips]
    return clips


def real_reference(scorer: quality.QualityScorer, clips: list[dict]) -> dict:
    prompts = [c for clip in clips for c in clip["captions"]]
    feats = [clip["features"] for clip in clips for _ in clip["captions"]]
    sims = scorer.similarity(prompts, feats)
    jerks = [quality.mean_jerk(clip["joints"]) for clip in clips]
    return {"similarity_percentiles": np.percentile(sims, np.arange(101)).round(5).tolist(),
            "jerk_mean": float(np.mean(jerks)),
            "source": f"{len(clips)} test clips, {len(prompts)} (clip, own caption) pairs of the prepared Bandai data",
            "command": "python scripts/quality_table.py --data DIR --write-reference"}


def generate(pipe, clips: list[dict], batch: int) -> list[dict]:
    out_rows = []
    lo, hi = pipe.min_seconds, pipe.max_seconds
    for a in range(0, len(clips), batch):
        chunk = clips[a:a + batch]
        secs = [float(np.clip(len(c["joints"]) / pipe.fps, lo, hi)) for c in chunk]
        out = pipe([c["captions"][0] for c in chunk], seconds=secs, seed=0)
        for i, c in enumerate(chunk):
            n = int(out.lengths[i])
            out_rows.append({"content": c["content"], "prompt": c["captions"][0], "joints": out.joints[i, :n],
                             "features": out.features[i, :n]})
        print(f"generated {len(out_rows)}/{len(clips)}", file=sys.stderr)
    return out_rows


def per_content(rows: list[dict], badges: list) -> dict:
    table = defaultdict(list)
    for r, b in zip(rows, badges):
        table[r["content"]].append(b)
        table["all"].append(b)
    return {k: {"n": len(v), **{key: float(np.mean([getattr(b, key) for b in v])) for key in KEYS}}
            for k, v in table.items()}


def print_table(real: dict, gen: dict | None) -> None:
    head = "| content | n | " + " | ".join(f"{k} real" + (f" / gen" if gen else "") for k in KEYS) + " |"
    print(head)
    print("|---" * (2 + len(KEYS)) + "|")
    for c in sorted(real, key=lambda k: (k == "all", k)):
        r, g = real[c], (gen or {}).get(c)
        cells = []
        for k in KEYS:
            fmt = "{:.0f}" if k == "adherence" else "{:.2f}"
            cells.append(fmt.format(r[k]) + (" / " + fmt.format(g[k]) if g else ""))
        print(f"| {c} | {r['n']} | " + " | ".join(cells) + " |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--model", type=Path, default=None)
    ap.add_argument("--write-reference", action="store_true", help="write the evaluator folder's quality_reference.json")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--max-clips", type=int, default=0, help="use at most this many test clips (0: all)")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--real-only", action="store_true")
    args = ap.parse_args(argv)
    import torch

    from mld_core.eval.evaluator import DEFAULT_DIR
    from mld_core.fileio import atomic_write

    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    clips = load_test(args.data, args.max_clips)
    scorer = quality.QualityScorer.from_pretrained()
    reference = real_reference(scorer, clips)
    if args.write_reference:
        path = DEFAULT_DIR / quality.REFERENCE_NAME
        atomic_write(path, lambda tmp: Path(tmp).write_text(json.dumps(reference, indent=1) + "\n"))
        print(f"wrote {path}", file=sys.stderr)
    scorer.reference = reference
    rows = [{"content": c["content"], "prompt": c["captions"][0], "joints": c["joints"], "features": c["features"]}
            for c in clips]
    real = per_content(rows, scorer.score([r["prompt"] for r in rows], [r["joints"] for r in rows],
                                          [r["features"] for r in rows]))
    gen = None
    report = {"reference": reference, "real": real}
    if not args.real_only:
        from mld_core.pipeline import MLDPipeline

        pipe = MLDPipeline.from_pretrained(args.model)
        generated = generate(pipe, clips, args.batch)
        gen = per_content(generated, scorer.score([r["prompt"] for r in generated], [r["joints"] for r in generated],
                                                  [r["features"] for r in generated]))
        report.update(generated=gen, model_id=pipe.model_id)
    print_table(real, gen)
    print(f"\n{len(clips)} test clips; {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
