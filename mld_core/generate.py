"""``python -m mld_core generate``: prompts in, motions out (.npz, optional .bvh per variant)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from mld_core import inputs
from mld_core.fileio import OutputSet
from mld_core.inputs import InputError, PromptLine
from mld_core.shards import shard_lines



def read_prompt_file(path: Path) -> list[PromptLine]:
    """The prompt file's lines (mld_core.inputs: the same format and messages as the batch)."""
    return inputs.read_prompt_file(path)


def write_npz(path: Path, out, records: list | None = None, outputs: OutputSet | None = None,
              shard: dict | None = None, lines: list | None = None) -> None:
    """``records``: per row a JSON-able dict (coverage, badges), stored as one JSON string ``quality``. ``shard``
    (a shard's record, mld_core.shards) and ``lines`` (each row's prompt line, 0-based) for a sharded run. Staged in
    ``outputs`` when given (committed with the other outputs), else written on its own."""
    extra = {"quality": np.array(json.dumps(records))} if records and any(records) else {}
    if shard is not None:
        extra.update(shard=np.array(json.dumps(shard)), lines=np.asarray(lines, np.int64))

    def save(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, features=out.features.astype(np.float32), joints=out.joints.astype(np.float32),
                     lengths=np.asarray(out.lengths, np.int64), fps=np.int64(out.fps), prompts=np.array(out.prompts),
                     seeds=np.asarray(out.seeds, np.int64), model_id=np.array(out.model_id),
                     draws=np.asarray(out.draws or [0] * len(out.lengths), np.int64), **extra)

    if outputs is not None:
        outputs.stage(path, save)
        return
    with OutputSet(overwrite=True) as single:
        single.stage(path, save)


def bvh_paths(path: Path, n: int, rows: list[int] | None = None) -> list[Path]:
    """The BVH file of each of ``n`` rows (``rows``: a shard's rows, numbered as in the whole run of ``n``)."""
    path = Path(path)
    if n == 1:
        return [path]
    return [path.with_name(f"{path.stem}_{i:03d}{path.suffix or '.bvh'}") for i in (range(n) if rows is None else rows)]


def write_bvhs(path: Path, out, fps: int, outputs: OutputSet, names: list[Path] | None = None) -> list[Path]:
    """The canonical skeleton with its rotations, one file per generated row (named ``names``, default
    bvh_paths), staged in ``outputs``."""
    from mld_core.motion.bvh import write_canonical_bvh
    from mld_core.motion.quaternion import resample_quaternions
    from mld_core.motion.rotations import features_to_rotations

    paths = names or bvh_paths(path, len(out.lengths))
    for i, p in enumerate(paths):
        n = int(out.lengths[i])
        quats, root = features_to_rotations(out.features[i, :n])
        if fps != out.fps:
            quats, root = resample_quaternions(quats, root, out.fps, fps)
        outputs.stage(p, lambda tmp: write_canonical_bvh(tmp, root, quats, 1.0 / fps))
    return paths


def _prompt_lines(args) -> list[PromptLine]:
    if sum(x is not None for x in (args.prompt, args.prompts, args.sequence)) > 1:
        raise InputError("give one of a PROMPT, --prompts FILE or --sequence FILE")
    if args.sequence is not None:
        return _sequence_lines(args)
    if args.prompts is not None:
        return read_prompt_file(args.prompts)
    if (args.unconditional or args.action) and not (args.prompt or "").strip():
        return [PromptLine(0, "", None)]
    if args.prompt is None or not args.prompt.strip():
        raise InputError("empty prompt: type what the motion should be, or pass --unconditional")
    return [PromptLine(0, inputs.check_prompt(args.prompt), None)]


SEQUENCE_OVERLAP_S = 0.5  # each later segment also makes the previous one's last half second


