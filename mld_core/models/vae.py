"""Motion VAE of MLD: per-frame features of any length <-> a latent z of shape (n, d).

Encoder: [2n learnable distribution tokens ; Linear(features)] + positions -> SkipTransformer; the first n outputs
are mu, the next n are log-variance. Decoder: L positional queries attend to z (cross-attention memory) through a
SkipTransformer and a Linear back to the feature size. Padding masks let any length up to ``max_frames`` through.
Features are normalised (Mean/Std of the training folder) outside this module.

The encoder side (ENCODER_MODULES) fixes the latents a denoiser learns; a decoder side trained on its own
(``train vae`` with ``train_modules`` = DECODER_MODULES) can be swapped in under that denoiser (``take_decoder``).
A trained latent grows to more tokens (``grow_latent``) for a fine-tune that needs more room in it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch
from torch import nn

from mld_core.models.transformer import SkipTransformer, TransformerConfig, sinusoidal_embedding


@dataclass
class VAEConfig:
    feature_dim: int = 263
    latent_tokens: int = 1  # n
    latent_dim: int = 256  # d
    max_frames: int = 196
    encoder: TransformerConfig = field(default_factory=lambda: TransformerConfig(layers=3))
    decoder: TransformerConfig = field(default_factory=lambda: TransformerConfig(layers=3, cross_attention=True))
    kl_weight: float = 1e-4

    def __post_init__(self):
        if isinstance(self.encoder, dict):
            self.encoder = TransformerConfig(**self.encoder)
        if isinstance(self.decoder, dict):
            self.decoder = TransformerConfig(**self.decoder)
        if not self.decoder.cross_attention:
            raise ValueError("the VAE decoder reads z through cross-attention (decoder.cross_attention=True)")
        if self.encoder.dim != self.latent_dim or self.decoder.dim != self.latent_dim:
            raise ValueError("encoder/decoder width must equal latent_dim")

    def to_dict(self) -> dict:
        return asdict(self)


def padding_mask(lengths: torch.Tensor, max_len: int) -> torch.Tensor:
    """(B,) lengths -> (B, max_len) bool, True where padded."""
    return torch.arange(max_len, device=lengths.device)[None, :] >= lengths[:, None]


ENCODER_MODULES = ("embed", "distribution_tokens", "encoder")
DECODER_MODULES = ("latent_positions", "decoder", "head")


class MotionVAE(nn.Module):
    def __init__(self, config: VAEConfig):
        super().__init__()
        self.config = config
        d, n = config.latent_dim, config.latent_tokens
        self.embed = nn.Linear(config.feature_dim, d)
        self.distribution_tokens = nn.Parameter(torch.randn(2 * n, d) * 0.02)
        self.latent_positions = nn.Parameter(torch.randn(n, d) * 0.02)
        self.encoder = SkipTransformer(config.encoder)
        self.decoder = SkipTransformer(config.decoder)
        self.head = nn.Linear(d, config.feature_dim)
        self.register_buffer("frame_positions", sinusoidal_embedding(torch.arange(config.max_frames), d), persistent=False)

    def encode(self, x: torch.Tensor, lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x (B, T, F) normalised features, lengths (B,) -> mu, logvar each (B, n, d)."""
        B, T, _ = x.shape
        n = self.config.latent_tokens
        if T > self.config.max_frames:
            raise ValueError(f"{T} frames exceed the model's max_frames {self.config.max_frames}")
        frames = self.embed(x) + self.frame_positions[:T]  # (B, T, d)
        tokens = self.distribution_tokens.expand(B, -1, -1)  # (B, 2n, d)
        seq = torch.cat([tokens, frames], dim=1)  # (B, 2n + T, d)
        mask = torch.cat([torch.zeros(B, 2 * n, dtype=torch.bool, device=x.device), padding_mask(lengths, T)], dim=1)
        out = self.encoder(seq, padding_mask=mask)[:, : 2 * n]  # (B, 2n, d)
        return out[:, :n], out[:, n:].clamp(-20.0, 10.0)

    def decode(self, z: torch.Tensor, lengths: torch.Tensor, max_len: int | None = None) -> torch.Tensor:
        """z (B, n, d), lengths (B,) -> (B, T, F) normalised features, zero beyond each length."""
        T = int(lengths.max()) if max_len is None else max_len
        if T > self.config.max_frames:
            raise ValueError(f"{T} frames exceed the model's max_frames {self.config.max_frames}")
        B = z.shape[0]
        queries = self.frame_positions[:T].expand(B, -1, -1)  # (B, T, d)
        mask = padding_mask(lengths, T)
        memory = z + self.latent_positions
        out = self.head(self.decoder(queries, padding_mask=mask if mask.any() else None, memory=memory,
                                     fixed_queries=T))  # (B, T, F): the queries depend on T alone
        return out.masked_fill(mask[..., None], 0.0)

    def forward(self, x: torch.Tensor, lengths: torch.Tensor, sample: bool = True, noise: torch.Tensor | None = None):
        """``noise`` (B, n, d): the sampled z's standard normal draw (default: drawn here)."""
        mu, logvar = self.encode(x, lengths)
        if not sample:
            return self.decode(mu, lengths, max_len=x.shape[1]), mu, logvar
        noise = torch.randn_like(mu) if noise is None else noise.to(mu)
        z = mu + noise * (0.5 * logvar).exp()
        return self.decode(z, lengths, max_len=x.shape[1]), mu, logvar

    def loss(self, x: torch.Tensor, lengths: torch.Tensor, return_recon: bool = False,
             feature_weights: torch.Tensor | None = None, noise: torch.Tensor | None = None):
        """MSE on valid frames of normalised features + kl_weight * KL(q(z|x) || N(0, I)): (loss, parts), and the
        reconstruction (B, T, F) too with ``return_recon``. ``feature_weights`` (F,) weight each feature's squared
        error (the mean over features stays the reduction). ``noise``: as in forward."""
        recon, mu, logvar = self(x, lengths, noise=noise)
        recon, mu, logvar = recon.float(), mu.float(), logvar.float()  # the loss in fp32 under autocast too
        valid = ~padding_mask(lengths, x.shape[1])  # (B, T)
        err = (recon - x) ** 2  # (B, T, F)
        if feature_weights is not None:
            err = err * feature_weights
        mse = err.mean(-1)[valid].mean()
        kl = (-0.5 * (1 + logvar - mu**2 - logvar.exp())).sum(-1).mean()
        loss, parts = mse + self.config.kl_weight * kl, {"mse": mse.item(), "kl": kl.item()}
        return (loss, parts, recon) if return_recon else (loss, parts)


