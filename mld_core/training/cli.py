"""``python -m mld_core train vae|denoiser``: one training entry per stage."""

from __future__ import annotations

import os
from pathlib import Path

from mld_core.cli import UsageError
from mld_core.inputs import (check_output_folder, check_world, int_in_range, number_in_range, parse_json,
                             read_json_file, true_or_false)


def _run_options(p) -> None:
    """Resuming, seed, threads, budget and learning rate: the options every training stage has."""
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its train_state.pt")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    p.add_argument("--steps", type=int, default=None, help="stop after this many optimiser steps")
    p.add_argument("--minutes", type=float, default=None, help="stop after this much wall time")
    p.add_argument("--lr", type=float, default=None)
    _device_options(p)


def _device_options(p) -> None:
    """Where the stage trains: the device and, on CUDA, the precision (mld_core.training.distributed)."""
    p.add_argument("--device", default="cpu",
                   help="cpu (default), cuda, mps or auto (CUDA, then MPS, then the CPU). Under torchrun "
                        "(torchrun --nproc_per_node N -m mld_core train ...) each process trains on its own rows of "
                        "every batch: the config's batch sizes (batch_size, frames_per_batch) are totals over all "
                        "processes, the learning rate is the one of that total batch")
    p.add_argument("--fp32", action="store_true",
                   help="on CUDA, train in float32 (default there: mixed precision, bfloat16 where the GPU has it, "
                        "else float16 with a gradient scaler)")


def _common(p) -> None:
    p.add_argument("--data", required=True, help="a HumanML3D-format folder (HumanML3D, KIT-ML, or `data prepare` output)")
    p.add_argument("--out", required=True, help="the run folder to write (a complete model folder when done)")
    _run_options(p)
    p.add_argument("--layers", type=int, default=None, help="transformer layers (odd with skips)")
    p.add_argument("--no-skip", action="store_true", help="turn the long skip connections off")
    p.add_argument("--bf16", action="store_true", help="bfloat16 autocast (about 2x faster on CPUs with AVX512-BF16 or AMX)")
    p.add_argument("--config", default=None, metavar="JSON_OR_FILE",
                   help="overrides of the stage's config dataclass: a JSON object, inline or in a file")
    p.add_argument("--init", nargs="?", const="default", default=None, metavar="MODEL_DIR",
                   help="fine-tune: start from a model folder's weights and architecture (no value: the bundled model)")


def _check_data(path: str) -> None:
    """A HumanML3D-format folder whose statistics and training split can be used, checked before the run folder
    is made."""
    import numpy as np

    root = Path(path)
    missing = [n for n in ("new_joint_vecs", "train.txt", "Mean.npy", "Std.npy") if not (root / n).exists()]
    if missing:
        raise UsageError(f"{root} is not a HumanML3D-format folder (missing {', '.join(missing)})")
    stats = []
    for name in ("Mean.npy", "Std.npy"):
        try:
            stats.append(np.asarray(np.load(root / name, allow_pickle=False), np.float64))
        except (OSError, ValueError) as exc:
            raise UsageError(f"{root / name} is not a numpy array file: {exc}") from None
    mean, std = stats
    if mean.ndim != 1 or mean.shape != std.shape:
        raise UsageError(f"{root}: Mean.npy and Std.npy must be vectors of one length, got {mean.shape} and {std.shape}")
    if not (np.isfinite(mean).all() and np.isfinite(std).all()) or (std <= 0).any():
        raise UsageError(f"{root}: Mean.npy/Std.npy hold non-finite values or a std <= 0")
    ids = [line.strip() for line in (root / "train.txt").read_text(errors="replace").splitlines() if line.strip()]
    if not any((root / "new_joint_vecs" / f"{i}.npy").is_file() for i in ids):
        raise UsageError(f"{root}: the training split (train.txt) names no clip found in new_joint_vecs/")


def _where(args) -> dict:
    """--device (checked and resolved by mld_core.cli) and --fp32 as config settings."""
    return {"device": args.device, "fp32": args.fp32}