def _sequence_lines(args) -> list[PromptLine]:
    """--sequence segments as prompt lines (their seconds as frames); refused with what a sequence cannot take."""
    from mld_core.take_fixes.constraints import sequence_from_data

    clashes = [flag for flag, on in (("--variants", args.variants != 1), ("--best", args.best is not None),
                                     ("--keys", args.keys is not None), ("--path", args.path is not None),
                                     ("--loop", args.loop), ("--action", bool(args.action)),
                                     ("--unconditional", args.unconditional)) if on]
    if clashes:
        raise InputError(f"--sequence makes one motion from its segments: drop {', '.join(clashes)}")
    segments = sequence_from_data(inputs.read_json_file(args.sequence, "--sequence"), f"--sequence {args.sequence}")
    limits = inputs.model_limits(args.model)
    lines = []
    for n, (text, seconds) in enumerate(segments, start=1):
        extra = SEQUENCE_OVERLAP_S if n > 1 else 0.0
        inputs.check_seconds(seconds + extra, limits, f"--sequence segment {n}: length" + (
            f" (+ {SEQUENCE_OVERLAP_S:g} s overlap)" if extra else ""))
        lines.append(PromptLine(n, text, int(round(seconds * inputs.MODEL_FPS))))
    return lines


def _constraints(args):
    """--keys, --path and --loop as one mld_core.take_fixes.constraints.Constraints (empty when none is given)."""
    from mld_core.take_fixes import constraints as C

    items = []
    if args.keys is not None:
        items.append(C.keys_from_data(inputs.read_json_file(args.keys, "--keys"), f"--keys {args.keys}"))
    if args.path is not None:
        items.append(C.path_from_data(inputs.read_json_file(args.path, "--path"), f"--path {args.path}"))
    if args.loop:
        items.append(C.Loop())
    return C.Constraints(items)


def _checked_args(args) -> tuple[list[PromptLine], list[float], object]:
    """Every input checked before the model loads or anything is written: (lines, seconds per line, constraints).
    With --shard, the shard's lines (their indices in the file: args.line_indices, of args.lines_total)."""
    inputs.check_threads(args.threads, "--threads")
    lines = _prompt_lines(args)
    args.lines_total, args.line_indices = len(lines), list(range(len(lines)))
    if args.shard is not None:  # shard I of N: lines I, I + N, ... (their seeds as in the whole run)
        if args.sequence is not None:
            raise InputError("--shard splits a prompt file's lines; a --sequence is one motion")
        args.all_lines = lines
        args.line_indices = shard_lines(len(lines), inputs.check_shard(args.shard))
    variants = inputs.int_in_range(args.variants, "--variants", 1, 64)
    if args.best is not None:
        inputs.int_in_range(args.best, "--best", 1, variants)
    inputs.check_seed(args.seed, len(lines) * variants, "--seed")  # the whole run's seeds
    if args.steps is not None:
        inputs.check_steps(args.steps, "--steps")
    args.guidance = inputs.check_guidance(args.guidance, "--guidance")  # 0: the model's default (None)
    inputs.check_fps(args.fps, "--fps")
    default = inputs.finite_number(args.seconds, "--seconds")
    limits = inputs.model_limits(args.model)
    seconds = []
    for line in lines:
        what = f"line {line.line}: length" if line.line else "--seconds"
        length = line.seconds(default)  # a sequence's segments were checked with their overlap
        seconds.append(length if args.sequence is not None else inputs.check_seconds(length, limits, what))
    constraints = _constraints(args)
    if constraints:
        for s in seconds:
            constraints.check_frames(int(round(s * limits.fps)))
    lines, seconds = [lines[i] for i in args.line_indices], [seconds[i] for i in args.line_indices]  # every line
    rows = 1 if args.sequence is not None else len(lines) * (args.best or variants)
    outputs = {"--out": args.out}
    if args.bvh is not None:
        args.bvh_names = _bvh_names(args, rows)
        outputs.update({f"--bvh ({p.name})": p for p in args.bvh_names})
    inputs.check_outputs(outputs, {"--prompts": args.prompts, "--keys": args.keys, "--path": args.path,
                                   "--sequence": args.sequence},
                         overwrite=args.overwrite)
    return lines, seconds, constraints


