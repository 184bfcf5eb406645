"""Prompt coverage: how close a prompt is to what the model was trained on.

A model folder may ship ``coverage_index.npz``: the unique training captions (normalised, see below), their
sentence vectors from the model's own frozen text encoder (fp16, unit length), the content label of each and the
model's known contents. :class:`CoverageIndex` answers, per prompt, a score in [0, 1] (the cosine similarity of
the prompt to its nearest training caption), a verdict and the 3 nearest captions:

- ``known``: score >= KNOWN_MIN: the model has seen this motion, worded about like this;
- ``near``: NEAR_MIN <= score < KNOWN_MIN: related wording, possibly a different motion;
- ``unknown``: score < NEAR_MIN: nothing like it in the training data; expect the nearest known motion.

A prompt that asks for one of the model's known contents by a checked verb's words (``mld_core.data.verbs``: "a
person collapses" asks for on_ground) is ``near`` at least, however its sentence scores: a model trained on that
content is never said not to have learned it. The verbs only count where they are the model's contents (a model
of the 24 Bandai contents knows kicks, not throws).

Side words (left/right) and style words (tired, happy, elderly, ...) are removed from prompt and captions alike
before they are encoded (:func:`normalise`), so they can never flip a verdict: "a tired person jumps" scores
exactly as "a person jumps"; a command without a subject is given one ("jump" is compared as "a person jump"), so
it scores as its sentence does. The thresholds are calibrated on two hand-written prompt sets
(``research/coverage_calibration.py`` prints the table; docs/quality.md has the numbers).

Build an index with :func:`build_index` (training and ``scripts/export_model.py`` do) or from a data folder with
``python scripts/build_coverage_index.py --data DIR --model DIR``.
The bundled default's index: ``python scripts/build_coverage_index.py --data data/bandai --model mld_core/weights/default``
(1,754 normalised captions of the 4,896 training clips, 1.3 MB).
"""

from __future__ import annotations

import json
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from mld_core.condition.wording import SENTENCE_STARTS, SUBJECT_WORDS

INDEX_NAME = "coverage_index.npz"
FORMAT = "mld-coverage-index"

# Calibrated on tests/fixtures: coverage_known.txt (paraphrases of known contents) and coverage_absent.txt
# (motions absent from the data); see docs/quality.md for the table these come from.
KNOWN_MIN = 0.80
NEAR_MIN = 0.68
NEAREST = 3

SIDE_WORDS = frozenset("left right lefthand righthand".split())
# Style words: the Bandai styles as the captions word them, and their everyday synonyms.
STYLE_WORDS = frozenset("""
happy happily cheerful cheerfully joyful joyfully joy glad sad sadly gloomy gloomily dejected unhappy upset angry
angrily furious furiously irritated mad proud proudly confident confidently self-assured shy shyly unsure timid
timidly hesitant hesitantly nervous nervously manly macho masculine feminine graceful gracefully elegant elegantly
childish playful playfully young youthful lively energetic energetically active old elderly aged tired tiredly
weary wearily exhausted sleepy worn lazy lazily theatrical theatrically exaggerated showy cocky thuggish giant huge
heavy heavily lumbering relaxed calm calmly excited excitedly slowly quickly briskly stiffly lightly strong
""".split())
# SUBJECT_WORDS: only for listing distinct neighbours. A text that starts with none of SENTENCE_STARTS is a command
# ("crawl", "squat down") and is given the subject every training caption has, so a command scores as its sentence
# does (mld_core.condition.wording, which generation uses to word it as a caption).
_WORD = re.compile(r"[a-z0-9]+(?:'[a-z]+)?")


def normalise(text: str) -> str:
    """Lower case, punctuation dropped, side and style words removed, a command given a subject ("A tired man waves
    his LEFT hand." -> "a man waves his hand"; "Crawl!" -> "a person crawl")."""
    words = [w for w in _WORD.findall(str(text).lower()) if w not in SIDE_WORDS and w not in STYLE_WORDS]
    if words and words[0] not in SENTENCE_STARTS:
        words = ["a", "person"] + words
    return " ".join(words)


