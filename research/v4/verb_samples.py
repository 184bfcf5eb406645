"""A model's own takes of the checked verbs, kept only where they show them, as a prepared folder to train on.

    python research/v4/verb_samples.py --data data/bandai_cmu --model mld_core/weights/v4_preview --out data/verb_samples \
        [--per-verb 96] [--minutes 60] [--batch 8] [--threads 1]

For each checked verb (mld_core/data/verbs.py), the train clips of ``--data`` labelled with it whose captions name it
are taken in turn, each caption naming it with its own seed, until ``--per-verb`` takes of that verb are kept: the
model (its verb guidance and verb redraws included) makes the caption at the clip's length, and a take is kept when
it shows every verb the caption names, and written with its lowest joint on the floor as every prepared clip has it
(``put_on_floor``: a model's takes may sink into the floor or hover above it). The captions ``scripts/vocabulary.py``
measures (its caption wording on the CMU folder, its commands and its user prompts) are never used. The folder is what ``data prepare`` writes (features,
joints, captions, train.txt, actions.json with the clip's label), so ``data merge`` joins it to the training data: a
denoiser fine-tuned on the merge learns from the takes of its own that show what was asked (rejection-sampled
fine-tuning). A run stops after ``--minutes`` and a second run on the same ``--out`` goes on where it stopped.
A measurement tool, not a test: it asserts nothing.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from mld_core.data import terms  # noqa: E402
from mld_core.data.dataset import read_actions, read_captions, split_ids  # noqa: E402
from mld_core.data.verbs import VERBS, verbs_in  # noqa: E402

PROGRESS = "progress.jsonl"  # one line per take tried: id, verb, caption, seed, kept


def plain(text: str) -> str:
    """A caption as compared with the measured prompts: lower case, no end punctuation or spaces around."""
    return text.strip().lower().rstrip(".!").strip()


def measured_prompts(cmu: Path | None) -> set[str]:
    """The prompts scripts/vocabulary.py scores (:func:`plain`): never trained on."""
    import vocabulary

    prompts = {plain(p) for table in (vocabulary.COMMANDS, vocabulary.USER) for p in table.values()}
    if cmu is not None:
        from mld_core.data.cmu_joints import whole_trial_windows

        whole = set(whole_trial_windows(cmu))
        for verb in VERBS:
            wordings, _ = vocabulary.prompts_for(cmu, verb, whole, 2)
            prompts |= {plain(p) for ps in wordings.values() for p in ps}
    return prompts


def candidates(data: Path, excluded: set[str]) -> dict[str, list[tuple[str, str, int]]]:
    """{verb: [(clip id, caption, frames), ...]}: the train clips labelled with a checked verb (mirrored copies left
    out), one entry per caption of theirs that names that verb (a caption a clip lists twice, once), in id order."""
    labels = (read_actions(data) or {}).get("clips", {})
    out: dict[str, list] = {verb: [] for verb in VERBS}
    for cid in sorted(split_ids(data, "train")):
        verb = labels.get(cid)
        if verb not in out or cid.startswith("M"):
            continue
        frames = int(np.load(data / "new_joint_vecs" / f"{cid}.npy", mmap_mode="r").shape[0])
        texts = dict.fromkeys(cap.text for cap in read_captions(data / "texts" / f"{cid}.txt"))
        out[verb] += [(cid, text, frames) for text in texts if verb in verbs_in(text) and plain(text) not in excluded]
    return out


def read_progress(out: Path) -> list[dict]:
    path = out / PROGRESS
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def plan(cands: dict, done: list[dict], per_verb: int) -> list[dict]:
    """The takes not tried yet, the verbs in turn: each verb's captions round after round (round r with seed r), at
    most 4 x ``per_verb`` tries per verb in all."""
    tried = {(d["id"], d["caption"], d["seed"]) for d in done}
    todo = {}
    for verb, items in cands.items():
        rounds = 4 * per_verb // len(items) + 1 if items else 0
        mine = [{"id": c, "caption": t, "frames": f, "seed": r, "verb": verb}
                for r in range(rounds) for c, t, f in items]
        todo[verb] = [m for m in mine[: 4 * per_verb] if (m["id"], m["caption"], m["seed"]) not in tried]
    order = []
    for k in range(max(map(len, todo.values()), default=0)):
        order += [todo[verb][k] for verb in VERBS if k < len(todo[verb])]
    return order


def start_folder(data: Path, out: Path, model_terms: list[dict]) -> None:
    """The prepared folder's fixed parts: the statistics and licence of ``data``, empty splits, a README, and
    ``terms.json``: the terms of ``data`` and of the model that makes the takes (``model_terms``)."""
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    (out / PROGRESS).touch()  # marks the folder as this script's from the start
    for name in ("Mean.npy", "Std.npy", "LICENSE"):
        if (data / name).is_file() and not (out / name).is_file():
            shutil.copy2(data / name, out / name)
    terms.write(out, terms.union(terms.of_folder(data), model_terms))
    (out / "README.md").write_text(
        "Takes made by a text-to-motion model from train captions that name a checked verb, kept where they show "
        "every verb the caption names (research/v4/verb_samples.py). Synthetic motion: its licence is that of the "
        f"model that made it and of the data that model was trained on ({data.name}/LICENSE).\n", encoding="utf-8")


def write_take(out: Path, sid: str, features: np.ndarray, caption: str) -> None:
    """One take as prepared data: its features moved as a whole so the lowest joint is on the floor, and the joints
    they give."""
    from mld_core.motion.features import features_to_joints
    from mld_core.take_fixes.repair import put_on_floor

    features = put_on_floor(features).astype(np.float32)
    np.save(out / "new_joint_vecs" / f"{sid}.npy", features)
    np.save(out / "new_joints" / f"{sid}.npy", features_to_joints(features))
    (out / "texts" / f"{sid}.txt").write_text(f"{caption}##0.0#0.0\n", encoding="utf-8")


def write_index(out: Path, done: list[dict], classes: list[str]) -> None:
    """train.txt / all.txt (every kept take), empty val.txt and test.txt, actions.json (each take's verb)."""
    kept = list({take_id(d): d for d in done if d["kept"]}.values())  # a take tried twice (an older run's), once
    ids = [take_id(d) for d in kept]
    for split, rows in (("train", ids), ("all", ids), ("val", []), ("test", [])):
        (out / f"{split}.txt").write_text("".join(f"{i}\n" for i in rows), encoding="utf-8")
    actions = {"classes": classes, "clips": {take_id(d): d["verb"] for d in kept}}
    (out / "actions.json").write_text(json.dumps(actions, indent=1) + "\n", encoding="utf-8")


def take_id(d: dict) -> str:
    return f"S{d['id']}_{d['caption_index']}_{d['seed']}"


def run(args) -> int:
    import torch

    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(args.threads)
    pipe = MLDPipeline.from_pretrained(args.model)
    classes = (read_actions(args.data) or {}).get("classes", list(VERBS))
    cands = candidates(args.data, measured_prompts(args.cmu))
    args.out.mkdir(parents=True, exist_ok=True)
    lock = open(args.out / ".lock", "w")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # released when this process ends, however it ends
    except BlockingIOError:
        print(f"error: another run is writing {args.out}; wait for it or name another --out", file=sys.stderr)
        return 2
    start_folder(args.data, args.out, terms.of_model(pipe.config))
    done = read_progress(args.out)
    todo = plan(cands, done, args.per_verb)
    index = {(c, t): k for items in cands.values() for k, (c, t, _) in enumerate(items)}
    print(f"{sum(map(len, cands.values()))} captions; {len(done)} takes tried before, {len(todo)} planned",
          flush=True)
    kept = {v: sum(d["kept"] for d in done if d["verb"] == v) for v in VERBS}
    t0 = time.perf_counter()
    with open(args.out / PROGRESS, "a", encoding="utf-8") as log:
        while todo and (time.perf_counter() - t0) / 60 < args.minutes:
            todo = [b for b in todo if kept[b["verb"]] < args.per_verb]  # a verb with enough takes stops
            batch, todo = todo[: args.batch], todo[args.batch :]
            if not batch:
                break
            frames = [max(pipe.config.min_frames, min(b["frames"], pipe.config.max_frames)) for b in batch]
            out = pipe([b["caption"] for b in batch], [f / pipe.config.fps for f in frames],
                       seed=[b["seed"] for b in batch], verb_redraws=args.verb_redraws)
            for r, b in enumerate(batch):
                n = int(out.lengths[r])
                reason = out.redrawn_for[r] if out.redrawn_for else ""
                record = {"id": b["id"], "caption": b["caption"], "caption_index": index[(b["id"], b["caption"])],
                          "seed": b["seed"], "verb": b["verb"], "kept": not reason.endswith("missed"),
                          "draw": int(out.draws[r]) if out.draws else 0}
                if record["kept"]:
                    write_take(args.out, take_id(record), out.features[r, :n], b["caption"])
                log.write(json.dumps(record) + "\n")
                done.append(record)
                kept[b["verb"]] += record["kept"]
            log.flush()
            write_index(args.out, done, classes)
    write_index(args.out, done, classes)
    for verb in VERBS:
        mine = [d for d in done if d["verb"] == verb]
        print(f"{verb:12} kept {sum(d['kept'] for d in mine):4d} of {len(mine):4d} tried", flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, type=Path, help="the training folder (its train clips' captions)")
    ap.add_argument("--cmu", type=Path, default=None,
                    help="the CMU folder scripts/vocabulary.py measures on: its caption prompts are left out too")
    ap.add_argument("--model", required=True)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--per-verb", type=int, default=96)
    ap.add_argument("--verb-redraws", type=int, default=2)
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    error = problem(args)
    if error is None:
        from mld_core.checkpoint import CheckpointError

        try:
            return run(args)
        except (CheckpointError, OSError, ValueError) as exc:  # a model folder that does not load, a full disk
            error = str(exc)
    print(f"error: {error}", file=sys.stderr)
    return 2


def problem(args) -> str | None:
    """What is wrong with the arguments, in one line (None: nothing). ``--out`` is a new folder or an earlier run's,
    never the data or inside it, so no run writes over a prepared folder."""
    if not (args.data / "train.txt").is_file():
        return f"{args.data} is not a prepared folder (no train.txt)"
    for name, value, lo, hi in (("--per-verb", args.per_verb, 1, 100_000), ("--batch", args.batch, 1, 256),
                                ("--threads", args.threads, 1, 1024), ("--verb-redraws", args.verb_redraws, 0, 8)):
        if not lo <= value <= hi:
            return f"{name} must be between {lo} and {hi}, got {value}"
    if not (math.isfinite(args.minutes) and args.minutes > 0):
        return f"--minutes must be a positive number, got {args.minutes}"
    out = args.out.resolve()
    for name, folder in (("--data", args.data), ("--cmu", args.cmu)):
        if folder is not None and (out == folder.resolve() or folder.resolve() in out.parents
                                   or out in folder.resolve().parents):
            return f"--out {args.out} is, holds or sits in {name} {folder}; name a folder of its own"
    if args.out.exists() and not args.out.is_dir():
        return f"--out {args.out} is a file; name a folder"
    if args.out.is_dir() and any(args.out.iterdir()) and not (args.out / PROGRESS).is_file():
        return f"--out {args.out} holds something that is not an earlier run of this script; name a new folder"
    return None


if __name__ == "__main__":
    raise SystemExit(main())
