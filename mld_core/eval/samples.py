"""Text-motion pairs drawn from a split, the way the T2M evaluation draws them.

Each clip gives one pair per draw: a random caption of the clip, the motion cropped to that caption's
segment (start/end seconds; 0/0 or missing means the whole clip), then a random window of at most
``max_frames``. Captions whose segment is shorter than ``min_frames`` are skipped; a clip with no usable
caption is skipped. Everything random comes from the ``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


@dataclass
class Pair:
    clip_id: str
    text: str
    features: np.ndarray  # (T, D) unnormalised
    action: str | None

    @property
    def length(self) -> int:
        return len(self.features)


def _segment(clip_frames: int, start_s, end_s, fps: int) -> tuple[int, int]:
    start_s = float(start_s or 0.0)
    end_s = float(end_s or 0.0)
    if start_s <= 0.0 and end_s <= 0.0:
        return 0, clip_frames
    start = max(0, int(round(start_s * fps)))
    end = clip_frames if end_s <= 0.0 else min(clip_frames, int(round(end_s * fps)))
    return start, end


def usable_captions(clip, *, min_frames: int, fps: int = 20) -> list[tuple[str, int, int]]:
    """(text, start_frame, end_frame) of the clip's captions whose segment has >= min_frames frames."""
    out = []
    n = len(clip.features)
    for cap in clip.captions:
        text = getattr(cap, "text", cap)
        if not isinstance(text, str) or not text.strip():
            continue
        s, e = _segment(n, getattr(cap, "start_s", 0.0), getattr(cap, "end_s", 0.0), fps)
        if e - s >= min_frames:
            out.append((text.strip(), s, e))
    return out


def draw_pairs(
    clips: Sequence,
    rng: np.random.Generator,
    *,
    min_frames: int = 20,
    max_frames: int = 196,
    fps: int = 20,
) -> list[Pair]:
    """One random (caption, cropped motion) pair per usable clip, in the clips' order."""
    pairs = []
    for clip in clips:
        caps = usable_captions(clip, min_frames=min_frames, fps=fps)
        if not caps:
            continue
        text, s, e = caps[int(rng.integers(len(caps)))]
        n = e - s
        if n > max_frames:
            s += int(rng.integers(n - max_frames + 1))
            n = max_frames
        pairs.append(Pair(clip.id, text, np.asarray(clip.features[s : s + n], np.float32),
                          getattr(clip, "action", None)))
    return pairs


def all_caption_texts(clips: Sequence, *, min_frames: int = 20, fps: int = 20) -> list[str]:
    """Every distinct usable caption of the clips, sorted (for precomputing sentence vectors)."""
    texts = set()
    for clip in clips:
        texts.update(t for t, _, _ in usable_captions(clip, min_frames=min_frames, fps=fps))
    return sorted(texts)
