"""Transformer stacks with UNet-like long skip connections (MLD's SkipTransformerEncoder/Decoder).

With ``skip=True`` and an odd number of layers ``2k + 1``: k input blocks push their outputs, one middle block,
then k output blocks each concatenate the popped skip (2d) and project back to d before the layer.
With ``skip=False`` the same layers run as a plain stack. Batch-first: (B, S, d).
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
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
        self._packed: dict = {}  # id(layer) -> prepacked weights; see pack_for_cpu_inference
        self._packed_projections: list = []  # the skip projections' prepacked (weight, bias), in order
        self._fixed_queries: dict = {}  # key -> the first layer's self-attention of fixed queries (fixed_queries)
        self.register_load_state_dict_post_hook(lambda module, _keys: module._forget_derived())

    def _plain(self, padding_mask, memory_padding_mask) -> bool:
        return padding_mask is None and memory_padding_mask is None and not self.training and not torch.is_grad_enabled()

    def _run(self, layer: nn.Module, x, padding_mask, memory, memory_padding_mask, self_attended=None):
        plain = self._plain(padding_mask, memory_padding_mask)
        if self.config.cross_attention:
            if plain:
                return decoder_layer_inference(layer, x, memory, self._packed.get(id(layer)), self_attended)
            return layer(x, memory, tgt_key_padding_mask=padding_mask, memory_key_padding_mask=memory_padding_mask)
        if plain:
            return encoder_layer_inference(layer, x, self._packed.get(id(layer)))
        return layer(x, src_key_padding_mask=padding_mask)

    # -- CPU inference ------------------------------------------------------------------------------------------
    def pack_for_cpu_inference(self, dtype: torch.dtype | None = None) -> bool:
        """Keep oneDNN-prepacked copies of the layers' weights for inference without padding masks (the denoiser's
        steps, the decoding of rows of one length): each matrix is reordered once instead of on every call, which
        halves a step's time on a CPU at the few tokens a step runs. ``dtype`` (e.g. bfloat16) runs the matrix
        products, and the attention between them, in that precision while layer norms and the residual stream keep
        the module's, much as autocast does. A snapshot: ``train()`` drops it. False where oneDNN is unavailable."""
        self._forget_derived()
        if not _packing_available(self, dtype):
            return False
        d = self.config.dim
        for layer in [*self.input_blocks, *self.middle_blocks, *self.output_blocks]:
            attn = layer.self_attn
            packed = {
                "in": _pack(attn.in_proj_weight, attn.in_proj_bias, dtype),
                "out": _pack(attn.out_proj.weight, attn.out_proj.bias, dtype),
                "ff1": _pack(layer.linear1.weight, layer.linear1.bias, dtype),
                "ff2": _pack(layer.linear2.weight, layer.linear2.bias, dtype),
            }
            if self.config.cross_attention:
                cross = layer.multihead_attn
                packed["cross_q"] = _pack(cross.in_proj_weight[:d], cross.in_proj_bias[:d], dtype)
                packed["cross_kv"] = _pack(cross.in_proj_weight[d:], cross.in_proj_bias[d:], dtype)
                packed["cross_out"] = _pack(cross.out_proj.weight, cross.out_proj.bias, dtype)
            self._packed[id(layer)] = packed
        self._packed_projections = [_pack(p.weight, p.bias, dtype) for p in self.skip_projections]
        return True

    def train(self, mode: bool = True):
        if mode:
            self._forget_derived()
        return super().train(mode)

    def _apply(self, fn, *args, **kwargs):  # .to(), .half(), ...: what was derived from the weights is stale
        self._forget_derived()
        return super()._apply(fn, *args, **kwargs)

    def _forget_derived(self) -> None:
        """Drop the prepacked weights and cached first-layer queries (new weights, dtype or device)."""
        self._packed, self._packed_projections, self._fixed_queries = {}, [], {}

    def forward(self, x: torch.Tensor, padding_mask: torch.Tensor | None = None, memory: torch.Tensor | None = None,
                memory_padding_mask: torch.Tensor | None = None, fixed_queries=None) -> torch.Tensor:
        """x (B, S, d); padding_mask (B, S) True where padded; memory (B, M, d) for cross-attention.
        ``fixed_queries``: a key saying that x is the same on every call with it (the VAE decoder's frame queries
        of one length): a cross-attention stack then computes its first layer's self-attention once per key."""
        if self.config.cross_attention and memory is None:
            raise ValueError("a cross-attention stack needs memory")
        first = None
        if fixed_queries is not None and self.config.cross_attention and self._plain(padding_mask, memory_padding_mask):
            first = self._first_self_attention(x, fixed_queries)
        skips = []
        for layer in self.input_blocks:
            x, first = self._run(layer, x, padding_mask, memory, memory_padding_mask, first), None
            skips.append(x)
        for layer in self.middle_blocks:
            x, first = self._run(layer, x, padding_mask, memory, memory_padding_mask, first), None
        for i, layer in enumerate(self.output_blocks):
            x = self._project(i, torch.cat([x, skips.pop()], dim=-1), padding_mask, memory_padding_mask)
            x = self._run(layer, x, padding_mask, memory, memory_padding_mask)
        return self.norm(x)

    PACKED_PROJECTION_TOKENS = 32  # measured: at fewer tokens the plain product is as fast as the packed one

    def _project(self, i: int, x: torch.Tensor, padding_mask, memory_padding_mask) -> torch.Tensor:
        """Long skip i's projection (B, S, 2d) -> (B, S, d), on its prepacked weights for long sequences (the VAE
        decoder's frames); the few tokens of a denoising step keep the plain product at any batch size."""
        project = self.skip_projections[i]
        if not self._packed_projections or x.shape[1] < self.PACKED_PROJECTION_TOKENS \
                or not self._plain(padding_mask, memory_padding_mask):
            return project(x)
        packed = self._packed_projections[i]
        return _linear(x, project.weight, project.bias, packed)

    def _first_self_attention(self, x: torch.Tensor, key) -> torch.Tensor:
        """x + the first layer's self-attention of x (B, S, d), computed for the first row once per key."""
        cached = self._fixed_queries.get(key)
        if cached is None or cached.dtype != x.dtype:
            layer = (list(self.input_blocks) + list(self.middle_blocks))[0]
            cached = self._fixed_queries[key] = decoder_self_attention(layer, x[:1], self._packed.get(id(layer)))
        return cached.expand(len(x), -1, -1)