@dataclass
class Coverage:
    prompt: str
    score: float  # [0, 1]: similarity to the nearest training caption (0 when unavailable)
    verdict: str  # "known" | "near" | "unknown" | "unavailable"
    nearest: list = field(default_factory=list)  # [(caption, similarity, content)], best first
    known_contents: list = field(default_factory=list)  # the model's motion contents

    @property
    def available(self) -> bool:
        return self.verdict != "unavailable"

    def warning(self) -> str:
        """One line for an ``unknown`` prompt ('' otherwise)."""
        if self.verdict != "unknown":
            return ""
        closest = "; ".join(f'"{c}" ({s:.3f})' for c, s, _ in self.nearest[:2])
        return f'this model has not learned "{self.prompt}" (coverage {self.score:.3f}); the closest it knows: {closest}'

    def as_dict(self) -> dict:
        return {"verdict": self.verdict, "score": round(float(self.score), 4),
                "nearest": [{"caption": c, "similarity": round(float(s), 4), "content": k} for c, s, k in self.nearest]}


def unavailable(prompt: str, known_contents: Sequence[str] = ()) -> Coverage:
    return Coverage(prompt, 0.0, "unavailable", [], list(known_contents))


def verdict_for(score: float, known_min: float | None = None, near_min: float | None = None) -> str:
    known_min = KNOWN_MIN if known_min is None else known_min
    near_min = NEAR_MIN if near_min is None else near_min
    return "known" if score >= known_min else "near" if score >= near_min else "unknown"


class CoverageIndex:
    """Normalised training captions + their unit sentence vectors; queried with the model's text encoder.
    ``thresholds`` (known_min, near_min) belong to the sentence encoder; default: KNOWN_MIN, NEAR_MIN (MiniLM)."""

    def __init__(self, captions: Sequence[str], contents: Sequence[str], embeddings: np.ndarray,
                 known_contents: Sequence[str], text_encoder: dict | None = None,
                 thresholds: tuple[float, float] | None = None):
        emb = np.asarray(embeddings)
        if emb.ndim != 2 or len(emb) != len(captions) or len(contents) != len(captions):
            raise ValueError(f"coverage index: {len(captions)} captions, {len(contents)} contents, "
                             f"embeddings {emb.shape}")
        self.captions = list(captions)
        self.contents = list(contents)
        self.embeddings = emb.astype(np.float16)  # (N, D)
        self._emb32 = self.embeddings.astype(np.float32)
        self.known_contents = list(known_contents)
        self.text_encoder = dict(text_encoder or {})
        self.thresholds = tuple(thresholds) if thresholds else (KNOWN_MIN, NEAR_MIN)

    def __len__(self) -> int:
        return len(self.captions)

    # -- querying -----------------------------------------------------------------------------------------------
    def query_vectors(self, prompts: Sequence[str], vectors: np.ndarray) -> list[Coverage]:
        """Coverage from the normalised prompts' unit sentence vectors (B, D)."""
        sims = np.asarray(vectors, np.float32) @ self._emb32.T  # (B, N)
        out = []
        for prompt, row in zip(prompts, sims):
            top = _distinct(np.argsort(-row, kind="stable")[: 8 * NEAREST], self.captions)[:NEAREST]
            score = float(np.clip(row[top[0]], 0.0, 1.0)) if len(top) else 0.0
            nearest = [(self.captions[i], float(row[i]), self.contents[i]) for i in top]
            verdict = verdict_for(score, *self.thresholds)
            if verdict == "unknown" and self.contents_named(prompt):
                verdict = "near"
            out.append(Coverage(prompt, score, verdict, nearest, list(self.known_contents)))
        return out

    def contents_named(self, prompt: str) -> list[str]:
        """The known contents ``prompt`` asks for by a checked verb's words (``mld_core.data.verbs``)."""
        from mld_core.data.verbs import verbs_in

        return [verb for verb in verbs_in(prompt) if verb in self.known_contents]

    def nearest_scores(self, vectors: np.ndarray) -> np.ndarray:
        """(B,) the cosine of each normalised prompt's unit vector (B, D) to its nearest training caption, in [0, 1]."""
        sims = np.asarray(vectors, np.float32) @ self._emb32.T  # (B, N)
        return np.clip(sims.max(axis=1), 0.0, 1.0)

    def query(self, prompts: Sequence[str], text_encoder) -> list[Coverage]:
        """Encode the normalised prompts with ``text_encoder`` (the model's own) and compare."""
        prompts = [prompts] if isinstance(prompts, str) else list(prompts)
        if not prompts:
            return []
        return self.query_vectors(prompts, encode(text_encoder, [normalise(p) or p for p in prompts]))

    # -- files --------------------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        from mld_core.fileio import atomic_write

        path = Path(path)
        meta = json.dumps({"format": FORMAT, "version": 1, "text_encoder": self.text_encoder,
                           "known_contents": self.known_contents, "thresholds": list(self.thresholds)})

        def write(tmp):
            with open(tmp, "wb") as f:
                np.savez_compressed(f, embeddings=self.embeddings, captions=np.array(self.captions, dtype=str),
                                    contents=np.array(self.contents, dtype=str), meta=np.array(meta))

        atomic_write(path, write)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "CoverageIndex":
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                if meta.get("format") != FORMAT:
                    raise ValueError(f"format {meta.get('format')!r}")
                return cls([str(c) for c in data["captions"]], [str(c) for c in data["contents"]],
                           data["embeddings"], meta.get("known_contents", []), meta.get("text_encoder"),
                           meta.get("thresholds"))
        except (OSError, ValueError, KeyError) as exc:
            raise ValueError(f"cannot read the coverage index {path}: {exc}") from None


