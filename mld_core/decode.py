"""Decode: diffusion-space latents z_0 (B, n, d) -> denormalised features (B, T, F) -> joints (B, T, 22, 3), and
features back to latents. x = D(z_0 / latent_scale + latent_mean) * std + mean, zero beyond each length.

The take fixes (mld_core.take_fixes) read the model through a :class:`LatentDecoder`: plain decodes, differentiable
ones (stepping and constraints take Adam steps through the decoder) and joints.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from mld_core.inputs import InputError
from mld_core.motion.features import features_to_joints


class LatentDecoder:
    """A model's VAE as the decode stage: Final's decoder, or the Draft's (its own precision) for a Draft's takes.
    ``config`` (the model's) is read when called (latent_scale, latent_mean, fps); ``mean``, ``std`` (F,) are its
    features' normalisation."""

    def __init__(self, config, vae, draft_vae, device: torch.device, mean: np.ndarray, std: np.ndarray):
        self.config = config
        self.vae, self.draft_vae = vae, draft_vae
        self.device = device
        self.mean, self.std = mean, std

    @property
    def fps(self) -> int:
        return self.config.fps

    def normalize(self, features: np.ndarray) -> np.ndarray:
        return (features - self.mean) / self.std

    def denormalize(self, features: np.ndarray) -> np.ndarray:
        return features * self.std + self.mean

    @torch.inference_mode()
    def latents(self, features: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        """Denormalised feature clips [(T_i, F)] -> their VAE means in diffusion space (B, n, d) and lengths (B,):
        the inverse of :meth:`features` (a reconstruction is one after the other)."""
        lengths = torch.tensor([len(f) for f in features])
        x = np.zeros((len(features), int(lengths.max()), self.config.vae.feature_dim), np.float32)  # (B, T, F)
        for i, f in enumerate(features):
            x[i, : len(f)] = self.normalize(f)
        mu, _ = self.vae.encode(torch.from_numpy(x).to(self.device), lengths.to(self.device))  # (B, n, d)
        return (mu.float() - self.config.latent_mean) * self.config.latent_scale, lengths

    @torch.no_grad()
    def features(self, z: torch.Tensor, lengths: torch.Tensor, draft: bool = False) -> np.ndarray:
        """Diffusion-space latents (B, n, d) -> denormalised features (B, T, F), zero beyond each length; ``draft``
        decodes with the Draft's decoder (its precision)."""
        vae = self.draft_vae if draft else self.vae
        mu = z / self.config.latent_scale + self.config.latent_mean
        x = vae.decode(mu, lengths).float().cpu().numpy()
        feats = self.denormalize(x)
        for i, n in enumerate(lengths.tolist()):
            feats[i, n:] = 0.0
        return feats.astype(np.float32)

    def normalised_with_grad(self, latent: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """Normalised features (B, max length, F) of diffusion-space latents (B, n, d), differentiable (fp32)."""
        x = self.vae.decode(latent / self.config.latent_scale + self.config.latent_mean, lengths).float()
        return x[:, : int(lengths.max())]

    def mean_std(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The features' mean and std (F,) as float32 tensors on the model's device (to denormalise with grad)."""
        return tuple(torch.tensor(a, dtype=torch.float32, device=self.device) for a in (self.mean, self.std))

    @staticmethod
    def joints(features: np.ndarray, lengths: list) -> np.ndarray:
        """Joints (B, T, 22, 3) of denormalised features (B, T, F); frames beyond a length repeat its last frame."""
        B, T = features.shape[:2]
        joints = np.zeros((B, T, 22, 3), np.float32)
        for i, n in enumerate(lengths):
            joints[i, :n] = features_to_joints(features[i, :n])
            joints[i, n:] = joints[i, n - 1]
        if not np.isfinite(joints).all():  # never hand a take of NaN/inf joints to a writer
            raise InputError("the model produced non-finite motion (NaN or inf): check the guidance scale and the "
                             "model's config.json (mean/std)")
        return joints
