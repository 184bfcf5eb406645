"""Prompt files for the headless batch (bpy-free).

One take per line. A line is either plain text (the length comes from ``--seconds``) or MLD's demo format
``<frames> <text>`` with the length in model frames at 20 fps (``100 a person walks backward slowly`` is
5 s). Blank lines and lines starting with ``#`` are skipped. Problems raise :class:`BatchFileError` naming
the file and line.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from .validation import MODEL_FPS, RequestError, validate_request

_FRAMES_PREFIX = re.compile(r"^(\d+)(?:\s+(.*))?$")
_NUMBER_PREFIX = re.compile(r"^[-+]?\d*\.\d+\s")


class BatchFileError(ValueError):
    """A prompt file that cannot be used; the message names the file and line."""


@dataclass(frozen=True)
class PromptLine:
    line: int  # 1-based line number in the file
    text: str
    frames: int | None  # from a "<frames> <text>" line, at 20 fps; None: use the default length

    def seconds(self, default: float) -> float:
        return default if self.frames is None else self.frames / MODEL_FPS


def parse_prompt_lines(text: str, source: str = "<prompts>") -> list[PromptLine]:
    """Parse the content of a prompt file."""
    lines = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        match = _FRAMES_PREFIX.match(line)
        if match:
            frames = int(match.group(1))
            prompt = (match.group(2) or "").strip()
            if not prompt:
                raise BatchFileError(f"{source}:{number}: a length ({frames} frames) but no prompt text")
            if frames <= 0:
                raise BatchFileError(f"{source}:{number}: the length must be a positive number of frames")
            lines.append(PromptLine(number, prompt, frames))
            continue
        if _NUMBER_PREFIX.match(line):
            raise BatchFileError(
                f"{source}:{number}: the length must be a whole number of frames at {MODEL_FPS} fps "
                f"('<frames> <text>'), got {line.split()[0]!r}"
            )
        lines.append(PromptLine(number, line, None))
    if not lines:
        raise BatchFileError(f"{source}: no prompts (one per line, optionally '<frames> <text>')")
    return lines


def read_prompt_file(path) -> list[PromptLine]:
    """Read and parse a prompt file (UTF-8)."""
    path = Path(path)
    if not path.is_file():
        raise BatchFileError(f"prompt file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise BatchFileError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    return parse_prompt_lines(text, source=str(path))


def requests_from_lines(lines: list[PromptLine], *, default_seconds: float, seed: int, **settings) -> list:
    """Validated requests, one per line; line ``i`` (0-based) uses seed ``seed + i``.

    ``settings`` are passed to :func:`validation.validate_request` (steps, guidance, model_dir, ...).
    """
    requests = []
    for index, line in enumerate(lines):
        try:
            requests.append(
                validate_request(line.text, line.seconds(default_seconds), seed + index, **settings)
            )
        except RequestError as exc:
            raise BatchFileError(f"line {line.line}: {exc}") from None
    return requests