def _init_dir(args) -> str | None:
    """--init's model folder (checked: a model folder with a config.json), "default" meaning the bundled one."""
    return None if args.init is None else str(_model_folder(args.init, "--init"))


def _vae_dir(value: str) -> str:
    """--vae: a VAE run or model folder, or a bundled model's name (its VAE)."""
    from mld_core.bundled import UnknownModel, model_folder

    if not str(value).strip():  # an empty --vae is a mistake, not the bundled default
        raise UsageError("--vae is empty: give a VAE run folder, a model folder or a bundled model's name")
    try:
        return str(model_folder(value))
    except UnknownModel as exc:
        raise UsageError(f"--vae: {exc}") from None


def _model_folder(value: str | None, flag: str) -> Path:
    """A model folder named by ``flag`` (None: the bundled default; or a bundled model's name), checked to hold a
    config.json."""
    from mld_core.bundled import UnknownModel, model_folder

    try:
        path = model_folder(value)
    except UnknownModel as exc:
        raise UsageError(f"{flag}: {exc}") from None
    if not (path / "config.json").is_file():
        raise UsageError(f"{flag} {path} is not a model folder (no config.json)")
    return path


def _check_run_options(args) -> None:
    """--steps, --minutes and --lr (and --layers, --latent-tokens where the stage has them) in range, before the
    run folder is made: a run that would make no optimiser step is refused."""
    from mld_core.training.common import checked_budget

    checked_budget(args.steps, args.minutes, ("--steps", "--minutes"))
    if args.lr is not None:
        number_in_range(args.lr, "--lr", 1e-12, 1.0)
    for flag in ("layers", "latent_tokens"):
        if getattr(args, flag, None) is not None:
            int_in_range(getattr(args, flag), f"--{flag.replace('_', '-')}", 1, 64)


RUN_FLAGS = {"data": "--data", "out": "--out", "seed": "--seed", "threads": "--threads", "steps": "--steps",
             "minutes": "--minutes", "device": "--device", "fp32": "--fp32"}  # every stage's own flags
VAE_FLAGS = {**RUN_FLAGS, "init": "--init"}
DENOISER_FLAGS = {**VAE_FLAGS, "vae": "--vae", "cond": "--cond"}
DISTILLATION_FLAGS = {**RUN_FLAGS, "teacher": "--teacher"}


def _overrides(args, config_class, flags: dict) -> dict:
    """--config: a JSON object of the stage config's own fields, written inline or in a file; a field the stage
    sets from its own flag (``flags``: field -> flag) is refused, naming that flag."""
    if args.config is None:
        return {}
    inline = args.config.lstrip()[:1] in ("{", "[")
    data = parse_json(args.config, "--config") if inline else read_json_file(args.config, "--config")
    if not isinstance(data, dict):
        raise UsageError(f"--config {args.config} must hold a JSON object of settings, got a {type(data).__name__}")
    unknown = sorted(set(data) - set(config_class.__dataclass_fields__))
    if unknown:
        raise UsageError(f"--config {args.config}: unknown setting(s) {', '.join(unknown)}; known: "
                         f"{', '.join(sorted(config_class.__dataclass_fields__))}")
    flagged = [k for k in data if k in flags]
    if flagged:
        raise UsageError(f"--config {args.config}: {', '.join(flagged)} {'is' if len(flagged) == 1 else 'are'} set by "
                         f"{', '.join(flags[k] for k in flagged)}, not in --config")
    switches = [k for k in data if isinstance(config_class.__dataclass_fields__[k].default, bool)]
    try:
        for key in switches:  # "false" or 1 would otherwise read as on
            true_or_false(data[key], key)
    except ValueError as exc:
        raise UsageError(f"bad settings: {exc}") from None
    return data