def _load(args, model=None):
    from mld_core.checkpoint import CheckpointError
    from mld_core.pipeline import MLDPipeline

    try:
        return MLDPipeline.from_pretrained(args.model if model is None else model, precision=args.precision,
                                           draft_precision=args.draft_precision, device=args.device)
    except CheckpointError as exc:
        raise InputError(str(exc)) from None
    except ImportError as exc:
        raise InputError(f"missing dependency: {exc}") from None


def _load_routed(args, lines):
    """--model auto: the bundled model the prompts go to (mld_core.model_route), said on stderr when it is not the
    default; the default for --unconditional and --action, which read no prompt."""
    from mld_core.bundled import DEFAULT_NAME
    from mld_core.model_route import ModelRouter

    router = ModelRouter(lambda name: _load(args, name))
    if args.unconditional or args.action:
        return router.pipe(DEFAULT_NAME)
    _, pipe, said = router.route([line.text for line in lines], one_motion=args.sequence is not None)
    for line in said:
        print(line, file=sys.stderr)
    return pipe


def _warn_long_prompts(encoder, lines) -> None:
    for line in lines:
        count = len(encoder.tokenizer.tokenize_ids(line.text)) + 2  # [CLS] ... [SEP]
        if count > encoder.max_tokens:
            print(f"warning: prompt{f' on line {line.line}' if line.line else ''} has {count} tokens; "
                  f"only the first {encoder.max_tokens} are used", file=sys.stderr)


def _warn_unmet(out) -> None:
    """One warning line per constraint a take did not meet, with its residual: the best effort is still written."""
    for row, residuals in enumerate(out.residuals or []):
        for kind, metres, met in residuals:
            if not met:
                print(f"warning: take {row} (seed {out.seeds[row]}): the {kind} constraint is off by "
                      f"{metres * 100:.1f} cm (best effort)", file=sys.stderr)


def run(args) -> int:
    from mld_core import take_report
    from mld_core.cli import UsageError

    try:
        return _run(args, take_report)
    except (ValueError, take_report.BeyondModel) as exc:  # InputError is a ValueError
        raise UsageError(str(exc)) from None
    except FileExistsError as exc:  # another run took an output name between our check and our rename
        raise UsageError(str(exc)) from None
    except OSError as exc:  # a folder we may not write to, a full disk: nothing was put in place
        raise UsageError(f"cannot write {exc.filename or 'the outputs'}: {exc.strerror or exc}") from None


