"""Training targets that fold a model's verb guidance into its own text denoiser.

A model with a verb denoiser (config ``verb_guide``, ``mld_core.condition.verb_guide``) samples a prompt that names
one of its labels with two denoisers a step: eps = eps(null) + s (eps(text) - eps(null)) + s_a (eps_a(label) -
eps_a(null)). A text denoiser trained towards eps(text) + (s_a / s) (eps_a(label) - eps_a(null)) on the captions that
name a label, and towards the model's own eps(text) or eps(null) on every other row, gives that step alone when it is
guided at s (guidance distillation): the verb then costs no second pass, and the model needs no verb denoiser.
"""

from __future__ import annotations

import copy
import hashlib
from dataclasses import dataclass
from pathlib import Path

import torch

from mld_core.checkpoint import VERB_WEIGHTS, ModelConfig, load_weights
from mld_core.condition.verb_guide import VerbGuide
from mld_core.models.denoiser import LatentDenoiser


@dataclass
class VerbFold:
    """The model's own denoiser (frozen), its verb ``guide`` and the guidance scale s it is sampled at; each
    caption's label id of the guide (-1: names none)."""

    teacher: LatentDenoiser
    guide: VerbGuide
    guidance_scale: float
    caption_labels: torch.Tensor  # (captions,) long

    @torch.no_grad()
    def targets(self, z_t: torch.Tensor, t: torch.Tensor, lengths: torch.Tensor, text, drop: torch.Tensor,
                captions: torch.Tensor) -> torch.Tensor:
        """The noise a row's denoiser is to predict at z_t (B, n, d), timesteps t (B,): the teacher's, with the
        verb term added on the rows whose condition is kept and whose caption (ids ``captions`` (B,)) names a
        label."""
        cond = self.teacher.condition_tokens(len(z_t), text=text, drop=drop)
        eps = self.teacher(z_t, t, cond, lengths).float()  # (B, n, d)
        return self.with_verb_term(eps, z_t, t, lengths, captions, (~drop).float())

    def with_verb_term(self, eps: torch.Tensor, z_t: torch.Tensor, t: torch.Tensor, lengths: torch.Tensor,
                       captions: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        """``eps`` (B, n, d) plus ``weight`` (B,) x (s_a / s) x (eps_a(label) - eps_a(null)) on the rows whose
        caption (ids ``captions`` (B,)) names a label; rows of weight 0 are left as they are. A weight of 1 gives
        the fold's text target; the guidance scale w gives the term of a step guided at w (the Draft's teacher)."""
        labels = self.caption_labels[captions]
        rows = torch.nonzero((labels >= 0) & (weight != 0)).squeeze(1)  # (B',)
        if not len(rows):
            return eps
        eps = eps.clone()
        term = self._verb_term(z_t[rows], t[rows], lengths[rows], labels[rows])  # (B', n, d)
        eps[rows] += (weight[rows, None, None] * self.guide.scale / self.guidance_scale) * term
        return eps

    def _verb_term(self, z_t, t, lengths, labels) -> torch.Tensor:
        """eps_a(label) - eps_a(null) (B', n, d) from one pass over [null; label] rows."""
        g = self.guide.denoiser
        cond = torch.cat([g.null_tokens(len(z_t)), g.condition_tokens(len(z_t), actions=labels)])
        eps_null, eps_label = g(torch.cat([z_t, z_t]), torch.cat([t, t]), cond,
                                torch.cat([lengths, lengths])).float().chunk(2)  # each (B', n, d)
        return eps_label - eps_null


def check_foldable(model_dir: Path, config: ModelConfig, vae_dir: Path) -> None:
    """A model folder ``model_dir`` (``config`` its config) whose verb guide a run on ``vae_dir``'s VAE can fold;
    a model without a verb denoiser, a denoiser that reads verb hints, or another VAE is refused (ValueError)."""
    if config.verb_guide is None:
        raise ValueError(f"fold_verb_guide: {model_dir} has no verb denoiser (config verb_guide) to fold")
    if config.denoiser is None or config.denoiser.cond != "text" or config.denoiser.verb_hints:
        raise ValueError(f"fold_verb_guide: {model_dir}'s denoiser must read text without verb hints")
    if _digest(model_dir / "vae.safetensors") != _digest(vae_dir / "vae.safetensors"):
        raise ValueError(f"fold_verb_guide: --vae {vae_dir} is not {model_dir}'s VAE (the verb denoiser samples "
                         "that VAE's latents)")


def load_verb_fold(model_dir: Path, config: ModelConfig, vae_dir: Path, captions: list[str],
                   device: torch.device) -> VerbFold:
    """The fold of the model folder ``model_dir`` (``config`` its config) for a run on ``vae_dir``'s VAE
    (``check_foldable``), each of ``captions`` with the label it names."""
    check_foldable(model_dir, config, vae_dir)
    teacher = LatentDenoiser(copy.deepcopy(config.denoiser))
    load_weights(model_dir / "denoiser.safetensors", teacher)
    g = config.verb_guide
    verb = LatentDenoiser(copy.deepcopy(g.denoiser))
    load_weights(model_dir / VERB_WEIGHTS, verb)
    for m in (teacher, verb):
        m.eval().requires_grad_(False).to(device)
    guide = VerbGuide(verb, list(g.actions), float(g.scale))
    rows, labels = guide.rows_and_labels(captions)
    caption_labels = torch.full((len(captions),), -1, dtype=torch.long)
    caption_labels[rows] = labels
    return VerbFold(teacher, guide, float(config.guidance_scale), caption_labels.to(device))


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
