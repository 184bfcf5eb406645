"""Does a model do what a user notices first? Side, gesture and rare-content accuracy by physical checks.

    .venv/bin/python research/side_accuracy.py --model DIR --data DIR [--seeds 4] [--seconds 4] [--clip-length]
        [--prompts paraphrase|captions|both] [--contents raise-up-left-hand,...] [--max-clips 16]
        [--steps N] [--guidance G] [--batch 32] [--threads N] [--json OUT.json] [--real-only] [--vae-recon]
        [--first-seed 0] [--valid-references]

For the test-split clips of the sided contents (raise-up-*, wave-*, walk-turn-*, walk-left/right), the rare
ones (bow, kick, walk-back, dash, bye, ...) and walk/run, it generates motions with the pipeline from
  (a) the clips' own test captions ("captions": seed k uses caption k of each clip), and
  (b) hand-written paraphrases per content, never seen in training ("paraphrase"),
at ``--seconds`` (default 4) and/or at each clip's own length (``--clip-length``), ``--seeds`` seeds each,
and scores them with mld_core.eval.physical: the pass rate of the content's checks, the side accuracy (the
detected side equals the named side: raised wrist for hands, facing change for turns, travel direction for
walk-left/right) and the opposite-side rate. The same numbers for the real clips are the ceiling.
Contents with no test clip (kick, respond, slash) fall back to their clips in the other splits (marked '*').
``--real-only`` scores only the real clips (no model needed): the calibration of the checks.
``--vae-recon`` also encodes each chosen clip with the model's VAE and decodes it at its own length and at
``--seconds`` (rows "vae-recon@..."): does a latent keep its gesture when decoded to another length? It works
on a folder with only a VAE (then nothing is generated from text).
``--first-seed K`` runs seeds K..K+seeds-1: fresh takes of the same prompts (a confirmation on new samples).
``--valid-references`` leaves out the captions of test clips whose own capture fails the content's checks (an
elderly "run" slower than the run check's threshold): a faithful take of such a caption fails too.
Prints a table; ``--json`` writes every number, with each generated take's pass (0/1), skating ratio and key
(prompt, seconds, seed, variant) in generation order (the same order for every model), so
``research/compare_side_accuracy.py --z`` can pair the takes of two runs and count a repeated request once (a
mirrored clip whose caption names no side asks for the same take). Assert nothing: a measurement, not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mld_core.eval import physical  # noqa: E402
from mld_core.eval.quality import foot_skating_ratio  # noqa: E402
from mld_core.inputs import MAX_SIDE_REDRAWS, MAX_VERB_REDRAWS  # noqa: E402
from mld_core.motion.features import mirror_text  # noqa: E402

SIDED = ("raise-up-left-hand", "raise-up-right-hand", "raise-up-both-hands", "wave-left-hand", "wave-right-hand",
         "wave-both-hands", "walk-turn-left", "walk-turn-right")
RARE = ("bow", "kick", "walk-back", "walk-left", "walk-right", "dash", "bye", "byebye", "respond", "slash")
COMMON = ("walk", "run")
DEFAULT_CONTENTS = SIDED + RARE + COMMON

# Hand-written paraphrases, worded unlike the template captions of the prepared data. The right-side
# versions are the left ones mirrored (mirror_text), so both sides are asked in the same words.
_LEFT_PARAPHRASES = {
    "raise-up-left-hand": [
        "someone lifts their left arm above the head",
        "a person puts the left hand up high and brings it down",
        "the man reaches up towards the sky with his left hand",
        "a woman holds her left arm straight up in the air",
    ],
    "wave-left-hand": [
        "someone waves hello with their left hand",
        "a person greets a friend by waving the left hand",
        "the man lifts his left hand and waves it from side to side",
        "a woman waves at someone across the room with her left hand",
    ],
    "walk-turn-left": [
        "someone walks forward and turns to the left",
        "a person walks ahead, then changes direction to their left",
        "the man walks and takes a left turn",
        "a woman strolls forward and veers off to the left",
    ],
    "walk-left": [
        "someone walks forward diagonally to the left without turning",
        "a person walks ahead while drifting to their left",
    ],
}
PARAPHRASES = {
    **_LEFT_PARAPHRASES,
    **{physical.mirror_label(k): [mirror_text(p) for p in v] for k, v in _LEFT_PARAPHRASES.items()},
    "raise-up-both-hands": [
        "someone lifts both arms above the head",
        "a person throws both hands up in the air",
        "the man reaches up high with both arms and lowers them",
        "a woman holds both arms up over her head",
    ],
    "wave-both-hands": [
        "someone waves both hands above the head",
        "a person greets someone by waving both arms in the air",
        "the man raises both hands and waves them from side to side",
        "a woman waves both of her hands at a friend",
    ],
    "bow": [
        "someone bows politely",
        "a person bends forward at the waist to bow, then stands up straight",
        "the man takes a deep bow",
        "a woman bows her head and upper body to greet someone",
    ],
    "jump": [  # not a Bandai content (the CMU fine-tune of docs/library.md); not in DEFAULT_CONTENTS
        "a person jumps forward",
        "someone jumps up and down in place",
        "the man takes a big jump",
        "a woman hops forward with both feet",
    ],
    "kick": [
        "someone kicks high with the right leg",
        "a person does a high kick",
        "the man kicks forward as in martial arts",
    ],
    "walk-back": [
        "someone walks backwards",
        "a person steps backward several times while facing forward",
        "the man backs up slowly",
        "a woman retreats by walking backwards",
    ],
    "dash": [
        "someone sprints ahead as fast as they can",
        "a person dashes forward at top speed",
    ],
    "bye": [
        "someone says goodbye by waving one hand",
        "a person waves farewell with the right hand",
    ],
    "byebye": [
        "someone says goodbye by waving both hands",
        "a person waves farewell with both arms",
    ],
    "respond": [
        "someone raises a hand high to answer a question",
        "a person puts the left hand up to reply",
    ],
    "slash": [
        "someone swings a sword down from above the head with both hands",
        "a person lifts an imaginary blade overhead and cuts downward",
    ],
    "walk": [
        "someone walks forward",
        "a person strolls straight ahead",
        "the man walks at a normal pace",
        "a woman takes a walk in a straight line",
    ],
    "run": [
        "someone runs forward",
        "a person jogs straight ahead",
        "the man runs at a steady pace",
        "a woman runs in a straight line",
    ],
}


# ---- data --------------------------------------------------------------------------------------------------


def _ids(root: Path, split: str) -> list[str]:
    path = root / f"{split}.txt"
    return [s.strip() for s in path.read_text(encoding="utf-8").splitlines() if s.strip()] if path.exists() else []


def _joints_of(root: Path, cid: str) -> np.ndarray:
    path = root / "new_joints" / f"{cid}.npy"
    if path.exists():
        return np.load(path).astype(np.float32)
    from mld_core.motion.features import features_to_joints

    return np.asarray(features_to_joints(np.load(root / "new_joint_vecs" / f"{cid}.npy").astype(np.float32)))


def load_clips(root: Path, contents: list[str], fps: float = 20.0) -> dict[str, list[dict]]:
    """{content: [{"id", "joints", "captions", "seconds", "split"}]} from the test split, or from the other
    splits for a content with no test clip."""
    from mld_core.data.dataset import read_actions, read_captions

    actions = read_actions(root)
    if actions is None:
        raise SystemExit(f"{root} has no actions.json: the content labels are needed")
    labels = actions["clips"]
    test = _ids(root, "test")
    others = [i for s in ("train", "val") for i in _ids(root, s)]
    out: dict[str, list[dict]] = {}
    for content in contents:
        split, ids = "test", [i for i in test if labels.get(i) == content]
        if not ids:
            split, ids = "train/val", [i for i in others if labels.get(i) == content]
        clips = []
        for cid in sorted(ids):
            try:
                joints = _joints_of(root, cid)
                caps = [c.text for c in read_captions(root / "texts" / f"{cid}.txt")]
            except OSError as exc:
                print(f"skipping {cid}: {exc}", file=sys.stderr)
                continue
            clips.append({"id": cid, "joints": joints, "captions": caps or [content.replace("-", " ")],
                          "seconds": len(joints) / fps, "split": split,
                          "features": root / "new_joint_vecs" / f"{cid}.npy"})
        out[content] = clips
    return out


def _spread(items: list, n: int) -> list:
    """Up to n items evenly spaced over the list (deterministic)."""
    if n <= 0 or len(items) <= n:
        return list(items)
    return [items[k] for k in np.linspace(0, len(items) - 1, n).round().astype(int)]


# ---- scoring -----------------------------------------------------------------------------------------------


class Tally:
    def __init__(self):
        self.n = 0
        self.passed = 0
        self.sided = 0
        self.side_ok = 0
        self.opposite = 0
        self.skating = 0.0
        self.failed = defaultdict(int)
        self.take_passed: list[int] = []  # per take, in generation order: what a paired comparison of two runs needs
        self.take_skating: list[float] = []
        self.take_keys: list[str] = []  # what was asked (prompt | seconds | seed | variant): equal keys, equal takes

    def add(self, joints: np.ndarray, content: str, fps: float, key: str = "") -> None:
        skating = float(foot_skating_ratio(joints, fps))
        self.skating += skating
        result = physical.classify(joints, fps)
        failed = physical.failed_checks(joints, content, result, fps)
        self.n += 1
        self.passed += not failed
        self.take_passed.append(int(not failed))
        self.take_skating.append(round(skating, 5))
        self.take_keys.append(key)
        for name in failed:
            self.failed[name] += 1
        side = physical.side_of(content)
        if side is not None:
            got = physical.detected_side(result, content)
            self.sided += 1
            self.side_ok += got == side
            self.opposite += got == ("right" if side == "left" else "left")

    def merge(self, other: "Tally") -> None:
        self.n += other.n
        self.passed += other.passed
        self.sided += other.sided
        self.side_ok += other.side_ok
        self.opposite += other.opposite
        self.skating += other.skating
        self.take_passed += other.take_passed
        self.take_skating += other.take_skating
        self.take_keys += other.take_keys
        for k, v in other.failed.items():
            self.failed[k] += v

    def as_dict(self, takes: bool = False) -> dict:
        """The content's numbers; ``takes`` adds each take's pass (0/1) and skating ratio, in generation order."""
        out = {
            "n": self.n,
            "pass_rate": self.passed / self.n if self.n else None,
            "side_n": self.sided,
            "side_accuracy": self.side_ok / self.sided if self.sided else None,
            "opposite_side": self.opposite / self.sided if self.sided else None,
            "skating": self.skating / self.n if self.n else None,
            "failed_checks": dict(self.failed),
        }
        if takes:
            out["takes"] = {"passed": list(self.take_passed), "skating": list(self.take_skating),
                            "keys": list(self.take_keys)}
        return out


# ---- generation --------------------------------------------------------------------------------------------


def failing_references(clips: dict, fps: float) -> dict[str, list[str]]:
    """{content: ids of its clips whose own motion capture fails the content's checks}: a caption of such a clip
    asks for a motion the checks do not call that content (e.g. an elderly "run" slower than the run check's
    threshold), so a faithful take fails too."""
    out = {}
    for content, cl in clips.items():
        out[content] = [c["id"] for c in cl
                        if physical.failed_checks(c["joints"], content, physical.classify(c["joints"], fps), fps)]
    return out


def build_requests(clips: dict, modes: list[str], lengths: list, seeds: int, max_clips: int,
                   lo: float, hi: float, skip_ids: frozenset = frozenset(), first_seed: int = 0) -> list[dict]:
    """One request per (content, prompt source, length mode, prompt); each is generated with ``seeds`` seeds from
    ``first_seed`` on (another ``first_seed`` gives fresh takes of the same prompts). Caption requests skip the clips
    in ``skip_ids`` (after choosing ``max_clips``, so the other takes stay the same)."""
    reqs = []
    for content, cl in clips.items():
        chosen = [c for c in _spread(cl, max_clips) if c["id"] not in skip_ids]
        for length in lengths:
            if "captions" in modes:
                for c in chosen:
                    secs = c["seconds"] if length == "clip" else float(length)
                    # one request per seed so that seed k uses caption k of the clip
                    for k in range(first_seed, first_seed + seeds):
                        reqs.append({"content": content, "source": "captions", "length": length,
                                     "prompt": c["captions"][k % len(c["captions"])],
                                     "seconds": float(np.clip(secs, lo, hi)), "seed": k, "variants": 1})
            if "paraphrase" in modes and content in PARAPHRASES:
                own = [c["seconds"] for c in cl] or [4.0]
                for p, prompt in enumerate(PARAPHRASES[content]):
                    secs = own[p % len(own)] if length == "clip" else float(length)
                    reqs.append({"content": content, "source": "paraphrase", "length": length, "prompt": prompt,
                                 "seconds": float(np.clip(secs, lo, hi)), "seed": first_seed, "variants": seeds})
    return reqs


def generate(pipe, reqs: list[dict], batch: int, steps: int | None, guidance: float | None, fps: float,
             tallies: dict, repair: bool = True, per_prompt: dict | None = None,
             side_redraws: int | None = None, redraws: dict | None = None, verb_redraws: int | None = None) -> float:
    """Run the requests through the pipeline in batches (grouped by seed/variants) and tally the results, per
    (source, length) and content; paraphrases also per (length, content, prompt) into ``per_prompt``; into
    ``redraws``: under "kept", per "source@length" and content, how many takes are a later draw of their seed
    (the pipeline's side and verb redraws); under "seconds", the time spent drawing again."""
    from tqdm import tqdm

    cond = pipe.denoiser.config.cond if pipe.denoiser is not None else "none"
    groups = defaultdict(list)
    for r in reqs:
        groups[(r["seed"], r["variants"])].append(r)
    total = sum(r["variants"] for r in reqs)
    t0 = time.perf_counter()
    with tqdm(total=total, desc="generating", unit="motion") as bar:
        for (seed, variants), rs in groups.items():
            per = max(1, batch // variants)
            for a in range(0, len(rs), per):
                chunk = rs[a:a + per]
                kwargs = dict(seconds=[r["seconds"] for r in chunk], seed=seed, num_variants=variants,
                              num_inference_steps=steps, guidance_scale=guidance, repair=repair,
                              side_redraws=side_redraws, verb_redraws=verb_redraws)
                if cond == "action":
                    out = pipe([r["content"] for r in chunk], actions=[r["content"] for r in chunk], **kwargs)
                else:
                    out = pipe([r["prompt"] for r in chunk], **kwargs)
                for row in range(len(out.lengths)):
                    r = chunk[row // variants]
                    joints = out.joints[row, : int(out.lengths[row])]
                    key = f"{r['prompt']}|{r['seconds']:.3f}|{seed}|{row % variants}"
                    tallies[(r["source"], r["length"])][r["content"]].add(joints, r["content"], fps, key)
                    if per_prompt is not None and r["source"] == "paraphrase":
                        per_prompt[(r["length"], r["content"], r["prompt"])].add(joints, r["content"], fps)
                    if redraws is not None:
                        length = "clip" if r["length"] == "clip" else f"{r['length']:g}s"
                        where = f"{r['source']}@{length}"
                        kept = redraws.setdefault("kept", {}).setdefault(where, {}).setdefault(
                            r["content"], {"takes": 0, "redrawn": 0})
                        kept["takes"] += 1
                        kept["redrawn"] += int(bool(out.draws and out.draws[row]))
                if redraws is not None:
                    spent = sum(out.timings.get(k, 0.0) for k in ("side_redraws_s", "verb_redraws_s"))
                    redraws["seconds"] = redraws.get("seconds", 0.0) + spent
                bar.update(len(out.lengths))
    return time.perf_counter() - t0


def vae_reconstruct(pipe, clips: dict, lengths: list, max_clips: int, batch: int, fps: float,
                    tallies: dict) -> float:
    """Encode each chosen clip (its first max_frames frames) to the VAE mean and decode it at each length."""
    import torch

    from tqdm import tqdm

    max_frames = pipe.config.vae.max_frames
    items = [(content, c) for content, cl in clips.items() for c in _spread(cl, max_clips) if c["features"].exists()]
    t0 = time.perf_counter()
    with torch.inference_mode(), tqdm(total=len(items) * len(lengths), desc="vae recon", unit="motion") as bar:
        for a in range(0, len(items), batch):
            chunk = items[a:a + batch]
            feats = [np.load(c["features"]).astype(np.float32)[:max_frames] for _, c in chunk]
            z, n = pipe.features_to_latents(feats)  # (B, n, d) diffusion-space latents, (B,) lengths
            for length in lengths:
                if length == "clip":
                    out_n = n
                else:
                    secs = float(np.clip(length, pipe.min_seconds, pipe.max_seconds))
                    out_n = torch.full_like(n, pipe.frames_for(secs))
                out = pipe.latents_to_features(z, out_n.to(pipe.device))
                joints = pipe.joints_from_features(out, out_n.tolist())
                for i, (content, clip) in enumerate(chunk):
                    tallies[("vae-recon", length)][content].add(joints[i, : int(out_n[i])], content, fps,
                                                                f"{clip['id']}|{length}")
                bar.update(len(chunk))
    return time.perf_counter() - t0


# ---- report ------------------------------------------------------------------------------------------------


def _fmt(x, width: int = 4) -> str:
    return "-".rjust(width) if x is None else f"{x:{width}.2f}"


def summarise(per_content: dict[str, "Tally"], contents: list[str]) -> dict:
    """Overall numbers: mean pass rate over contents (macro), pooled pass rate and pooled side accuracy."""
    groups = {"sided": [c for c in contents if c in SIDED], "rare": [c for c in contents if c in RARE],
              "all": list(contents)}
    out = {}
    for name, cs in groups.items():
        pooled = Tally()
        rates = []
        for c in cs:
            t = per_content.get(c)
            if t is None or t.n == 0:
                continue
            pooled.merge(t)
            rates.append(t.passed / t.n)
        d = pooled.as_dict()
        d["mean_pass_rate"] = float(np.mean(rates)) if rates else None
        d["contents"] = len(rates)
        out[name] = d
    return out


def print_table(report: dict, contents: list[str]) -> None:
    cols = [k for k in report["generated"]]
    head = f"{'content':22s} {'real n':>6s} {'pass':>4s} {'side':>4s} {'skate':>5s}"
    for k in cols:
        head += f" | {k:>27s}"
    print()
    if cols:
        print(" " * 44 + "".join(f" | {'n pass side  opp skate':>27s}" for _ in cols))
    print(head)
    print("-" * len(head))
    real = report["real"]["contents"]
    for c in contents:
        r = real.get(c)
        if r is None:
            continue
        star = "*" if report["real"]["splits"].get(c) != "test" else " "
        line = f"{c:21s}{star} {r['n']:6d} {_fmt(r['pass_rate'])} {_fmt(r['side_accuracy'])} {_fmt(r['skating'], 5)}"
        for k in cols:
            g = report["generated"][k]["contents"].get(c)
            if g is None or g["n"] == 0:
                line += f" | {'':>27s}"
            else:
                line += f" | {g['n']:6d} {_fmt(g['pass_rate'])} {_fmt(g['side_accuracy'])} {_fmt(g['opposite_side'])}" \
                        f" {_fmt(g['skating'], 5)}"
        print(line)
    print("-" * len(head))
    for name in ("sided", "rare", "all"):
        r = report["real"]["overall"][name]
        line = f"{'mean/pooled: ' + name:22s} {r['n']:6d} {_fmt(r['mean_pass_rate'])} {_fmt(r['side_accuracy'])} " \
               f"{_fmt(r['skating'], 5)}"
        for k in cols:
            g = report["generated"][k]["overall"][name]
            line += f" | {g['n']:6d} {_fmt(g['mean_pass_rate'])} {_fmt(g['side_accuracy'])} {_fmt(g['opposite_side'])}" \
                    f" {_fmt(g['skating'], 5)}"
        print(line)
    print("\npass = the content's physical checks pass (mean over contents in the overall rows); side = the named side "
          "was used (pooled); opp = the opposite side alone was used; skate = mean foot skating ratio "
          "(mld_core.eval.quality); * = no test clip, clips from train/val.")


def print_prompt_table(rows: list[dict]) -> None:
    """One line per paraphrase: which wordings the model follows (a content's pass rate hides them)."""
    print(f"\n{'content':22s} {'length':>6s} {'n':>4s} {'pass':>4s} {'side':>4s}  paraphrase")
    for r in rows:
        print(f"{r['content']:22s} {r['length']:>6s} {r['n']:4d} {_fmt(r['pass_rate'])} {_fmt(r['side_accuracy'])}  "
              f"{r['prompt']}")


def _write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=1)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=None, help="model folder (default: the bundled default model)")
    ap.add_argument("--data", required=True, help="HumanML3D-format folder with actions.json (Bandai Namco)")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds run from this one (a fresh sample: e.g. 16)")
    ap.add_argument("--seconds", type=float, default=None, help="generated length (default 4 unless --clip-length)")
    ap.add_argument("--clip-length", action="store_true", help="also/instead generate at each clip's own length")
    ap.add_argument("--prompts", choices=("paraphrase", "captions", "both"), default="both")
    ap.add_argument("--contents", default=",".join(DEFAULT_CONTENTS), help="comma-separated content labels")
    ap.add_argument("--max-clips", type=int, default=16, help="test clips per content used for captions (0 = all)")
    ap.add_argument("--steps", type=int, default=None, help="DDIM steps (default: the model's)")
    ap.add_argument("--guidance", type=float, default=None, help="guidance scale (default: the model's)")
    ap.add_argument("--batch", type=int, default=32, help="motions per pipeline call")
    ap.add_argument("--threads", type=int, default=None, help="torch threads")
    ap.add_argument("--json", type=Path, default=None, help="write every number here")
    ap.add_argument("--real-only", action="store_true", help="score only the real clips (no model)")
    ap.add_argument("--vae-recon", action="store_true",
                    help="also score VAE reconstructions at the clip's own length and at --seconds")
    ap.add_argument("--per-prompt", action="store_true", help="also print the pass rate of each paraphrase")
    ap.add_argument("--valid-references", action="store_true",
                    help="leave out the captions of test clips whose own motion fails the content's checks")
    ap.add_argument("--no-repair", action="store_true", help="generate without the model's repairs (planted feet, "
                    "one skeleton): the ablation")
    ap.add_argument("--side-redraws", type=int, default=None, metavar="N",
                    help="draws of a take beyond its first when it misses the side its prompt names (default: the "
                         "model's config side_redraws; 0: every take is its seed's first draw, the model alone)")
    ap.add_argument("--verb-redraws", type=int, default=None, metavar="N",
                    help="draws of a take beyond its first when it does not show the checked verb its prompt names "
                         "(default: the model's config verb_redraws; 0: the model alone)")
    args = ap.parse_args(argv)
    if args.side_redraws is not None and not 0 <= args.side_redraws <= MAX_SIDE_REDRAWS:
        ap.error(f"--side-redraws must be between 0 and {MAX_SIDE_REDRAWS}, got {args.side_redraws}")
    if args.verb_redraws is not None and not 0 <= args.verb_redraws <= MAX_VERB_REDRAWS:
        ap.error(f"--verb-redraws must be between 0 and {MAX_VERB_REDRAWS}, got {args.verb_redraws}")

    contents = [c.strip() for c in args.contents.split(",") if c.strip()]
    unknown = [c for c in contents if physical.expected_for(c) is None]
    if unknown:
        ap.error(f"no physical check for {', '.join(unknown)}; checked contents: {', '.join(physical.CHECKED_LABELS)}")
    if args.seeds < 1:
        ap.error("--seeds must be >= 1")
    if args.first_seed < 0:
        ap.error("--first-seed must be >= 0")
    root = Path(args.data)
    if not root.is_dir():
        ap.error(f"data folder {root} does not exist")
    fps = 20.0
    clips = load_clips(root, contents, fps)
    contents = [c for c in contents if clips[c] or c in PARAPHRASES]

    real = {}
    for c in contents:
        t = Tally()
        for clip in clips[c]:
            t.add(clip["joints"], c, fps)
        real[c] = t
    report = {
        "data": str(root),
        "real": {"contents": {c: t.as_dict() for c, t in real.items() if t.n},
                 "splits": {c: (clips[c][0]["split"] if clips[c] else None) for c in contents},
                 "overall": summarise(real, contents)},
        "generated": {},
    }

    if not args.real_only:
        import torch

        from mld_core.checkpoint import CheckpointError
        from mld_core.pipeline import MLDPipeline

        if args.threads:
            torch.set_num_threads(args.threads)
        t0 = time.perf_counter()
        try:
            pipe = MLDPipeline.from_pretrained(args.model)
        except (CheckpointError, OSError) as exc:
            print(f"side_accuracy.py: cannot load the model: {exc}", file=sys.stderr)
            return 2
        print(f"loaded {pipe.model_id} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        lengths = []
        if args.seconds is not None or not args.clip_length:
            lengths.append(float(args.seconds if args.seconds is not None else 4.0))
        if args.clip_length:
            lengths.append("clip")
        cond = pipe.denoiser.config.cond if pipe.denoiser is not None else None
        if cond is None and not args.vae_recon:
            print(f"side_accuracy.py: {args.model} holds only a VAE: use --vae-recon (or --real-only)", file=sys.stderr)
            return 2
        tallies = defaultdict(lambda: defaultdict(Tally))
        per_prompt = defaultdict(Tally)
        seconds = 0.0
        if args.vae_recon:
            recon_lengths = list(dict.fromkeys(["clip", *lengths]))
            seconds += vae_reconstruct(pipe, clips, recon_lengths, args.max_clips, args.batch, fps, tallies)
        if cond is not None:
            modes = ["paraphrase", "captions"] if args.prompts == "both" else [args.prompts]
            if cond == "action":
                modes = ["captions"]  # the prompt text is not used: one "action" row per clip and seed
            skip = set()
            if args.valid_references:
                failing = failing_references(clips, fps)
                report["failing_references"] = {c: ids for c, ids in failing.items() if ids}
                skip = {i for ids in failing.values() for i in ids}
                for c, ids in report["failing_references"].items():
                    print(f"{c}: leaving out the captions of {len(ids)} clip(s) whose own capture fails its checks: "
                          f"{', '.join(ids)}", file=sys.stderr)
            reqs = build_requests(clips, modes, lengths, args.seeds, args.max_clips, pipe.min_seconds,
                                  pipe.max_seconds, frozenset(skip), args.first_seed)
            seconds += generate(pipe, reqs, args.batch, args.steps, args.guidance, fps, tallies, not args.no_repair,
                                per_prompt, args.side_redraws, report.setdefault("redraws", {}), args.verb_redraws)
        n = sum(t.n for per in tallies.values() for t in per.values())
        print(f"generated and scored {n} motions in {seconds:.1f} s ({seconds / max(n, 1):.3f} s each)",
              file=sys.stderr)
        for (source, length), per in sorted(tallies.items(), key=lambda kv: (kv[0][0], str(kv[0][1]))):
            name = f"{'action' if cond == 'action' and source != 'vae-recon' else source}@" \
                   f"{'clip' if length == 'clip' else f'{length:g}s'}"
            report["generated"][name] = {"contents": {c: t.as_dict(takes=True) for c, t in per.items()},
                                         "overall": summarise(per, contents)}
        order = {c: k for k, c in enumerate(contents)}
        report["paraphrases"] = [
            {"content": content, "length": "clip" if length == "clip" else f"{length:g}s", "prompt": prompt,
             **t.as_dict()}
            for (length, content, prompt), t in sorted(per_prompt.items(),
                                                       key=lambda kv: (order.get(kv[0][1], 0), str(kv[0][0])))]
        report.update(model=str(args.model or "default"), model_id=pipe.model_id, seeds=args.seeds,
                      first_seed=args.first_seed,
                      repair=not args.no_repair,
                      side_redraws=pipe.config.side_redraws if args.side_redraws is None else args.side_redraws,
                      verb_redraws=pipe.config.verb_redraws if args.verb_redraws is None else args.verb_redraws,
                      steps=args.steps, guidance=args.guidance, max_clips=args.max_clips, generation_s=seconds)

    print_table(report, contents)
    if args.per_prompt and report.get("paraphrases"):
        print_prompt_table(report["paraphrases"])
    if args.json is not None:
        _write_json(args.json, report)
        print(f"wrote {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
