"""``python -m mld_core generate``: prompts in, motions out (.npz, optional .bvh per variant)."""

from __future__ import annotations

import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mld_core.fileio import atomic_write

_FRAMES_LINE = re.compile(r"^\s*(\d+)\s+(.*\S)\s*$")


@dataclass
class PromptLine:
    text: str
    seconds: float | None  # None: use --seconds
    line: int


def parse_prompt_lines(text: str, fps: int = 20, source: str = "prompts") -> list[PromptLine]:
    """One prompt per line; MLD's ``<frames> <text>`` lines set the length. Blank lines and ``#`` comments skip."""
    prompts = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if "\x00" in line:
            raise ValueError(f"{source}, line {number}: not text")
        match = _FRAMES_LINE.match(line)
        if match:
            frames = int(match.group(1))
            if frames <= 0:
                raise ValueError(f"{source}, line {number}: frame count must be positive")
            prompts.append(PromptLine(match.group(2), frames / fps, number))
        else:
            prompts.append(PromptLine(line, None, number))
    if not prompts:
        raise ValueError(f"{source}: no prompts (one per line, optionally '<frames> <text>')")
    return prompts


def read_prompt_file(path: Path, fps: int = 20) -> list[PromptLine]:
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read prompt file {path}: {exc.strerror or exc}") from None
    for number, raw in enumerate(data.split(b"\n"), start=1):
        try:
            raw.decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError(f"{path}, line {number}: not UTF-8 text") from None
    return parse_prompt_lines(data.decode("utf-8"), fps, str(path))


def write_npz(path: Path, out, records: list | None = None) -> None:
    """``records``: per row a JSON-able dict (coverage, badges), stored as one JSON string ``quality``."""
    extra = {"quality": np.array(json.dumps(records))} if records and any(records) else {}

    def save(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, features=out.features.astype(np.float32), joints=out.joints.astype(np.float32),
                     lengths=np.asarray(out.lengths, np.int64), fps=np.int64(out.fps), prompts=np.array(out.prompts),
                     seeds=np.asarray(out.seeds, np.int64), model_id=np.array(out.model_id), **extra)

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, save)


def bvh_paths(path: Path, n: int) -> list[Path]:
    path = Path(path)
    if n == 1:
        return [path]
    return [path.with_name(f"{path.stem}_{i:03d}{path.suffix or '.bvh'}") for i in range(n)]


def write_bvhs(path: Path, out, fps: int) -> list[Path]:
    """The canonical skeleton with its rotations, one file per generated row."""
    from mld_core.motion import skeleton
    from mld_core.motion.bvh import write_bvh
    from mld_core.motion.quaternion import resample_quaternions
    from mld_core.motion.rotations import features_to_rotations

    paths = bvh_paths(path, len(out.lengths))
    for i, p in enumerate(paths):
        n = int(out.lengths[i])
        quats, root = features_to_rotations(out.features[i, :n])
        if fps != out.fps:
            quats, root = resample_quaternions(quats, root, out.fps, fps)
        atomic_write(p, lambda tmp: write_bvh(tmp, list(skeleton.JOINT_NAMES), list(skeleton.PARENTS),
                                              np.asarray(skeleton.REST_OFFSETS), root, quats, 1.0 / fps))
    return paths