def _run(args, take_report) -> int:
    # 1. Inputs and output paths, all checked before any work.
    lines, seconds, constraints = _checked_args(args)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    # 2. The model (--model auto: the one the prompts go to), and what it can be asked.
    from mld_core.model_route import is_auto

    pipe = _load_routed(args, lines) if is_auto(args.model) else _load(args)
    if args.draft and pipe.draft_denoiser is None:
        raise InputError(f"--draft: {pipe.draft_problem}" if pipe.draft_problem else
                         f"--draft: the model {pipe.model_id} has no Draft denoiser (make one with "
                         "`python -m mld_core train draft`)")
    cond = pipe.denoiser.config.cond if pipe.denoiser is not None else "none"
    if args.action and cond != "action":
        raise InputError(f"--action needs an action-conditioned model; this model is conditioned on {cond}: "
                         "give a PROMPT instead")
    prompts = [line.text for line in lines]
    coverages = None
    if cond == "text" and not args.unconditional:
        if hasattr(pipe.text_encoder, "tokenizer"):
            _warn_long_prompts(pipe.text_encoder, lines)
        coverages = take_report.check_prompts(pipe, prompts, strict=args.strict,
                                              warn=lambda line: print(line, file=sys.stderr))
    if args.unconditional and cond == "text":
        prompts = [""] * len(prompts)
    # 3. Generate: line i, variant v uses seed + i * variants + v (the batch's rule with one variant per line); a
    #    shard's lines keep their indices in the file.
    seeds = [args.seed + i * args.variants for i in args.line_indices]
    kwargs = dict(seconds=seconds, num_inference_steps=args.steps, guidance_scale=args.guidance, seed=seeds,
                  num_variants=args.variants, rank=args.best is not None, constraints=constraints or None,
                  draft=args.draft, side_redraws=args.side_redraws, verb_redraws=args.verb_redraws)
    if args.sequence is not None:  # one motion, segment k continuing segment k-1 (seed + k)
        out = pipe.sequence(list(zip(prompts, seconds)), seed=args.seed, overlap_s=SEQUENCE_OVERLAP_S,
                            num_inference_steps=args.steps, guidance_scale=args.guidance, draft=args.draft)
    elif cond == "action":
        actions = [args.action] * len(prompts) if args.action else prompts
        out = pipe(prompts, actions=actions, **kwargs)
    elif args.unconditional:
        out = pipe(prompts, unconditional=True, **kwargs)
    else:
        out = pipe(prompts, **kwargs)
    _warn_unmet(out)
    if args.sequence is not None:
        for line in take_report.seam_lines(out.seams[0], prompts):
            print(f"warning: {line}", file=sys.stderr)
    out = take_report.keep_best(out, args.variants, args.best)
    if cond == "text" and not args.unconditional and args.sequence is None:  # a sequence's sides are per segment
        for line in take_report.side_lines(out):
            print(line, file=sys.stderr)
    if out.badges is not None:
        print(take_report.badge_table(out))
    # 4. Outputs: written beside their targets, then renamed together (all or none).
    shard, row_lines = _shard_record(args, pipe, len(out.lengths))
    with OutputSet(overwrite=args.overwrite) as outputs:
        write_npz(args.out, out, take_report.records_for(out, coverages), outputs, shard, row_lines)
        bvhs = write_bvhs(args.bvh, out, int(args.fps or out.fps), outputs, args.bvh_names) \
            if args.bvh is not None else []
    print(f"wrote {args.out}: {len(out.lengths)} motion(s), {int(out.lengths.max())} frames max at {out.fps} fps, "
          f"{out.timings.get('total_s', 0):.2f} s")
    for p in bvhs:
        print(f"wrote {p}")
    return 0


def _bvh_names(args, rows: int) -> list[Path]:
    """Each row's BVH file: for a shard, named by its row in the whole run (so the shards' files never clash and
    together are the unsharded run's)."""
    if args.shard is None:
        return bvh_paths(args.bvh, rows)
    per_line = rows // len(args.line_indices)
    whole = [i * per_line + v for i in args.line_indices for v in range(per_line)]
    return bvh_paths(args.bvh, args.lines_total * per_line, whole)


def _shard_record(args, pipe, rows: int) -> tuple[dict | None, list | None]:
    """(the shard's record, each row's line) for --shard; (None, None) otherwise."""
    if args.shard is None:
        return None, None
    from mld_core import shards

    settings = {"model_id": pipe.model_id, "model": shards.model_fingerprint(args.model),
                "prompts": shards.lines_fingerprint(args.all_lines), "seconds": args.seconds, "seed": args.seed,
                "steps": args.steps, "guidance": args.guidance, "variants": args.variants, "best": args.best,
                "draft": args.draft, "side_redraws": args.side_redraws, "verb_redraws": args.verb_redraws,
                "precision": args.precision,
                "draft_precision": args.draft_precision if args.draft else None, "strict": args.strict,
                "unconditional": args.unconditional, "action": args.action, "loop": args.loop, "fps": args.fps,
                "keys": shards.file_fingerprint(args.keys), "path": shards.file_fingerprint(args.path),
                "bvh": args.bvh is not None}
    record = shards.shard_record(inputs.check_shard(args.shard), args.lines_total, settings)
    record["device"] = args.device  # a machine's own choice: its takes are the same up to float rounding
    if args.bvh is not None:
        record["bvh"] = [str(p) for p in args.bvh_names]
    per_line = rows // len(args.line_indices)
    return record, [i for i in args.line_indices for _ in range(per_line)]


