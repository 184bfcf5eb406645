"""Action names from a prompt and a seed (bpy-free).

``"a person walks forward and waves", seed 7`` -> ``"walks_forward_and_waves_s7"``; a variant index is added
when a request makes several (``..._s7_v2``). Names fit Blender's 63-byte ID-name limit (Blender 4.x) and
never collide with existing names (``.001`` suffixes, as Blender does).
"""

from __future__ import annotations

import re
from collections.abc import Iterable

MAX_NAME_BYTES = 63
_SUBJECTS = (
    "a person",
    "the person",
    "a man",
    "the man",
    "a woman",
    "the woman",
    "a human",
    "someone",
    "somebody",
    "person",
)
_WORD = re.compile(r"[a-z0-9]+")


def prompt_slug(prompt: str, max_bytes: int = 40) -> str:
    """Lower-case words of the prompt without a leading subject, joined by '_', at most ``max_bytes``."""
    text = " ".join(str(prompt).lower().split())
    for subject in _SUBJECTS:
        if text.startswith(subject + " "):
            text = text[len(subject) + 1 :]
            break
    words = _WORD.findall(text)
    slug = ""
    for word in words:
        candidate = f"{slug}_{word}" if slug else word
        if len(candidate) > max_bytes:
            if not slug:
                slug = word[:max_bytes]
            break
        slug = candidate
    return slug or "motion"


def action_name(prompt: str, seed: int, variant: int = 0, variants: int = 1) -> str:
    """The base Action name for one take (variant is 0-based; shown 1-based when there are several)."""
    suffix = f"_s{int(seed)}"
    if variants > 1:
        suffix += f"_v{variant + 1}"
    slug = prompt_slug(prompt, max_bytes=MAX_NAME_BYTES - len(suffix) - 4)  # room for ".001"
    return slug + suffix


def unique_name(base: str, existing: Iterable[str]) -> str:
    """``base`` or ``base.001``, ``base.002`` ... whichever is not in ``existing``."""
    taken = set(existing)
    base = _truncate_bytes(base, MAX_NAME_BYTES)
    if base not in taken:
        return base
    stem = _truncate_bytes(base, MAX_NAME_BYTES - 4)
    for number in range(1, 10000):
        name = f"{stem}.{number:03d}"
        if name not in taken:
            return name
    raise ValueError(f"no free name for {base!r}")


def _truncate_bytes(text: str, limit: int) -> str:
    data = text.encode("utf-8")
    if len(data) <= limit:
        return text
    return data[:limit].decode("utf-8", errors="ignore")