def packing_available() -> bool:
    """Whether this torch build has oneDNN's prepacked linear ops."""
    return (torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_reorder_linear_weight")
            and hasattr(torch.ops.mkldnn, "_linear_pointwise"))


def native_bf16() -> bool:
    """Whether this CPU computes bfloat16 natively (AVX512-BF16 or AMX-BF16); elsewhere bfloat16 is emulated and
    slower than float32."""
    try:
        caps = torch.cpu.get_capabilities()
    except (AttributeError, RuntimeError):
        return False
    return bool(caps.get("avx512_bf16") or caps.get("amx_bf16"))


def _packing_available(module: nn.Module, dtype: torch.dtype | None = None) -> bool:
    p = next(module.parameters(), None)
    return (p is not None and p.device.type == "cpu" and packing_available()
            and packs_in(dtype if dtype is not None else p.dtype))


@functools.cache
def packs_in(dtype: torch.dtype) -> bool:
    """Whether oneDNN prepacks weights of ``dtype`` on this CPU (bfloat16 needs AVX512-BW/VL/DQ or AVX-NE-CONVERT;
    elsewhere the layers run unpacked)."""
    try:
        torch.ops.mkldnn._reorder_linear_weight(torch.zeros(16, 16, dtype=dtype), 16)
    except RuntimeError:
        return False
    return True


def _pack(weight: torch.Tensor, bias: torch.Tensor | None, dtype: torch.dtype | None = None) -> tuple:
    """oneDNN-prepacked (weight, bias), cast to ``dtype`` first when given (the matrix products' precision)."""
    with torch.no_grad():
        weight, bias = weight.detach(), bias.detach() if bias is not None else None
        if dtype is not None:
            weight, bias = weight.to(dtype), bias.to(dtype) if bias is not None else None
        return torch.ops.mkldnn._reorder_linear_weight(weight, 16), bias


def _linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, packed: tuple | None,
            gelu: bool = False) -> torch.Tensor:
    """x @ weight.T + bias (then GELU), on the prepacked weights when given; packed weights of another precision
    than x (a float32 module with bfloat16 products) take x in theirs and return the result in x's."""
    if packed is not None:
        compute = packed[0].dtype
        y = torch.ops.mkldnn._linear_pointwise(x.to(compute), packed[0], packed[1], "gelu" if gelu else "none", [],
                                               "none" if gelu else "")
        return y.to(x.dtype)
    y = F.linear(x, weight, bias)
    return F.gelu(y) if gelu else y