def _run(train, make_config, out: str, resume: bool, device: str = "cpu") -> int:
    """Build the stage config and train; a run that fails before its first checkpoint leaves no folder behind."""
    import shutil

    from mld_core.checkpoint import CheckpointError
    from mld_core.training.distributed import finish, is_main_process

    out_dir = Path(out)
    check_world(os.environ, device)  # torchrun's environment, before anything is written
    check_output_folder(out_dir, "--out")
    new_folder = not out_dir.exists() and is_main_process()  # only rank 0 makes (and may remove) the run folder
    try:
        cfg = make_config()
    except (TypeError, ValueError) as exc:
        raise UsageError(f"bad settings: {exc}") from None
    try:
        out = train(cfg, resume=resume)
    except (FileExistsError, FileNotFoundError, NotADirectoryError, CheckpointError, ValueError) as exc:
        if new_folder and out_dir.is_dir() and not (out_dir / "train_state.pt").exists():
            shutil.rmtree(out_dir, ignore_errors=True)
        raise UsageError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    except BaseException:
        if new_folder and out_dir.is_dir() and not (out_dir / "train_state.pt").exists():
            shutil.rmtree(out_dir, ignore_errors=True)
        raise
    finish()
    if is_main_process():
        print(f"wrote {out}")
    return 0


def run_vae(args) -> int:
    from mld_core.training.vae import VAETrainConfig, train_vae

    _check_run_options(args)
    _check_data(args.data)
    over = _overrides(args, VAETrainConfig, VAE_FLAGS)
    return _run(train_vae, lambda: _vae_config(args, over), args.out, args.resume, args.device)


def _vae_config(args, over: dict):
    from mld_core.models.transformer import TransformerConfig
    from mld_core.models.vae import VAEConfig
    from mld_core.training.vae import VAETrainConfig

    vae = VAEConfig(**over.pop("vae", {}))
    if args.layers or args.no_skip or args.latent_tokens:
        layers = args.layers or vae.encoder.layers
        skip = not args.no_skip
        vae.encoder = TransformerConfig(**{**vae.encoder.to_dict(), "layers": layers, "skip": skip})
        vae.decoder = TransformerConfig(**{**vae.decoder.to_dict(), "layers": layers, "skip": skip})
        vae.latent_tokens = args.latent_tokens or vae.latent_tokens
    cfg = VAETrainConfig(data=args.data, out=str(args.out), seed=args.seed, threads=args.threads, steps=args.steps,
                         minutes=args.minutes, vae=vae, init=_init_dir(args), **_where(args), **over)
    if args.lr:
        cfg.lr = args.lr
    cfg.bf16 = cfg.bf16 or args.bf16
    return cfg


def run_denoiser(args) -> int:
    from mld_core.training.denoiser import DenoiserTrainConfig, train_denoiser

    _check_run_options(args)
    _check_data(args.data)
    over = _overrides(args, DenoiserTrainConfig, DENOISER_FLAGS)
    return _run(train_denoiser, lambda: _denoiser_config(args, over), args.out, args.resume, args.device)


def _denoiser_config(args, over: dict):
    from mld_core.models.denoiser import DenoiserConfig
    from mld_core.models.transformer import TransformerConfig
    from mld_core.training.denoiser import DenoiserTrainConfig

    # an action-conditioned denoiser learns one class per label of the data's actions.json: the trainer counts them
    den = DenoiserConfig(**{"cond": args.cond, "num_actions": int(args.cond == "action"), **over.pop("denoiser", {})})
    if args.layers or args.no_skip or args.cross_attention:
        den.transformer = TransformerConfig(**{**den.transformer.to_dict(), "layers": args.layers or den.transformer.layers,
                                               "skip": not args.no_skip, "cross_attention": args.cross_attention})
    cfg = DenoiserTrainConfig(data=args.data, vae=_vae_dir(args.vae), out=str(args.out), cond=args.cond, seed=args.seed,
                              threads=args.threads, steps=args.steps, minutes=args.minutes, denoiser=den,
                              init=_init_dir(args), **_where(args), **over)
    if args.lr:
        cfg.lr = args.lr
    cfg.bf16 = cfg.bf16 or args.bf16
    return cfg


