"""Latent denoiser of MLD: predicts the noise eps added to the latent z_t, given the timestep and a condition.

Tokens: [timestep (+ target length) ; condition tokens ; latent tokens] through a SkipTransformer (concatenation,
the paper's default), or [timestep ; latent tokens] attending to the condition tokens (``cross_attention=True``).

Conditions (``cond``): "text" - the frozen sentence encoder's pooled vector as one token, plus ``text_pool_tokens``
tokens attention-pooled from its per-token features (the pooled vector alone barely tells "left" from "right");
"action" - a learned embedding per class; "none" - unconditional. A text denoiser with ``verb_hints`` also reads the
checked verb the prompt names (``mld_core.condition.verb_hint``): a learned vector per verb added to its first
condition token, zero for a prompt naming none (the sentence alone then, as without hints). Every kind has a learned
null condition used for classifier-free guidance (condition dropout in training, the unconditional branch at
sampling).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from mld_core.models.transformer import SkipTransformer, TransformerConfig, _attention, sinusoidal_embedding


@dataclass
class DenoiserConfig:
    latent_tokens: int = 1
    latent_dim: int = 256
    cond: str = "text"  # text | action | none
    text_dim: int = 384
    text_pool_tokens: int = 4  # 0: pooled vector only
    max_text_tokens: int = 32  # token features beyond this are not pooled (the same cut in training and sampling)
    num_actions: int = 0
    verb_hints: list = field(default_factory=list)  # text only: the checked verbs read as hints (id = 1 + index)
    length_conditioning: bool = True
    max_frames: int = 196
    cond_dropout: float = 0.1
    guidance_input: bool = False  # the guidance scale is an input (a Draft denoiser: guidance costs one pass)
    transformer: TransformerConfig = field(default_factory=lambda: TransformerConfig(layers=5))

    def __post_init__(self):
        if isinstance(self.transformer, dict):
            self.transformer = TransformerConfig(**self.transformer)
        if self.cond not in ("text", "action", "none"):
            raise ValueError(f"cond must be text, action or none, got {self.cond!r}")
        if self.cond == "action" and self.num_actions < 1:
            raise ValueError("an action-conditioned denoiser needs num_actions >= 1")
        self.verb_hints = list(self.verb_hints)
        if self.verb_hints and self.cond != "text":
            raise ValueError("verb hints go with a text-conditioned denoiser only")

    @property
    def cond_tokens(self) -> int:
        return 1 + self.text_pool_tokens if self.cond == "text" else 1

    def to_dict(self) -> dict:
        return asdict(self)


class AttentionPool(nn.Module):
    """K learned queries attend over a padded token sequence: (B, L, d) -> (B, K, d)."""

    def __init__(self, dim: int, heads: int, k: int):
        super().__init__()
        self.queries = nn.Parameter(torch.randn(k, dim) * 0.02)
        self.attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.norm = nn.LayerNorm(dim)
        self._fold, self._fold_key = None, None  # see pool_projected

    def forward(self, tokens: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        q = self.queries.expand(tokens.shape[0], -1, -1)  # (B, K, d)
        if self.training or torch.is_grad_enabled():
            out, _ = self.attn(q, tokens, tokens, key_padding_mask=~valid, need_weights=False)
        else:  # the same attention in plain functional ops: a third of the module path's time at inference
            out = self._attend(q, tokens, valid)
        return self.norm(out + q)

    def _attend(self, q: torch.Tensor, tokens: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        attn, d = self.attn, q.shape[-1]
        query = F.linear(q, attn.in_proj_weight[:d], attn.in_proj_bias[:d])  # (B, K, d)
        key, value = F.linear(tokens, attn.in_proj_weight[d:], attn.in_proj_bias[d:]).chunk(2, dim=-1)  # (B, L, d)
        out = _attention(query, key, value, attn.num_heads, valid[:, None, None, :])  # (B, K, d)
        return F.linear(out, attn.out_proj.weight, attn.out_proj.bias)

    def pool_projected(self, tokens: torch.Tensor, valid: torch.Tensor, project: nn.Linear) -> torch.Tensor:
        """``forward(project(tokens), valid)`` at inference, in fewer products: ``project`` is folded into the keys'
        and values' projection (the pool reads the projected tokens only through it) and the queries' projection
        is the same on every call; both are derived once per weights. tokens (B, L, D_in) -> (B, K, d)."""
        if self.training or torch.is_grad_enabled():
            return self(project(tokens), valid)
        query, kv_weight, kv_bias = self._folded(project)
        B = tokens.shape[0]
        key, value = F.linear(tokens.to(kv_weight.dtype), kv_weight, kv_bias).chunk(2, dim=-1)  # each (B, L, d)
        out = _attention(query.expand(B, -1, -1), key, value, self.attn.num_heads, valid[:, None, None, :])
        out = F.linear(out, self.attn.out_proj.weight, self.attn.out_proj.bias)  # (B, K, d)
        return self.norm(out + self.queries)

    def _folded(self, project: nn.Linear) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(projected queries (K, d), folded key/value weight (2d, D_in) and bias (2d,)), kept while the tensors
        they come from are the same objects, not updated in place since (inference tensors keep no version
        counter: they are folded on every call)."""
        attn = self.attn
        sources = (self.queries, attn.in_proj_weight, attn.in_proj_bias, project.weight, project.bias)
        if any(t.is_inference() for t in sources):
            return self._fold_now(project)
        key = [(t, t._version) for t in sources]  # the tensors themselves: a freed address cannot be mistaken
        if self._fold_key is None or any(a is not b or u != v for (a, u), (b, v) in zip(self._fold_key, key)):
            self._fold, self._fold_key = self._fold_now(project), key
        return self._fold

    def _fold_now(self, project: nn.Linear) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        d = self.queries.shape[-1]
        with torch.autocast(self.queries.device.type, enabled=False):  # the weights' own precision, always
            w, b = self.attn.in_proj_weight.float(), self.attn.in_proj_bias.float()
            query = F.linear(self.queries.float(), w[:d], b[:d])  # (K, d)
            kv_weight = w[d:] @ project.weight.float()  # (2d, d) @ (d, D_in) -> (2d, D_in)
            kv_bias = w[d:] @ project.bias.float() + b[d:]  # (2d,)
        dtype = self.queries.dtype
        return query.to(dtype), kv_weight.to(dtype), kv_bias.to(dtype)