def run(args) -> int:
    from mld_core import take_report
    from mld_core.checkpoint import CheckpointError
    from mld_core.cli import UsageError
    from mld_core.pipeline import MLDPipeline

    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    if args.prompt is not None and args.prompts is not None:
        raise UsageError("give a PROMPT or --prompts FILE, not both")
    try:
        if args.prompts is not None:
            lines = read_prompt_file(args.prompts)
        elif args.unconditional or args.action:
            lines = [PromptLine(args.prompt or "", None, 0)]
        else:
            if args.prompt is None or not args.prompt.strip():
                raise ValueError("empty prompt: type what the motion should be, or pass --unconditional")
            lines = [PromptLine(args.prompt.strip(), None, 0)]
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.variants < 1 or args.variants > 64:
        raise UsageError("--variants must be between 1 and 64")
    if args.steps is not None and not 1 <= args.steps <= 1000:
        raise UsageError("--steps must be between 1 and 1000")
    try:
        pipe = MLDPipeline.from_pretrained(args.model, precision=args.precision)
    except CheckpointError as exc:
        raise UsageError(str(exc)) from None
    except ImportError as exc:
        raise UsageError(f"missing dependency: {exc}") from None
    seconds = [line.seconds if line.seconds is not None else args.seconds for line in lines]
    for line, s in zip(lines, seconds):
        if not (pipe.min_seconds <= s <= pipe.max_seconds):
            where = f"line {line.line}: " if line.line else ""
            raise UsageError(f"{where}seconds must be between {pipe.min_seconds:g} and {pipe.max_seconds:g} "
                             f"for this model, got {s:g}")
    prompts = [line.text for line in lines]
    cond = pipe.denoiser.config.cond if pipe.denoiser is not None else "none"
    encoder = pipe.text_encoder
    if cond == "text" and hasattr(encoder, "tokenizer"):
        for line in lines:
            count = len(encoder.tokenizer.tokenize_ids(line.text)) + 2  # [CLS] ... [SEP]
            if count > encoder.max_tokens:
                print(f"warning: prompt{f' on line {line.line}' if line.line else ''} has {count} tokens; "
                      f"only the first {encoder.max_tokens} are used", file=sys.stderr)
    if args.best is not None and not 1 <= args.best <= args.variants:
        raise UsageError(f"--best must be between 1 and --variants ({args.variants})")
    coverages = None
    if cond == "text" and not args.unconditional:  # say so when a prompt is beyond the model (--strict: refuse)
        try:
            coverages = take_report.check_prompts(pipe, prompts, strict=args.strict,
                                                  warn=lambda line: print(line, file=sys.stderr))
        except take_report.BeyondModel as exc:
            raise UsageError(str(exc)) from None
    if args.unconditional and cond == "text":
        prompts = [""] * len(prompts)
    kwargs = dict(seconds=seconds, num_inference_steps=args.steps, guidance_scale=args.guidance, seed=args.seed,
                  num_variants=args.variants, rank=args.best is not None)
    try:
        if cond == "action":
            actions = [args.action] * len(prompts) if args.action else prompts
            out = pipe(prompts, actions=actions, **kwargs)
        elif args.unconditional:
            out = pipe(prompts, unconditional=True, **kwargs)
        else:
            out = pipe(prompts, **kwargs)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = take_report.keep_best(out, args.variants, args.best)
    if out.badges is not None:
        print(take_report.badge_table(out))
    write_npz(args.out, out, take_report.records_for(out, coverages))
    print(f"wrote {args.out}: {len(out.lengths)} motion(s), {int(out.lengths.max())} frames max at {out.fps} fps, "
          f"{out.timings.get('total_s', 0):.2f} s")
    if args.bvh is not None:
        for p in write_bvhs(args.bvh, out, args.fps or out.fps):
            print(f"wrote {p}")
    return 0


def register(groups) -> None:
    from mld_core.cli import PRECISION_CHOICES, PRECISION_HELP

    p = groups["root"].add_parser("generate", help="generate motion from text (or an action / nothing)")
    p.add_argument("prompt", nargs="?", default=None, help="what the motion should be")
    p.add_argument("--prompts", type=Path, default=None, help="a file with one prompt per line ('<frames> <text>' too)")
    p.add_argument("--seconds", type=float, default=4.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=None, help="DDIM steps (default: the model's, 50)")
    p.add_argument("--guidance", type=float, default=None, help="classifier-free guidance scale (default: the model's)")
    p.add_argument("--variants", type=int, default=1, help="motions per prompt (seeds seed, seed+1, ...)")
    p.add_argument("--best", type=int, default=None, metavar="K",
                   help="score every variant (adherence, skating, float, penetration, jitter: docs/quality.md), "
                        "print the table and keep each prompt's K best, best first")
    p.add_argument("--strict", action="store_true",
                   help="refuse a prompt this model has not learned (coverage 'unknown'): exit 2, nothing written")
    p.add_argument("--model", type=Path, default=None, help="a model folder (default: the bundled model)")
    p.add_argument("--unconditional", action="store_true", help="ignore text: sample the unconditional model")
    p.add_argument("--action", default=None, help="an action label, for action-conditioned models")
    p.add_argument("--out", type=Path, required=True, help="OUT.npz")
    p.add_argument("--bvh", type=Path, default=None, help="also write BVH (one file per motion)")
    p.add_argument("--fps", type=int, default=None, help="BVH frame rate (default 20)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--precision", choices=PRECISION_CHOICES, default="fp32", help=PRECISION_HELP)
    p.set_defaults(func=run)
