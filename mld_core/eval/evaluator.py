"""The evaluator: a motion encoder and a text head aligned contrastively, plus an action classifier.

It plays the part of Guo et al.'s text-motion matching model in the MLD evaluation: FID, R-precision,
MM-Dist, Diversity and MultiModality are computed on its embeddings, and action accuracy with its
classifier. It is independent of the generator (its own layers, its own normalisation statistics).

- Motion encoder: unnormalised features (B, T, D) -> normalised with the evaluator's own mean/std ->
  linear -> two stride-2 1-D convolutions (T/4 tokens) -> a small pre-norm transformer with a padding
  mask -> masked mean pooling -> a pooled vector; the embedding is its L2-normalised projection
  (cosine geometry, as TMR), the action logits a linear layer on it.
- Text head: the frozen sentence encoder's pooled vector (MiniLM, (B, 384)) -> MLP -> L2-normalised.
  The sentence encoder itself is never trained (it is loaded lazily and only for ``encode_text``).

Saved as ``config.json`` + ``model.safetensors`` (fp16 weights, fp32 statistics) + ``EVALUATOR_CARD.md``.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"
CARD_NAME = "EVALUATOR_CARD.md"
DEFAULT_DIR = Path(__file__).resolve().parents[1] / "weights" / "evaluator"


class EvaluatorError(ValueError):
    """A missing or corrupt evaluator folder."""


@dataclass
class EvaluatorConfig:
    feature_dim: int = 263
    hidden: int = 256  # transformer width
    embed_dim: int = 256  # joint text-motion space
    layers: int = 2
    heads: int = 4
    ff_dim: int = 512
    dropout: float = 0.1
    text_dim: int = 384  # pooled sentence vector of the frozen text encoder
    text_hidden: int = 512
    temperature: float = 0.1  # InfoNCE temperature (training only)
    action_names: list[str] = field(default_factory=list)  # classifier classes; empty -> no classifier
    max_frames: int = 196
    fps: int = 20
    text_encoder: dict = field(default_factory=dict)  # spec for mld_core.models.text_encoder.load_text_encoder

    def __post_init__(self):
        if self.hidden % self.heads:
            raise ValueError(f"hidden {self.hidden} is not divisible by heads {self.heads}")

    @property
    def num_actions(self) -> int:
        return len(self.action_names)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "EvaluatorConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})


def lengths_mask(lengths: torch.Tensor, max_len: int) -> torch.Tensor:
    """(B,) lengths -> (B, max_len) bool, True on valid frames."""
    return torch.arange(max_len, device=lengths.device)[None, :] < lengths[:, None]


def _sinusoid(length: int, dim: int) -> torch.Tensor:
    pos = torch.arange(length, dtype=torch.float32)[:, None]
    freq = torch.exp(-math.log(10000.0) * torch.arange(0, dim, 2, dtype=torch.float32) / dim)
    table = torch.zeros(length, dim)
    table[:, 0::2] = torch.sin(pos * freq)
    table[:, 1::2] = torch.cos(pos * freq[: dim // 2])
    return table


class MotionEncoder(nn.Module):
    """Normalised features (B, T, D) + lengths (B,) -> pooled (B, hidden)."""

    def __init__(self, config: EvaluatorConfig):
        super().__init__()
        h = config.hidden
        self.input = nn.Linear(config.feature_dim, h)
        self.down = nn.ModuleList([nn.Conv1d(h, h, 4, stride=2, padding=1), nn.Conv1d(h, h, 4, stride=2, padding=1)])
        layer = nn.TransformerEncoderLayer(h, config.heads, config.ff_dim, config.dropout, activation="gelu",
                                           batch_first=True, norm_first=True)
        self.blocks = nn.TransformerEncoder(layer, config.layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(h)
        self.register_buffer("positions", _sinusoid(config.max_frames // 4 + 8, h), persistent=False)

    def forward(self, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        if x.shape[1] < 4:  # the two stride-2 convolutions need 4 frames
            x = F.pad(x, (0, 0, 0, 4 - x.shape[1]))
        valid = lengths_mask(lengths, x.shape[1])  # (B, T)
        h = self.input(x) * valid[..., None]  # (B, T, h)
        h = h.transpose(1, 2)  # (B, h, T)
        for conv in self.down:
            h = F.gelu(conv(h))
            # floor(L / 2): the last kept output sees only valid frames and zero padding, so a motion
            # gets the same embedding alone or padded in a batch
            lengths = torch.div(lengths, 2, rounding_mode="floor").clamp(min=1)
            h = h * lengths_mask(lengths, h.shape[-1])[:, None, :]
        h = h.transpose(1, 2)  # (B, S, h) with S ~ T / 4
        s = h.shape[1]
        if s > self.positions.shape[0]:
            pos = _sinusoid(s, h.shape[-1]).to(h)
        else:
            pos = self.positions[:s]
        valid = lengths_mask(lengths, s)  # (B, S)
        h = self.blocks(h + pos, src_key_padding_mask=~valid)
        h = self.norm(h) * valid[..., None]
        return h.sum(1) / lengths[:, None].to(h.dtype)  # masked mean (B, h)


class TextHead(nn.Module):
    """Pooled sentence vector (B, text_dim) -> (B, embed_dim) before normalisation."""

    def __init__(self, config: EvaluatorConfig):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(config.text_dim, config.text_hidden),
            nn.GELU(),
            nn.Dropout(config.dropout),
            nn.Linear(config.text_hidden, config.text_hidden),
            nn.GELU(),
            nn.Linear(config.text_hidden, config.embed_dim),
        )

    def forward(self, pooled: torch.Tensor) -> torch.Tensor:
        return self.net(pooled)


class Evaluator(nn.Module):
    def __init__(self, config: EvaluatorConfig, mean: np.ndarray | None = None, std: np.ndarray | None = None):
        super().__init__()
        self.config = config
        d = config.feature_dim
        mean = np.zeros(d, np.float32) if mean is None else np.asarray(mean, np.float32)
        std = np.ones(d, np.float32) if std is None else np.asarray(std, np.float32)
        if mean.shape != (d,) or std.shape != (d,):
            raise ValueError(f"mean/std must have shape ({d},), got {mean.shape} and {std.shape}")
        self.register_buffer("mean", torch.from_numpy(mean.copy()))
        self.register_buffer("std", torch.from_numpy(np.where(std > 1e-8, std, 1.0).astype(np.float32)))
        self.motion_encoder = MotionEncoder(config)
        self.motion_proj = nn.Linear(config.hidden, config.embed_dim)
        self.text_head = TextHead(config)
        self.classifier = nn.Linear(config.hidden, config.num_actions) if config.num_actions else None
        self._text_encoder = None

    # ---------------------------------------------------------------- torch-level (training)
    def motion_forward(self, x_norm: torch.Tensor, lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Normalised features (B, T, D) -> (embedding (B, E) unit length, action logits (B, C) or None)."""
        pooled = self.motion_encoder(x_norm, lengths)
        emb = F.normalize(self.motion_proj(pooled), dim=-1)
        logits = self.classifier(pooled) if self.classifier is not None else None
        return emb, logits

    def text_forward(self, pooled_text: torch.Tensor) -> torch.Tensor:
        """Pooled sentence vectors (B, text_dim) -> unit-length embeddings (B, E)."""
        return F.normalize(self.text_head(pooled_text), dim=-1)

    def normalize(self, features: torch.Tensor) -> torch.Tensor:
        return (features - self.mean) / self.std

    # ---------------------------------------------------------------- numpy-level (evaluation)
    def _batches(self, features: Sequence[np.ndarray] | np.ndarray, lengths, batch_size: int):
        if isinstance(features, np.ndarray) and features.ndim == 3:
            seqs = [features[i, : int(lengths[i]) if lengths is not None else features.shape[1]]
                    for i in range(len(features))]
        else:
            seqs = [np.asarray(f) for f in features]
            if lengths is not None:
                seqs = [s[: int(n)] for s, n in zip(seqs, lengths)]
        for s in seqs:
            if s.ndim != 2 or s.shape[1] != self.config.feature_dim or len(s) < 1:
                raise ValueError(f"motion features must be (T>=1, {self.config.feature_dim}), got {s.shape}")
        order = np.argsort([len(s) for s in seqs])  # similar lengths together: less padding
        for start in range(0, len(seqs), batch_size):
            idx = order[start : start + batch_size]
            lens = [min(len(seqs[i]), self.config.max_frames) for i in idx]
            batch = np.zeros((len(idx), max(lens), self.config.feature_dim), np.float32)
            for row, (i, n) in enumerate(zip(idx, lens)):
                batch[row, :n] = seqs[i][:n]
            yield idx, torch.from_numpy(batch), torch.tensor(lens)

    @torch.no_grad()
    def _motion_outputs(self, features, lengths=None, batch_size: int = 64):
        was_training = self.training
        self.eval()
        n = len(features)
        emb = np.zeros((n, self.config.embed_dim), np.float32)
        logits = np.zeros((n, max(self.config.num_actions, 1)), np.float32)
        try:
            for idx, x, lens in self._batches(features, lengths, batch_size):
                device = self.mean.device  # the evaluator's (training may keep it on a GPU)
                e, lg = self.motion_forward(self.normalize(x.to(device)), lens.to(device))
                emb[idx] = e.float().cpu().numpy()
                if lg is not None:
                    logits[idx] = lg.float().cpu().numpy()
        finally:
            self.train(was_training)
        return emb, (logits if self.config.num_actions else None)

    def encode_motion(self, features, lengths=None, batch_size: int = 64) -> np.ndarray:
        """Unnormalised features ((N, T, D) array + lengths, or a list of (T_i, D)) -> (N, E) float32."""
        return self._motion_outputs(features, lengths, batch_size)[0]

    def classify(self, features, lengths=None, batch_size: int = 64) -> np.ndarray:
        """Action logits (N, C) for unnormalised motions."""
        if not self.config.num_actions:
            raise EvaluatorError("this evaluator has no action classifier (it was trained without action labels)")
        return self._motion_outputs(features, lengths, batch_size)[1]

    @torch.no_grad()
    def encode_pooled_text(self, pooled: np.ndarray | torch.Tensor) -> np.ndarray:
        was_training = self.training
        self.eval()
        try:
            out = self.text_forward(torch.as_tensor(np.asarray(pooled, np.float32)).to(self.mean.device))
        finally:
            self.train(was_training)
        return out.float().cpu().numpy()

    @property
    def text_encoder(self):
        if self._text_encoder is None:
            from mld_core.models.text_encoder import load_text_encoder

            self._text_encoder = load_text_encoder(dict(self.config.text_encoder))
            for p in self._text_encoder.parameters():
                p.requires_grad_(False)
            self._text_encoder.eval()
        return self._text_encoder

    @torch.no_grad()
    def encode_text(self, texts: Sequence[str], batch_size: int = 128) -> np.ndarray:
        """Captions -> (N, E) float32 via the frozen sentence encoder and the trained head."""
        texts = list(texts)
        pooled = [pooled_text(self.text_encoder, texts[i : i + batch_size]) for i in range(0, len(texts), batch_size)]
        return self.encode_pooled_text(np.concatenate(pooled) if pooled else np.zeros((0, self.config.text_dim)))

    # ---------------------------------------------------------------- persistence
    def save_pretrained(self, directory: str | os.PathLike, card: str | None = None) -> Path:
        """Write config.json, model.safetensors (fp16 weights) and the card; each file atomically."""
        from safetensors.torch import save_file

        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        tensors = {}
        for name, value in self.state_dict().items():
            keep_fp32 = name in ("mean", "std")
            tensors[name] = value.detach().to(torch.float32 if keep_fp32 else torch.float16).cpu().contiguous()
        _atomic_write(directory / WEIGHTS_NAME, lambda p: save_file(tensors, str(p), metadata={"format": "pt"}))
        text = json.dumps(self.config.to_dict(), indent=2) + "\n"
        _atomic_write(directory / CONFIG_NAME, lambda p: Path(p).write_text(text))
        if card is not None:
            _atomic_write(directory / CARD_NAME, lambda p: Path(p).write_text(card))
        return directory

    @classmethod
    def from_pretrained(cls, directory: str | os.PathLike | None = None) -> "Evaluator":
        """Load an evaluator folder (None -> the bundled default evaluator)."""
        from safetensors.torch import load_file

        directory = Path(directory) if directory is not None else DEFAULT_DIR
        cfg_path, w_path = directory / CONFIG_NAME, directory / WEIGHTS_NAME
        if not cfg_path.is_file() or not w_path.is_file():
            raise EvaluatorError(f"{directory} is not an evaluator folder (needs {CONFIG_NAME} and {WEIGHTS_NAME}); "
                                 "train one with: python -m mld_core train evaluator --data DIR --out DIR")
        try:
            config = EvaluatorConfig.from_dict(json.loads(cfg_path.read_text()))
            state = load_file(str(w_path))
        except Exception as exc:  # corrupt JSON or weights
            raise EvaluatorError(f"cannot read the evaluator in {directory}: {exc}") from exc
        model = cls(config)
        state = {k: v.to(torch.float32) for k, v in state.items()}
        missing, unexpected = model.load_state_dict(state, strict=False)
        if missing or unexpected:
            raise EvaluatorError(f"evaluator weights in {directory} do not match its config "
                                 f"(missing {sorted(missing)[:3]}, unexpected {sorted(unexpected)[:3]})")
        model.eval()
        return model


def pooled_text(encoder, texts: Sequence[str]) -> np.ndarray:
    """Pooled (B, D) float32 vectors from a TextEncoder (contract: forward(list[str]) -> .pooled)."""
    with torch.no_grad():
        out = encoder(list(texts))
    pooled = out.pooled if hasattr(out, "pooled") else out
    return pooled.detach().to(torch.float32).cpu().numpy()


def _atomic_write(path: Path, writer) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    try:
        writer(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file ordinary permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