class LatentDenoiser(nn.Module):
    def __init__(self, config: DenoiserConfig):
        super().__init__()
        self.config = config
        d = config.transformer.dim
        self.latent_in = nn.Linear(config.latent_dim, d)
        self.latent_out = nn.Linear(d, config.latent_dim)
        self.time_mlp = nn.Sequential(nn.Linear(d, d), nn.SiLU(), nn.Linear(d, d))
        if config.length_conditioning:
            self.length_mlp = nn.Sequential(nn.Linear(d, d), nn.SiLU(), nn.Linear(d, d))
        if config.guidance_input:  # zero-initialised last layer: a fresh student starts as its teacher
            self.guidance_mlp = nn.Sequential(nn.Linear(d, d), nn.SiLU(), nn.Linear(d, d))
            nn.init.zeros_(self.guidance_mlp[2].weight)
            nn.init.zeros_(self.guidance_mlp[2].bias)
        if config.cond == "text":
            self.text_proj = nn.Linear(config.text_dim, d)
            if config.text_pool_tokens:
                self.token_proj = nn.Linear(config.text_dim, d)
                self.token_pool = AttentionPool(d, config.transformer.heads, config.text_pool_tokens)
            if config.verb_hints:  # row 0 (no verb named) stays zero, the others start at zero: a warm start holds
                self.verb_embedding = nn.Embedding(1 + len(config.verb_hints), d, padding_idx=0)
                nn.init.zeros_(self.verb_embedding.weight)
        elif config.cond == "action":
            self.action_embedding = nn.Embedding(config.num_actions, d)
        self.null_condition = nn.Parameter(torch.randn(config.cond_tokens, d) * 0.02)
        n_seq = 1 + config.latent_tokens + (0 if config.transformer.cross_attention else config.cond_tokens)
        self.positions = nn.Parameter(torch.randn(n_seq, d) * 0.02)
        if config.transformer.cross_attention:
            self.cond_positions = nn.Parameter(torch.randn(config.cond_tokens, d) * 0.02)
        self.transformer = SkipTransformer(config.transformer)

    # -- conditions -------------------------------------------------------------------------------------------
    def condition_tokens(self, batch_size: int, *, text=None, actions: torch.Tensor | None = None,
                         verbs: torch.Tensor | None = None, drop: torch.Tensor | None = None) -> torch.Tensor:
        """The condition as tokens (B, C, d). ``text`` is a TextEmbedding (pooled, tokens, mask); ``actions`` (B,)
        class ids; ``verbs`` (B,) verb-hint ids (``mld_core.condition.verb_hint``; None: no verb named, and ignored by
        a denoiser without hints); ``drop`` (B,) bool replaces the condition with the learned null condition
        (guidance, dropout)."""
        cfg = self.config
        null = self.null_condition.expand(batch_size, -1, -1)  # (B, C, d)
        if cfg.cond == "none":
            return null
        if cfg.cond == "text":
            if text is None:
                raise ValueError("a text-conditioned denoiser needs text embeddings")
            cond = self.text_proj(text.pooled.to(null.dtype))[:, None]  # (B, 1, d)
            if cfg.text_pool_tokens:
                L = cfg.max_text_tokens
                words = self.token_pool.pool_projected(text.tokens[:, :L].to(null.dtype), text.mask[:, :L],
                                                       self.token_proj)  # (B, K, d)
                cond = torch.cat([cond, words], dim=1)  # (B, 1 + K, d)
            if cfg.verb_hints and verbs is not None:
                hint = self.verb_embedding(verbs).to(cond.dtype)[:, None]  # (B, 1, d)
                cond = torch.cat([cond[:, :1] + hint, cond[:, 1:]], dim=1)
        else:
            if actions is None:
                raise ValueError("an action-conditioned denoiser needs action ids")
            cond = self.action_embedding(actions)[:, None]  # (B, 1, d)
        if drop is not None:
            cond = torch.where(drop[:, None, None], null, cond)
        return cond

    def null_tokens(self, batch_size: int) -> torch.Tensor:
        return self.null_condition.expand(batch_size, -1, -1)

    # -- noise prediction ---------------------------------------------------------------------------------------
    def forward(self, z_t: torch.Tensor, timesteps: torch.Tensor, cond: torch.Tensor,
                lengths: torch.Tensor | None = None, guidance: torch.Tensor | None = None) -> torch.Tensor:
        """z_t (B, n, latent_dim), timesteps (B,), cond (B, C, d) from ``condition_tokens``, lengths (B,) frames,
        guidance (B,) scales (``guidance_input`` denoisers only) -> predicted noise (B, n, latent_dim)."""
        cfg = self.config
        d = cfg.transformer.dim
        dtype = self.latent_in.weight.dtype
        time = self.time_mlp(sinusoidal_embedding(timesteps, d).to(dtype))  # (B, d)
        if cfg.length_conditioning:
            if lengths is None:
                raise ValueError("this denoiser is conditioned on the target length: pass lengths")
            length = sinusoidal_embedding(lengths.float() * (1000.0 / cfg.max_frames), d).to(dtype)  # (B, d)
            time = time + self.length_mlp(length)
        if cfg.guidance_input:
            if guidance is None:
                raise ValueError("this denoiser takes the guidance scale as an input: pass guidance")
            time = time + self.guidance_mlp(sinusoidal_embedding(guidance.float() * 100.0, d).to(dtype))
        latent = self.latent_in(z_t)  # (B, n, d)
        if cfg.transformer.cross_attention:
            seq = torch.cat([time[:, None], latent], dim=1) + self.positions  # (B, 1 + n, d)
            out = self.transformer(seq, memory=cond + self.cond_positions)
        else:
            seq = torch.cat([time[:, None], cond, latent], dim=1) + self.positions  # (B, 1 + C + n, d)
            out = self.transformer(seq)
        return self.latent_out(out[:, -cfg.latent_tokens:])


