"""Tiny seeded models for fast tests of everything built on the pipeline (add-on, evaluation, CLI)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from mld_core.checkpoint import DraftConfig, ModelConfig, save_model, save_weights
from mld_core.models.denoiser import DenoiserConfig, LatentDenoiser
from mld_core.models.transformer import TransformerConfig
from mld_core.models.vae import MotionVAE, VAEConfig

TINY_TEXT_ENCODER = {"kind": "minilm-random", "seed": 0, "hidden": 32, "layers": 2, "heads": 2, "vocab_path": "builtin"}


def tiny_config(cond: str = "text", actions: tuple = ("walk", "run", "wave"), latent_tokens: int = 1,
                layers: int = 1, dim: int = 32) -> ModelConfig:
    block = dict(dim=dim, heads=2, ff_dim=2 * dim, layers=layers, dropout=0.0)
    vae = VAEConfig(latent_tokens=latent_tokens, latent_dim=dim, encoder=TransformerConfig(**block),
                    decoder=TransformerConfig(**block, cross_attention=True))
    den = DenoiserConfig(latent_tokens=latent_tokens, latent_dim=dim, cond=cond, text_dim=TINY_TEXT_ENCODER["hidden"],
                         text_pool_tokens=2 if cond == "text" else 0, num_actions=len(actions) if cond == "action" else 0,
                         transformer=TransformerConfig(**block))
    # Mean/std of a plausible motion: standing at 0.9 m root height, unit-ish spread elsewhere.
    mean = np.zeros(263, np.float32)
    mean[3] = 0.9
    std = np.full(263, 0.05, np.float32)
    return ModelConfig(model_id=f"tiny-{cond}", vae=vae, denoiser=den,
                       text_encoder=dict(TINY_TEXT_ENCODER) if cond == "text" else {},
                       mean=mean.tolist(), std=std.tolist(), actions=list(actions) if cond == "action" else [],
                       num_inference_steps=4)


def tiny_model(model_dir: str | Path, seed: int = 0, cond: str = "text", draft: bool = False, **kwargs) -> Path:
    """Build and save a tiny random model folder; returns its path. ``draft`` adds a random Draft denoiser (whose
    guidance input has effect)."""
    from dataclasses import replace

    config = tiny_config(cond, **kwargs)
    torch.manual_seed(seed)
    vae = MotionVAE(config.vae)
    denoiser = LatentDenoiser(config.denoiser)
    if draft:
        config.draft = DraftConfig(denoiser=replace(config.denoiser, guidance_input=True), num_inference_steps=2)
        student = LatentDenoiser(config.draft.denoiser)
        torch.nn.init.normal_(student.guidance_mlp[2].weight, std=0.5)
        Path(model_dir).mkdir(parents=True, exist_ok=True)
        save_weights(Path(model_dir) / "draft.safetensors", student)
    return save_model(model_dir, config, vae, denoiser, card="# tiny random test model\n")


def tiny_pipeline(model_dir: str | Path, seed: int = 0, cond: str = "text", draft_precision: str = "fp32", **kwargs):
    """A pipeline over a tiny random model saved in ``model_dir`` (for tests; its motions are noise). Its Draft runs
    in ``draft_precision`` (fp32 by default, so tests give the same numbers on every CPU)."""
    from mld_core.pipeline import MLDPipeline

    return MLDPipeline.from_pretrained(tiny_model(model_dir, seed, cond, **kwargs), draft_precision=draft_precision)