def _distinct(order: np.ndarray, captions: Sequence[str]) -> list[int]:
    """``order`` without captions that only repeat an earlier one with another subject ("a person bows." after
    "the person bows.")."""
    seen, keep = set(), []
    for i in order.tolist():
        words = normalise(captions[i]).split()
        while words and words[0] in SUBJECT_WORDS:
            words.pop(0)
        gist = " ".join(words)
        if gist not in seen:
            seen.add(gist)
            keep.append(i)
    return keep


def encode(text_encoder, texts: Sequence[str], batch_size: int = 256) -> np.ndarray:
    """Unit sentence vectors (N, D) float32 from a TextEncoder (contract: forward(list[str]) -> .pooled)."""
    import torch

    chunks = []
    with torch.inference_mode():
        for i in range(0, len(texts), batch_size):
            pooled = text_encoder(list(texts[i:i + batch_size])).pooled.float()
            chunks.append(torch.nn.functional.normalize(pooled, dim=-1).cpu().numpy())
    return np.concatenate(chunks) if chunks else np.zeros((0, getattr(text_encoder, "dim", 0)), np.float32)


def build_index(captions: Sequence[str], contents: Sequence[str], text_encoder,
                known_contents: Sequence[str] | None = None) -> CoverageIndex:
    """An index over the unique normalised ``captions`` (each with the content label most of its captions have)."""
    by_norm: dict[str, Counter] = {}
    first: dict[str, str] = {}
    for caption, content in zip(captions, contents):
        key = normalise(caption)
        if not key:
            continue
        by_norm.setdefault(key, Counter())[content] += 1
        first.setdefault(key, caption.strip())
    keys = sorted(by_norm)
    labels = [by_norm[k].most_common(1)[0][0] for k in keys]
    known = sorted(set(contents)) if known_contents is None else list(known_contents)
    spec = dict(getattr(text_encoder, "spec", {}) or {})
    return CoverageIndex([first[k] for k in keys], labels, encode(text_encoder, keys), known, spec)


def training_captions(data_dir: str | Path, split: str = "train") -> tuple[list[str], list[str]]:
    """(captions, content labels) of a HumanML3D-format folder's split; the label is the clip's content from
    actions.json, else '' (folders without content labels)."""
    from mld_core.data.dataset import read_actions, read_captions, split_ids

    root = Path(data_dir)
    actions = read_actions(root) or {}
    labels = actions.get("clips", {})
    captions, contents = [], []
    for cid in split_ids(root, split):
        path = root / "texts" / f"{cid}.txt"
        if not path.exists():
            continue
        for c in read_captions(path):
            captions.append(c.text)
            contents.append(str(labels.get(cid, "")))
    return captions, contents


def build_for_folder(data_dir: str | Path, text_encoder, split: str = "train") -> CoverageIndex:
    captions, contents = training_captions(data_dir, split)
    if not captions:
        raise ValueError(f"{data_dir}: no {split} captions")
    known = sorted({c for c in contents if c})
    return build_index(captions, contents, text_encoder, known)


def load_for_model(model_dir: str | Path) -> CoverageIndex | None:
    """The model folder's index, or None when it has none (coverage then reports 'unavailable')."""
    path = Path(model_dir) / INDEX_NAME
    return CoverageIndex.load(path) if path.is_file() else None


def describe_content(label: str) -> str:
    """'walk-turn-left' -> 'walk-turn-left: walks forward and turns to the left' (from the caption templates)."""
    from mld_core.data.captions import CONTENTS

    phrases = CONTENTS.get(label)
    if not phrases:
        return label
    return f"{label}: {phrases[0].replace('{walks}', 'walks').replace('{runs}', 'runs')}"
