"""Commands: ``train evaluator`` and ``evaluate t2m|a2m|uncond|vae``."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from mld_core.inputs import check_world


def register(groups) -> None:
    from mld_core.cli import DEVICE_HELP, PRECISION_CHOICES, PRECISION_HELP

    p = groups["train"].add_parser(
        "evaluator", help="train the evaluator (motion + text encoders, action classifier) used by `evaluate`",
        description="Train the text-motion evaluator on a HumanML3D-format folder's train split "
                    "(val split for model selection; test split scored in the card).")
    p.add_argument("--data", required=True, help="HumanML3D-format folder (e.g. the output of `data prepare`)")
    p.add_argument("--out", required=True, help="run folder; holds the evaluator (config.json, model.safetensors, "
                                                "EVALUATOR_CARD.md) and the resumable train state")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1: leaves cores for others)")
    p.add_argument("--epochs", type=int, default=60)
    p.add_argument("--minutes", type=float, default=12.0, help="wall-time budget of this run (0: none)")
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--hidden", type=int, default=None, help="motion encoder width (default 256)")
    p.add_argument("--layers", type=int, default=None, help="motion encoder transformer layers (default 2)")
    p.add_argument("--ff-dim", type=int, default=None, help="transformer feed-forward width (default 2 x hidden)")
    p.add_argument("--text-encoder", default=None, metavar="JSON",
                   help='frozen sentence encoder spec, e.g. \'{"kind": "minilm"}\' (the default)')
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--device", default="cpu",
                   help="cpu (default), cuda, mps or auto (CUDA, then MPS, then the CPU); float32 everywhere. Under "
                        "torchrun each process embeds its rows of every batch: --batch-size is the total over all "
                        "processes")
    p.set_defaults(func=run_train)

    e = groups["root"].add_parser(
        "evaluate", help="paper-style evaluation table with 95%% confidence intervals",
        description="Evaluate a model folder on a data split with the evaluator: t2m (text-to-motion), a2m "
                    "(action-to-motion), uncond (unconditional), vae (reconstruction). Prints the table with a "
                    "Real row and writes JSON.")
    e.add_argument("task", choices=["t2m", "a2m", "uncond", "vae"])
    e.add_argument("--model", default=None, help="model folder or bundled model's name (default: the bundled default)")
    e.add_argument("--data", required=True, help="HumanML3D-format folder")
    e.add_argument("--split", default="test")
    e.add_argument("--evaluator", default=None, help="evaluator folder (default: the bundled evaluator)")
    e.add_argument("--preset", choices=["reduced", "full"], default="full",
                   help="reduced: 3 replications and a smaller MultiModality set (about 10 min for t2m on 2 "
                        "cores); full: the T2M/MLD protocol (20 replications, 100 texts x 30 generations)")
    e.add_argument("--replications", type=int, default=None, help="override the preset's replications")
    e.add_argument("--max-pairs", type=int, default=None, help="cap the pairs drawn per replication")
    e.add_argument("--mm-texts", type=int, default=None)
    e.add_argument("--mm-repeats", type=int, default=None)
    e.add_argument("--steps", type=int, default=None, help="DDIM steps (default: the model's)")
    e.add_argument("--guidance", type=float, default=None, help="guidance scale (default: the model's)")
    e.add_argument("--draft", action="store_true", help="sample with the model's Draft denoiser (its default steps "
                   "unless --steps)")
    e.add_argument("--side-redraws", type=int, default=None, metavar="N",
                   help="draws of a take beyond its first when it misses the side its prompt names (default: the "
                        "model's config side_redraws; 0: the model alone, as before 2026-11-27)")
    e.add_argument("--verb-redraws", type=int, default=None, metavar="N",
                   help="draws of a take beyond its first when it does not show the checked verb its prompt names "
                        "(default: the model's config verb_redraws; 0: the model alone)")
    e.add_argument("--batch-size", type=int, default=32, help="generation batch")
    e.add_argument("--action-prompt", default=None,
                   help="a2m with a text model: prompt template, {action} is replaced by the action's name "
                        "(default: 'a person does the {action} motion')")
    e.add_argument("--vae-mean", action="store_true", help="vae: decode the posterior mean instead of a sample")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    e.add_argument("--precision", choices=PRECISION_CHOICES, default="fp32", help=PRECISION_HELP)
    e.add_argument("--device", default="cpu", help=f"where the model generates: {DEVICE_HELP}")
    e.add_argument("--name", default=None, help="row name for the model (default: its model_id)")
    e.add_argument("--json", default=None, help="write the result here (default: no file)")
    e.add_argument("--no-progress", action="store_true")
    e.set_defaults(func=run_evaluate)


SETTING_FLAGS = {"num_inference_steps": "--steps", "guidance_scale": "--guidance"}  # else --field-name


def _usage(msg: str):
    from mld_core.cli import UsageError

    return UsageError(msg)


def _check_folder(path: str, split: str | None = "train") -> Path:
    root = Path(path)
    if not root.is_dir():
        raise _usage(f"--data {root}: no such folder")
    needed = ["new_joint_vecs", "Mean.npy", "Std.npy"] + ([f"{split}.txt"] if split else [])
    missing = [n for n in needed if not (root / n).exists()]
    if missing:
        raise _usage(f"{root} is not a HumanML3D-format folder (missing {', '.join(missing)})")
    return root


def _check_train_flags(args: argparse.Namespace) -> None:
    """train evaluator's numbers in range before any work (--minutes 0: no time limit)."""
    from mld_core.inputs import InputError, finite_number, int_in_range, number_in_range

    int_in_range(args.epochs, "--epochs", 1, 100_000)
    int_in_range(args.batch_size, "--batch-size", 2, 65_536)
    int_in_range(args.threads, "--threads", 1, 1024)
    if finite_number(args.minutes, "--minutes") < 0:
        raise InputError(f"--minutes must be 0 (no limit) or more, got {args.minutes:g}")
    number_in_range(args.lr, "--lr", 1e-12, 1.0)
    for flag, hi in (("hidden", 4096), ("layers", 64), ("ff_dim", 65_536)):
        if getattr(args, flag) is not None:
            int_in_range(getattr(args, flag), f"--{flag.replace('_', '-')}", 1, hi)


