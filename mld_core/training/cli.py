"""``python -m mld_core train vae|denoiser``: one training entry per stage."""

from __future__ import annotations

import json
from pathlib import Path


def _common(p) -> None:
    p.add_argument("--data", required=True, help="a HumanML3D-format folder (HumanML3D, KIT-ML, or `data prepare` output)")
    p.add_argument("--out", required=True, help="the run folder to write (a complete model folder when done)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its train_state.pt")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    p.add_argument("--steps", type=int, default=None, help="stop after this many optimiser steps")
    p.add_argument("--minutes", type=float, default=None, help="stop after this much wall time")
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--layers", type=int, default=None, help="transformer layers (odd with skips)")
    p.add_argument("--no-skip", action="store_true", help="turn the long skip connections off")
    p.add_argument("--bf16", action="store_true", help="bfloat16 autocast (about 2x faster on CPUs with AVX512-BF16 or AMX)")
    p.add_argument("--config", type=Path, default=None, help="JSON overrides of the stage's config dataclass")


def _check_data(path: str) -> None:
    from mld_core.cli import UsageError

    root = Path(path)
    missing = [n for n in ("new_joint_vecs", "train.txt", "Mean.npy", "Std.npy") if not (root / n).exists()]
    if missing:
        raise UsageError(f"{root} is not a HumanML3D-format folder (missing {', '.join(missing)})")


def _overrides(args) -> dict:
    if args.config is None:
        return {}
    try:
        return json.loads(args.config.read_text())
    except (OSError, ValueError) as exc:
        from mld_core.cli import UsageError

        raise UsageError(f"cannot read --config {args.config}: {exc}") from None


def _run(train, cfg, resume: bool) -> int:
    from mld_core.checkpoint import CheckpointError
    from mld_core.cli import UsageError

    try:
        out = train(cfg, resume=resume)
    except (FileExistsError, FileNotFoundError, CheckpointError) as exc:
        raise UsageError(str(exc)) from None
    print(f"wrote {out}")
    return 0


def run_vae(args) -> int:
    from mld_core.models.transformer import TransformerConfig
    from mld_core.models.vae import VAEConfig
    from mld_core.training.vae import VAETrainConfig, train_vae

    _check_data(args.data)
    over = _overrides(args)
    vae = VAEConfig(**over.pop("vae", {}))
    if args.layers or args.no_skip or args.latent_tokens:
        layers = args.layers or vae.encoder.layers
        skip = not args.no_skip
        vae.encoder = TransformerConfig(**{**vae.encoder.to_dict(), "layers": layers, "skip": skip})
        vae.decoder = TransformerConfig(**{**vae.decoder.to_dict(), "layers": layers, "skip": skip})
        vae.latent_tokens = args.latent_tokens or vae.latent_tokens
    cfg = VAETrainConfig(data=args.data, out=str(args.out), seed=args.seed, threads=args.threads, steps=args.steps,
                         minutes=args.minutes, vae=vae, **over)
    if args.lr:
        cfg.lr = args.lr
    cfg.bf16 = cfg.bf16 or args.bf16
    return _run(train_vae, cfg, args.resume)


def run_denoiser(args) -> int:
    from mld_core.models.denoiser import DenoiserConfig
    from mld_core.models.transformer import TransformerConfig
    from mld_core.training.denoiser import DenoiserTrainConfig, train_denoiser

    _check_data(args.data)
    over = _overrides(args)
    den = DenoiserConfig(**{"cond": args.cond, **over.pop("denoiser", {})})
    if args.layers or args.no_skip or args.cross_attention:
        den.transformer = TransformerConfig(**{**den.transformer.to_dict(), "layers": args.layers or den.transformer.layers,
                                               "skip": not args.no_skip, "cross_attention": args.cross_attention})
    cfg = DenoiserTrainConfig(data=args.data, vae=str(args.vae), out=str(args.out), cond=args.cond, seed=args.seed,
                              threads=args.threads, steps=args.steps, minutes=args.minutes, denoiser=den, **over)
    if args.lr:
        cfg.lr = args.lr
    cfg.bf16 = cfg.bf16 or args.bf16
    return _run(train_denoiser, cfg, args.resume)


def register(groups) -> None:
    p = groups["train"].add_parser("vae", help="stage 1: the motion VAE")
    _common(p)
    p.add_argument("--latent-tokens", type=int, default=None, help="n in the latent's shape n x d (1, 2, 5, 7, 10)")
    p.set_defaults(func=run_vae)
    p = groups["train"].add_parser("denoiser", help="stage 2: the latent denoiser on frozen-encoder latents")
    _common(p)
    p.add_argument("--vae", required=True, help="the stage-1 run folder")
    p.add_argument("--cond", choices=("text", "action", "none"), default="text")
    p.add_argument("--cross-attention", action="store_true", help="condition through cross-attention, not concatenation")
    p.set_defaults(func=run_denoiser)