def encoder_layer_inference(layer: nn.TransformerEncoderLayer, x: torch.Tensor, packed: dict | None = None
                            ) -> torch.Tensor:
    """The same pre-norm encoder layer as ``layer(x)`` in eval mode without a padding mask, written out with
    plain functional ops in the parameters' dtype (bfloat16 or float32), optionally on prepacked weights
    (:meth:`SkipTransformer.pack_for_cpu_inference`). At the few tokens a denoising step runs this is faster on a
    CPU than PyTorch's fused fast path: 1.3x unpacked in float32, 2.2x in bfloat16."""
    B, S, d = x.shape
    attn = layer.self_attn
    pk = packed or {}
    c = _compute_dtype(pk, x)  # each sub-block in c; the residual stream stays in x's dtype
    h = F.layer_norm(x, (d,), layer.norm1.weight, layer.norm1.bias, layer.norm1.eps).to(c)
    qkv = _linear(h, attn.in_proj_weight, attn.in_proj_bias, pk.get("in"))  # (B, S, 3d)
    q, k, v = qkv.view(B, S, 3, attn.num_heads, d // attn.num_heads).permute(2, 0, 3, 1, 4)  # each (B, H, S, d/H)
    a = F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(B, S, d)  # (B, S, d)
    x = x + _linear(a, attn.out_proj.weight, attn.out_proj.bias, pk.get("out")).to(x.dtype)
    h = F.layer_norm(x, (d,), layer.norm2.weight, layer.norm2.bias, layer.norm2.eps).to(c)
    h = _linear(h, layer.linear1.weight, layer.linear1.bias, pk.get("ff1"), gelu=True)  # (B, S, ff)
    return x + _linear(h, layer.linear2.weight, layer.linear2.bias, pk.get("ff2")).to(x.dtype)


def sinusoidal_embedding(positions: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal features of (possibly fractional) positions: (...,) -> (..., dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=positions.device) / half)
    angles = positions.float()[..., None] * freqs  # (..., half)
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)


def _attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, heads: int,
               mask: torch.Tensor | None = None) -> torch.Tensor:
    """Multi-head attention of q (B, S, d) over k, v (B, M, d) -> (B, S, d); ``mask`` (B, 1, 1, M) True = attend."""
    B, S, d = q.shape
    M = k.shape[1]
    q = q.reshape(B, S, heads, d // heads).transpose(1, 2)  # (B, H, S, d/H)
    k, v = (t.reshape(B, M, heads, d // heads).transpose(1, 2) for t in (k, v))  # (B, H, M, d/H)
    return F.scaled_dot_product_attention(q, k, v, attn_mask=mask).transpose(1, 2).reshape(B, S, d)


def decoder_self_attention(layer: nn.TransformerDecoderLayer, x: torch.Tensor, packed: dict | None = None
                           ) -> torch.Tensor:
    """x + the self-attention block of a pre-norm decoder layer (eval mode, no padding mask): (B, S, d)."""
    d = x.shape[-1]
    pk = packed or {}
    attn = layer.self_attn
    c = _compute_dtype(pk, x)
    h = F.layer_norm(x, (d,), layer.norm1.weight, layer.norm1.bias, layer.norm1.eps).to(c)
    q, k, v = _linear(h, attn.in_proj_weight, attn.in_proj_bias, pk.get("in")).chunk(3, dim=-1)  # each (B, S, d)
    a = _attention(q, k, v, attn.num_heads)
    return x + _linear(a, attn.out_proj.weight, attn.out_proj.bias, pk.get("out")).to(x.dtype)


def decoder_layer_inference(layer: nn.TransformerDecoderLayer, x: torch.Tensor, memory: torch.Tensor,
                            packed: dict | None = None, self_attended: torch.Tensor | None = None) -> torch.Tensor:
    """The same pre-norm decoder layer as ``layer(x, memory)`` in eval mode without padding masks, in plain
    functional ops, optionally on prepacked weights (the VAE decoder's frames reading the latent tokens).
    ``self_attended``: decoder_self_attention(layer, x), when already known."""
    d = x.shape[-1]
    pk = packed or {}
    cross = layer.multihead_attn
    c = _compute_dtype(pk, x)  # each sub-block in c; the residual stream stays in x's dtype
    x = decoder_self_attention(layer, x, pk) if self_attended is None else self_attended
    h = F.layer_norm(x, (d,), layer.norm2.weight, layer.norm2.bias, layer.norm2.eps).to(c)
    q = _linear(h, cross.in_proj_weight[:d], cross.in_proj_bias[:d], pk.get("cross_q"))  # (B, S, d)
    k, v = _linear(memory.to(c), cross.in_proj_weight[d:], cross.in_proj_bias[d:], pk.get("cross_kv")).chunk(2, -1)
    a = _attention(q, k, v, cross.num_heads)
    x = x + _linear(a, cross.out_proj.weight, cross.out_proj.bias, pk.get("cross_out")).to(x.dtype)
    h = F.layer_norm(x, (d,), layer.norm3.weight, layer.norm3.bias, layer.norm3.eps).to(c)
    h = _linear(h, layer.linear1.weight, layer.linear1.bias, pk.get("ff1"), gelu=True)  # (B, S, ff)
    return x + _linear(h, layer.linear2.weight, layer.linear2.bias, pk.get("ff2")).to(x.dtype)


def _compute_dtype(packed: dict, x: torch.Tensor) -> torch.dtype:
    """The precision of a layer's matrix products: its prepacked weights' (pack_for_cpu_inference), else x's."""
    first = next(iter(packed.values()), None)
    return first[0].dtype if first is not None else x.dtype