# The layers of one condition kind (text projections and pool, the class embedding): never carried to another.
CONDITION_LAYERS = ("text_proj.", "token_proj.", "token_pool.", "action_embedding.", "verb_embedding.")


def with_condition(denoiser: LatentDenoiser, config: DenoiserConfig, seed: int = 0) -> LatentDenoiser:
    """A denoiser of ``config`` (another condition kind, e.g. action instead of text) carrying over ``denoiser``'s
    shared weights: the transformer, the latent, time and length layers, the first condition token's position and
    null. The new condition's own layers (``CONDITION_LAYERS``: a class embedding, text projections) start fresh,
    drawn with ``seed``, even where their shapes match (an action model carried to other labels). A warm start for
    training another condition on the same latents."""
    if config.transformer != denoiser.config.transformer or config.latent_tokens != denoiser.config.latent_tokens:
        raise ValueError("only the condition may differ between a denoiser and the one it is carried over to")
    with torch.random.fork_rng(devices=[]):  # the fresh layers drawn from ``seed``, the caller's RNG untouched
        torch.manual_seed(seed)
        target = LatentDenoiser(config)
    old, new = denoiser.state_dict(), target.state_dict()
    n, c_old, c_new = config.latent_tokens, denoiser.config.cond_tokens, config.cond_tokens
    kept = {k: v for k, v in old.items()
            if k in new and v.shape == new[k].shape and not k.startswith(CONDITION_LAYERS)}
    kept["null_condition"] = _first_rows(old["null_condition"], new["null_condition"], c_new)
    if not config.transformer.cross_attention:  # positions (1 + C + n, d): time, condition, latent
        pos, fresh = old["positions"], new["positions"]
        cond = _first_rows(pos[1:1 + c_old], fresh[1:1 + c_new], c_new)
        kept["positions"] = torch.cat([pos[:1], cond, pos[-n:]])
    else:
        kept["cond_positions"] = _first_rows(old["cond_positions"], new["cond_positions"], c_new)
    target.load_state_dict({**new, **kept})
    return target