def run_train(args: argparse.Namespace) -> int:
    from mld_core.eval.evaluator import EvaluatorConfig
    from mld_core.eval.train import EvaluatorTrainConfig, train_evaluator
    from mld_core.inputs import parse_json

    _check_folder(args.data, "train")
    _check_train_flags(args)
    world = check_world(os.environ, args.device)  # torchrun's environment, before anything is written
    if args.batch_size < world.size:
        raise _usage(f"--batch-size {args.batch_size} must be at least the {world.size} processes")
    cfg = EvaluatorTrainConfig(data=args.data, out=args.out, seed=args.seed, threads=args.threads, epochs=args.epochs,
                               minutes=args.minutes or None, batch_size=args.batch_size, lr=args.lr,
                               device=args.device)
    model_cfg = EvaluatorConfig()
    if args.hidden:
        model_cfg.hidden = args.hidden
        model_cfg.ff_dim = 2 * args.hidden
    if args.ff_dim:
        model_cfg.ff_dim = args.ff_dim
    if args.text_encoder:
        spec = parse_json(args.text_encoder, "--text-encoder")
        if not isinstance(spec, dict) or "kind" not in spec:
            raise _usage('--text-encoder must be a JSON object with a "kind", e.g. {"kind": "minilm"}')
        model_cfg.text_encoder = spec
    if args.layers:
        model_cfg.layers = args.layers
    from mld_core.models.text_encoder import TextEncoderError

    try:
        EvaluatorConfig.from_dict(model_cfg.to_dict())
        out = train_evaluator(cfg, model_cfg, resume=args.resume, progress=not args.no_progress)
    except (FileExistsError, FileNotFoundError, ValueError, TextEncoderError) as exc:
        raise _usage(str(exc)) from None
    from mld_core.training.distributed import finish, is_main_process

    finish()
    if is_main_process():
        print(f"wrote {out}")
    return 0


def run_evaluate(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from mld_core.eval.evaluate import (PRESETS, EvalSettings, PipelineGenerator, check_settings, evaluate,
                                        format_table, write_json)
    from mld_core.eval.evaluator import Evaluator, EvaluatorError
    from mld_core.inputs import check_outputs

    root = _check_folder(args.data, args.split)
    settings = replace(EvalSettings(), **PRESETS[args.preset])
    overrides = {"replications": args.replications, "max_pairs": args.max_pairs, "mm_texts": args.mm_texts,
                 "mm_repeats": args.mm_repeats, "num_inference_steps": args.steps, "guidance_scale": args.guidance}
    overrides["action_prompt"] = args.action_prompt
    settings = replace(settings, **{k: v for k, v in overrides.items() if v is not None},
                       split=args.split, seed=args.seed, batch_size=args.batch_size, vae_sample=not args.vae_mean,
                       draft=args.draft, side_redraws=args.side_redraws, verb_redraws=args.verb_redraws)
    check_settings(settings, args.task, lambda field: SETTING_FLAGS.get(field, "--" + field.replace("_", "-")))
    if args.json:  # checked now: the results of a long run are not lost to an output that cannot be written
        check_outputs({"--json": Path(args.json)}, overwrite=True)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    try:
        evaluator = Evaluator.from_pretrained(args.evaluator)
    except EvaluatorError as exc:
        raise _usage(str(exc)) from None
    from mld_core.checkpoint import CheckpointError
    from mld_core.data.dataset import load_split
    from mld_core.pipeline import MLDPipeline

    try:
        pipe = MLDPipeline.from_pretrained(args.model, precision=args.precision, device=args.device)
    except (CheckpointError, FileNotFoundError) as exc:
        raise _usage(f"cannot load the model: {exc}") from None
    if args.draft and pipe.draft_denoiser is None:
        raise _usage(f"{args.model or 'the bundled model'} has no Draft denoiser (train one with `train draft`)")
    if pipe.denoiser is None and args.task != "vae":
        raise _usage(f"{args.model} holds only a VAE: evaluate it with `evaluate vae`")
    if args.task != "vae":
        cond = pipe.denoiser.config.cond
        if args.task == "t2m" and cond != "text":
            raise _usage(f"the model is conditioned on {cond!r}, not text: use `evaluate {'a2m' if cond == 'action' else 'uncond'}`")
        if args.task == "a2m" and cond == "none":
            raise _usage("an unconditional model cannot be evaluated on actions: use `evaluate uncond`")
    clips = load_split(root, args.split)
    try:
        result = evaluate(args.task, evaluator, clips, PipelineGenerator(pipe, settings, not args.no_progress),
                          settings, model_name=args.name or pipe.model_id or "MLD", progress=not args.no_progress)
    except ValueError as exc:
        raise _usage(str(exc)) from None
    result.update(data=str(root), model=str(args.model or "default"), model_id=pipe.model_id,
                  evaluator=str(args.evaluator or "default"))
    print(format_table(result))
    print(f"({result['seconds']:.0f} s wall, {result['cpu_seconds']:.0f} s CPU)")
    from mld_core.bench import busy_note

    note = busy_note(result.get("other_cpus"), os.cpu_count())
    if note:
        print(note)
    if args.json:
        write_json(result, args.json)
        print(f"wrote {args.json}")
    return 0
