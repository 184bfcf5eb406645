"""Content anchor: move a prompt's sentence vector towards the content that a linear classifier reads in it.

Why (docs/evaluation.md, "The content anchor"): the denoiser takes nearly all of a prompt's meaning, content and side,
from the text encoder's pooled sentence vector, and a wording unlike the training captions puts that vector where the
denoiser reads it poorly: "a person walks ahead, then changes direction to their left" walked straight on most draws.
The anchor keeps what the prompt's side and style words add to its vector and replaces the rest, the vector of the
prompt without them, by the mixture of training contents that a linear classifier reads in it:

    q  = unit vector of the prompt without side and style words (mld_core.condition.coverage.normalise)
    P  = softmax(classifier(q))                      # over side-free contents ("walk-turn-side", "bow", ...)
    p' = normalize(p + weight * (P @ centroids - q))  # p: the prompt's own vector, so its side and style stay

``centroids`` are the unit means of the side-free training captions of each content. The classifier and centroids are
fitted on a model's training captions and their rewordings (``fit``; ``scripts/build_content_anchor.py``) and kept in
the model folder as ``content_anchor.safetensors`` (fp16, like the weights). Config ``content_anchor``
(:class:`ContentAnchorConfig`) sets the weight (0: off) and, optionally, how the weight follows the prompt's coverage
score (mld_core.condition.coverage: the cosine of ``q`` to its nearest training caption): a prompt worded as a training
caption (score 1) is left as it is, one whose score is ``full_below`` or lower gets the whole weight, linearly in
between.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from mld_core.condition.coverage import normalise

FILE_NAME = "content_anchor.safetensors"
LOGIT_SCALE = 10.0  # unit vectors have small dot products: the classifier reads 10 x q


@dataclass
class ContentAnchorConfig:
    """weight: how far a prompt's vector moves (0: off, 1: its side-free part replaced by the classified centroids);
    full_below: None, every prompt gets the whole weight; else a coverage score in (0, 1): prompts scoring this or
    lower get the whole weight, a training caption's wording (score 1) none, linearly in between."""

    weight: float = 0.0
    full_below: float | None = None

    def check(self) -> None:
        w, f = self.weight, self.full_below
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not 0 <= w <= 2:
            raise ValueError(f"content_anchor.weight must be a number in 0..2, got {w!r}")
        if f is not None and (isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f < 1):
            raise ValueError(f"content_anchor.full_below must be null or a number between 0 and 1, got {f!r}")

    def strengths(self, scores: torch.Tensor | None) -> torch.Tensor | float:
        """The weight per prompt (B,) from their coverage scores (B,), or the weight itself (no ramp or no scores)."""
        if self.full_below is None or scores is None:
            return float(self.weight)
        ramp = ((1.0 - scores.float()) / (1.0 - self.full_below)).clamp(0.0, 1.0)
        return self.weight * ramp


def side_free_label(label: str) -> str:
    """'walk-turn-left' -> 'walk-turn-side', 'raise-up-right-hand' -> 'raise-up-side-hand' (a side is the prompt's
    own business: the anchor never moves a take towards a side)."""
    return "-".join("side" if w in ("left", "right") else w for w in str(label).split("-"))


