"""Transformer stacks with UNet-like long skip connections (MLD's SkipTransformerEncoder/Decoder).

With ``skip=True`` and an odd number of layers ``2k + 1``: k input blocks push their outputs, one middle block,
then k output blocks each concatenate the popped skip (2d) and project back to d before the layer.
With ``skip=False`` the same layers run as a plain stack. Batch-first: (B, S, d).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import nn


@dataclass
class TransformerConfig:
    dim: int = 256
    heads: int = 4
    ff_dim: int = 1024
    layers: int = 5
    dropout: float = 0.1
    skip: bool = True
    cross_attention: bool = False  # decoder layers (self + cross attention) instead of encoder layers

    def __post_init__(self):
        if self.skip and self.layers % 2 != 1:
            raise ValueError(f"long skips need an odd number of layers, got {self.layers}")
        if self.dim % self.heads:
            raise ValueError(f"dim {self.dim} is not divisible by heads {self.heads}")

    def to_dict(self) -> dict:
        return asdict(self)


def _layer(cfg: TransformerConfig) -> nn.Module:
    kind = nn.TransformerDecoderLayer if cfg.cross_attention else nn.TransformerEncoderLayer
    return kind(cfg.dim, cfg.heads, cfg.ff_dim, cfg.dropout, activation="gelu", batch_first=True, norm_first=True)


class SkipTransformer(nn.Module):
    """Self-attention (or self + cross-attention) stack with optional long skips and a final LayerNorm."""

    def __init__(self, config: TransformerConfig):
        super().__init__()
        self.config = config
        n_side = (config.layers - 1) // 2 if config.skip else 0
        self.input_blocks = nn.ModuleList(_layer(config) for _ in range(n_side))
        self.middle_blocks = nn.ModuleList(_layer(config) for _ in range(config.layers - 2 * n_side))
        self.output_blocks = nn.ModuleList(_layer(config) for _ in range(n_side))
        self.skip_projections = nn.ModuleList(nn.Linear(2 * config.dim, config.dim) for _ in range(n_side))
        self.norm = nn.LayerNorm(config.dim)

    def _run(self, layer: nn.Module, x, padding_mask, memory, memory_padding_mask):
        if self.config.cross_attention:
            return layer(x, memory, tgt_key_padding_mask=padding_mask, memory_key_padding_mask=memory_padding_mask)
        return layer(x, src_key_padding_mask=padding_mask)

    def forward(self, x: torch.Tensor, padding_mask: torch.Tensor | None = None, memory: torch.Tensor | None = None,
                memory_padding_mask: torch.Tensor | None = None) -> torch.Tensor:
        """x (B, S, d); padding_mask (B, S) True where padded; memory (B, M, d) for cross-attention."""
        if self.config.cross_attention and memory is None:
            raise ValueError("a cross-attention stack needs memory")
        skips = []
        for layer in self.input_blocks:
            x = self._run(layer, x, padding_mask, memory, memory_padding_mask)
            skips.append(x)
        for layer in self.middle_blocks:
            x = self._run(layer, x, padding_mask, memory, memory_padding_mask)
        for layer, project in zip(self.output_blocks, self.skip_projections):
            x = project(torch.cat([x, skips.pop()], dim=-1))  # (B, S, 2d) -> (B, S, d)
            x = self._run(layer, x, padding_mask, memory, memory_padding_mask)
        return self.norm(x)


def sinusoidal_embedding(positions: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal features of (possibly fractional) positions: (...,) -> (..., dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=positions.device) / half)
    angles = positions.float()[..., None] * freqs  # (..., half)
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)