def run_draft(args) -> int:
    from mld_core.training.draft import DraftTrainConfig, install_draft, train_draft

    extra = {"bf16": True} if args.bf16 else {}
    return _run_distillation(args, DraftTrainConfig, train_draft, install_draft, "the Draft denoiser", extra)


def run_draft_text(args) -> int:
    from mld_core.training.draft_text import DraftTextTrainConfig, install_draft_text, train_draft_text

    return _run_distillation(args, DraftTextTrainConfig, train_draft_text, install_draft_text,
                             "the Draft's text encoder")


def _run_distillation(args, config_class, train, install, what: str, extra: dict | None = None) -> int:
    """train draft / draft-text: distil a part of the --teacher model folder into --out, then with --install copy
    the result into the teacher's folder."""
    _check_run_options(args)
    _check_data(args.data)
    teacher = _model_folder(args.teacher, "--teacher")
    over = {**_overrides(args, config_class, DISTILLATION_FLAGS), **(extra or {})}
    if args.lr is not None:
        over["lr"] = args.lr

    def make_config():  # every setting is checked here (the config's __post_init__), before any work
        return config_class(data=args.data, teacher=str(teacher), out=str(args.out), seed=args.seed,
                            threads=args.threads, steps=args.steps, minutes=args.minutes, **_where(args), **over)

    code = _run(train, make_config, args.out, args.resume, args.device)
    from mld_core.training.distributed import is_main_process

    if args.install and is_main_process():
        from mld_core.checkpoint import CheckpointError

        try:
            install(Path(args.out), teacher)
        except (CheckpointError, OSError, ValueError) as exc:
            raise UsageError(str(exc).splitlines()[0]) from None
        print(f"installed {what} into {teacher}")
    return code


def _stage_options(p, config_name: str) -> None:
    """The options train draft and train draft-text share."""
    _run_options(p)
    p.add_argument("--config", default=None, metavar="JSON_OR_FILE",
                   help=f"overrides of {config_name}: a JSON object, inline or in a file")


def register(groups) -> None:
    p = groups["train"].add_parser("vae", help="stage 1: the motion VAE")
    _common(p)
    p.add_argument("--latent-tokens", type=int, default=None, help="n in the latent's shape n x d (1, 2, 5, 7, 10)")
    p.set_defaults(func=run_vae)
    p = groups["train"].add_parser("denoiser", help="stage 2: the latent denoiser on frozen-encoder latents")
    _common(p)
    p.add_argument("--vae", required=True, help="the stage-1 run folder (or a model folder, or a bundled model's name)")
    p.add_argument("--cond", choices=("text", "action", "none"), default="text")
    p.add_argument("--cross-attention", action="store_true", help="condition through cross-attention, not concatenation")
    p.set_defaults(func=run_denoiser)
    p = groups["train"].add_parser("draft", help="Draft mode: distil a model's denoiser into a few-step consistency model")
    p.add_argument("--data", required=True, help="the HumanML3D-format folder the teacher was trained on")
    p.add_argument("--teacher", default=None, help="the model folder to distil (default: the bundled model)")
    p.add_argument("--out", required=True, help="the run folder (the teacher's folder plus draft.safetensors)")
    p.add_argument("--install", action="store_true",
                   help="when done, copy the Draft denoiser (fp16) and its config into the teacher's folder")
    p.add_argument("--bf16", action="store_true", help="bfloat16 autocast")
    _stage_options(p, "DraftTrainConfig")
    p.set_defaults(func=run_draft)
    p = groups["train"].add_parser("draft-text", help="Draft mode: distil the model's text encoder into fewer layers")
    p.add_argument("--data", required=True, help="a HumanML3D-format folder: its train captions are the corpus")
    p.add_argument("--teacher", default=None, help="the model folder whose text encoder to distil (default: bundled)")
    p.add_argument("--out", required=True, help="the run folder (draft_text.safetensors, log.jsonl)")
    p.add_argument("--install", action="store_true",
                   help="when done, copy the layers (fp16) into the teacher's folder and set draft.text_layers")
    _stage_options(p, "DraftTextTrainConfig")
    p.set_defaults(func=run_draft_text)