class ContentAnchor:
    """A linear content classifier over side-free sentence vectors and each content's centroid.

    classes: C side-free content labels; weight (C, D) and bias (C,): the classifier; centroids (C, D), unit rows.
    """

    def __init__(self, classes: Sequence[str], weight: torch.Tensor, bias: torch.Tensor, centroids: torch.Tensor):
        self.classes = list(classes)
        self.weight = torch.as_tensor(weight, dtype=torch.float32)
        self.bias = torch.as_tensor(bias, dtype=torch.float32)
        self.centroids = torch.as_tensor(centroids, dtype=torch.float32)
        C, D = self.weight.shape
        if len(self.classes) != C or self.bias.shape != (C,) or self.centroids.shape != (C, D):
            raise ValueError(f"content anchor: {len(self.classes)} classes, weight {tuple(self.weight.shape)}, "
                             f"bias {tuple(self.bias.shape)}, centroids {tuple(self.centroids.shape)}")

    @property
    def dim(self) -> int:
        return self.weight.shape[1]

    def probabilities(self, plain: torch.Tensor) -> torch.Tensor:
        """(B, C) content probabilities of side-free unit vectors ``plain`` (B, D)."""
        return (LOGIT_SCALE * plain.float() @ self.weight.T + self.bias).softmax(-1)

    def anchored(self, pooled: torch.Tensor, plain: torch.Tensor, strength: float | torch.Tensor) -> torch.Tensor:
        """The prompts' vectors ``pooled`` (B, D) moved by ``strength`` (a number, or one per prompt (B,)) x
        (classified centroid - ``plain``), unit length, in ``pooled``'s dtype. ``plain``: the same prompts' side- and
        style-free vectors (B, D)."""
        strength = torch.as_tensor(strength, dtype=torch.float32).reshape(-1, 1)  # (1 or B, 1)
        if not strength.any():
            return pooled
        plain = F.normalize(plain.float(), dim=-1)
        target = self.probabilities(plain) @ self.centroids  # (B, D)
        return F.normalize(pooled.float() + strength * (target - plain), dim=-1).to(pooled.dtype)

    # -- files --------------------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        from safetensors.torch import save_file

        from mld_core.fileio import atomic_write

        path = Path(path)
        tensors = {name: getattr(self, name).to(torch.float16).contiguous()  # stored as fp16, computed in fp32
                   for name in ("weight", "bias", "centroids")}
        atomic_write(path, lambda tmp: save_file(tensors, str(tmp), metadata={"classes": json.dumps(self.classes)}))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "ContentAnchor":
        from safetensors import SafetensorError, safe_open

        try:
            with safe_open(str(path), framework="pt", device="cpu") as f:
                classes = json.loads((f.metadata() or {})["classes"])
                return cls(classes, f.get_tensor("weight"), f.get_tensor("bias"), f.get_tensor("centroids"))
        except (SafetensorError, OSError, KeyError, ValueError, RuntimeError) as exc:
            raise ValueError(f"cannot read the content anchor {path}: {exc}") from None


def encode_plain(text_encoder, texts: Sequence[str]) -> np.ndarray:
    """Unit sentence vectors (N, D) of ``texts`` without their side and style words (what the classifier reads)."""
    from mld_core.condition.coverage import encode

    return encode(text_encoder, [normalise(t) or t for t in texts])


def fit(texts: Sequence[str], labels: Sequence[str], text_encoder, steps: int = 1500, seed: int = 0) -> ContentAnchor:
    """Fit the classifier and centroids on ``texts`` (training captions, rewordings welcome) and their content
    ``labels``: both without side and style words. Deterministic for a seed."""
    pairs = sorted({(normalise(t), side_free_label(label)) for t, label in zip(texts, labels) if label and normalise(t)})
    if not pairs:
        raise ValueError("no labelled captions to fit a content anchor on")
    classes = sorted({label for _, label in pairs})
    index = {c: i for i, c in enumerate(classes)}
    x = torch.from_numpy(encode_plain(text_encoder, [t for t, _ in pairs]))  # (N, D) unit rows
    y = torch.tensor([index[label] for _, label in pairs])
    gen = torch.Generator().manual_seed(int(seed))
    linear = torch.nn.Linear(x.shape[1], len(classes))
    with torch.no_grad():
        linear.weight.normal_(0.0, 0.01, generator=gen)
        linear.bias.zero_()
    opt = torch.optim.Adam(linear.parameters(), lr=1e-2, weight_decay=1e-5)
    for _ in range(steps):
        rows = torch.randint(0, len(y), (min(512, len(y)),), generator=gen)
        loss = F.cross_entropy(linear(LOGIT_SCALE * x[rows]), y[rows])
        opt.zero_grad()
        loss.backward()
        opt.step()
    centroids = F.normalize(torch.stack([x[y == c].mean(0) for c in range(len(classes))]), dim=-1)  # (C, D)
    return ContentAnchor(classes, linear.weight.detach(), linear.bias.detach(), centroids)


def training_texts(data_dir: str | Path, rewordings: int = 4, seed: int = 0) -> tuple[list[str], list[str]]:
    """(texts, content labels) of a folder's train split: each caption and ``rewordings`` rewordings of it (with
    other turn verbs, as the default model's denoiser trained)."""
    from mld_core.data.captions import reworded
    from mld_core.condition.coverage import training_captions

    captions, contents = training_captions(data_dir, "train")
    rng = np.random.default_rng(seed)
    texts, labels = list(captions), list(contents)
    for caption, content in zip(captions, contents):
        for _ in range(rewordings):
            texts.append(reworded(caption, rng, turns=True))
            labels.append(content)
    return texts, labels


def load_for_model(model_dir: str | Path) -> ContentAnchor | None:
    """The model folder's anchor, or None when it has none."""
    path = Path(model_dir) / FILE_NAME
    return ContentAnchor.load(path) if path.is_file() else None