def register(groups) -> None:
    from mld_core.cli import DEVICE_HELP, PRECISION_CHOICES, PRECISION_HELP

    p = groups["root"].add_parser("generate", help="generate motion from text (or an action / nothing)")
    p.add_argument("prompt", nargs="?", default=None, help="what the motion should be")
    p.add_argument("--prompts", type=Path, default=None, help="a file with one prompt per line ('<frames> <text>' too)")
    p.add_argument("--seconds", type=float, default=4.0)
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the first take: line i, variant v of a prompt file uses seed + i * variants + v")
    p.add_argument("--steps", type=int, default=None,
                   help="DDIM steps (default: the model's, 50); with --draft, the Draft's steps (default: its config's; the "
                        "last of them may be guided DDIM steps of the model's own denoiser, config draft.teacher_steps)")
    p.add_argument("--guidance", type=float, default=None, help="classifier-free guidance scale (default: the model's)")
    p.add_argument("--draft", action="store_true",
                   help="Draft mode: the model's distilled denoiser, about 10x faster (docs/draft.md)")
    p.add_argument("--side-redraws", type=int, default=None, metavar="N",
                   help="a take that misses the side its prompt names (turns right for 'turns left', waves the other "
                        "hand) is drawn again from its seed, at most N times (default: the model's, 2; 0: never)")
    p.add_argument("--verb-redraws", type=int, default=None, metavar="N",
                   help="a take that does not show the checked verb its prompt names (a jump for 'jumps', a crawl, a "
                        "kick: docs/library.md) is drawn again from its seed, at most N times (default: the model's, "
                        "a Draft's own where its config sets one; 0: never)")
    p.add_argument("--variants", type=int, default=1, help="motions per prompt (seeds seed, seed+1, ...)")
    p.add_argument("--best", type=int, default=None, metavar="K",
                   help="score every variant (adherence, skating, float, penetration, jitter: docs/quality.md), "
                        "print the table and keep each prompt's K best, best first")
    p.add_argument("--strict", action="store_true",
                   help="refuse a prompt this model has not learned (coverage 'unknown'): exit 2, nothing written")
    p.add_argument("--keys", type=Path, default=None,
                   help='poses to hit: {"fps": 20, "keys": [{"frame": 40, "joints": {"pelvis": [x, y, z]}}]} '
                        "(docs/control.md)")
    p.add_argument("--path", type=Path, default=None,
                   help='a root path on the ground: {"fps": 20, "points": [[frame, x, z], ...]} (docs/control.md)')
    p.add_argument("--loop", action="store_true", help="make the last frame continue into the first")
    p.add_argument("--sequence", type=Path, default=None,
                   help='one motion from segments: [{"prompt": "...", "seconds": 3.0}, ...] (docs/control.md)')
    p.add_argument("--model", default=None,
                   help="a model folder, a bundled model's name such as v4_preview, or auto: the bundled model that makes "
                        "each prompt (default: the bundled default)")
    p.add_argument("--unconditional", action="store_true", help="ignore text: sample the unconditional model")
    p.add_argument("--action", default=None, help="an action label, for action-conditioned models")
    p.add_argument("--out", type=Path, required=True, help="OUT.npz")
    p.add_argument("--bvh", type=Path, default=None, help="also write BVH (one file per motion)")
    p.add_argument("--fps", type=int, default=None, help="BVH frame rate (default 20)")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.add_argument("--shard", default=None, metavar="I/N",
                   help="make only shard I of N (from 0) of a prompt file: lines I, I + N, ... with the seeds of the "
                        "whole run; `python -m mld_core merge` joins the shards (docs/training.md)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--precision", choices=PRECISION_CHOICES, default="fp32", help=PRECISION_HELP)
    p.add_argument("--device", default="cpu", help=f"where the model runs: {DEVICE_HELP}; a take is the same on "
                   "every device up to float rounding (its noise is drawn on the CPU)")
    p.add_argument("--draft-precision", choices=("auto", "fp32", "bf16"), default="auto",
                   help="the Draft's precision: auto (default) is bf16 on CPUs with native bfloat16 (AVX512-BF16, AMX), "
                        "fp32 elsewhere; fp32 gives the same Draft take on every CPU (docs/draft.md)")
    p.set_defaults(func=run)