def take_decoder(vae: MotionVAE, donor: MotionVAE) -> None:
    """Copy ``donor``'s decoder side into ``vae``. Refused (ValueError) unless both have one config and one encoder
    (equal at fp16, so a shipped fp16 folder matches the fp32 run it came from): another encoder makes other latents,
    which the denoiser paired with ``vae`` never learned."""
    if donor.config.to_dict() != vae.config.to_dict():
        raise ValueError("the decoder comes from a VAE of another shape (its config differs)")
    mine, theirs = vae.state_dict(), donor.state_dict()
    changed = sorted({k.split(".")[0] for k in mine if k.split(".")[0] in ENCODER_MODULES
                      and not torch.equal(mine[k].half(), theirs[k].half())})
    if changed:
        raise ValueError(f"the decoder's VAE has another encoder ({', '.join(changed)} differ): train it with "
                         f"train_modules {list(DECODER_MODULES)} from this model")
    vae.load_state_dict({k: theirs[k] if k.split(".")[0] in DECODER_MODULES else v for k, v in mine.items()})


def grow_latent(vae: MotionVAE, tokens: int, noise: float = 0.0, seed: int = 0) -> MotionVAE:
    """A copy of ``vae`` whose latent has ``tokens`` tokens instead of n: token i >= n starts as a copy of token
    i mod n (its distribution tokens and decoder position), plus Gaussian ``noise`` so fine-tuning can tell them
    apart. With noise 0 and ``tokens`` a multiple of n the decoder reads the copied latent exactly as the old one (each
    key repeated equally often in cross-attention changes no average); the encoder's frames see the copies too, so
    its latents move a little."""
    n = vae.config.latent_tokens
    if tokens < n:
        raise ValueError(f"a latent of {n} tokens cannot be grown to {tokens}")
    grown = MotionVAE(VAEConfig(**{**vae.config.to_dict(), "latent_tokens": tokens}))
    state = vae.state_dict()
    source = torch.arange(tokens) % n  # (tokens,): which old token each new one copies
    gen = torch.Generator().manual_seed(seed)

    def copied(rows: torch.Tensor) -> torch.Tensor:
        out = rows[source].clone()  # (tokens, d)
        out[n:] += noise * torch.randn(out[n:].shape, generator=gen)
        return out

    mu_tokens, logvar_tokens = state["distribution_tokens"][:n], state["distribution_tokens"][n:]
    state["distribution_tokens"] = torch.cat([copied(mu_tokens), copied(logvar_tokens)])  # (2 * tokens, d)
    state["latent_positions"] = copied(state["latent_positions"])
    grown.load_state_dict(state)
    return grown