def with_verb_hints(denoiser: LatentDenoiser, verbs: Sequence[str]) -> LatentDenoiser:
    """A copy of the text denoiser ``denoiser`` reading hints for ``verbs``: every weight carried over, the hint
    vectors of verbs it already reads kept and the others zero, so before training it makes what ``denoiser``
    makes."""
    config = DenoiserConfig(**{**denoiser.config.to_dict(), "verb_hints": list(verbs)})
    target = LatentDenoiser(config)
    state = {k: v for k, v in denoiser.state_dict().items() if not k.startswith("verb_embedding.")}
    if verbs:
        rows = target.verb_embedding.weight.detach().clone()  # (1 + V, d), zero
        old = denoiser.config.verb_hints
        for i, verb in enumerate(verbs):
            if verb in old:
                rows[1 + i] = denoiser.verb_embedding.weight[1 + old.index(verb)]
        state["verb_embedding.weight"] = rows
    target.load_state_dict(state)
    return target


def _first_rows(old: torch.Tensor, fresh: torch.Tensor, rows: int) -> torch.Tensor:
    """``old``'s first ``rows`` rows, the rest (where ``old`` has fewer) from ``fresh``."""
    k = min(rows, len(old))
    return torch.cat([old[:k], fresh[k:rows]])


def grow_latent(denoiser: LatentDenoiser, tokens: int, noise: float = 0.0, seed: int = 0) -> LatentDenoiser:
    """A copy of ``denoiser`` for a latent grown to ``tokens`` tokens (models.vae.grow_latent): latent token i >= n
    starts with the position of token i mod n, plus Gaussian ``noise``; every other weight is the old one's. A warm
    start for fine-tuning on the grown VAE's latents, not an equal model: the other tokens attend to the copies too."""
    n = denoiser.config.latent_tokens
    if tokens < n:
        raise ValueError(f"a latent of {n} tokens cannot be grown to {tokens}")
    grown = LatentDenoiser(DenoiserConfig(**{**denoiser.config.to_dict(), "latent_tokens": tokens}))
    state = denoiser.state_dict()
    positions = state["positions"]  # (1 [+ C] + n, d): the latent tokens last
    copied = positions[-n:][torch.arange(tokens) % n].clone()  # (tokens, d)
    copied[n:] += noise * torch.randn(copied[n:].shape, generator=torch.Generator().manual_seed(seed))
    state["positions"] = torch.cat([positions[:-n], copied])
    grown.load_state_dict(state)
    return grown
