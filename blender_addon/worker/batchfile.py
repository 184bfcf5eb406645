"""Prompt files for the headless batch (bpy-free): one take per line, read by mld_core.inputs (the same format and
messages as ``python -m mld_core generate --prompts``); here only the line -> request step."""

from __future__ import annotations

from mld_core.inputs import InputError as BatchFileError  # noqa: F401 - the batch catches this name
from mld_core.inputs import PromptLine, parse_prompt_lines, read_prompt_file, validate_request  # noqa: F401


def requests_from_lines(lines: list[PromptLine], *, default_seconds: float, seed: int, **settings) -> list:
    """Validated requests, one per line; line ``i`` (0-based) uses seed ``seed + i``.

    ``settings`` are passed to :func:`mld_core.inputs.validate_request` (steps, guidance, model_dir, ...).
    """
    requests = []
    for index, line in enumerate(lines):
        try:
            requests.append(validate_request(line.text, line.seconds(default_seconds), seed + index, **settings))
        except BatchFileError as exc:
            raise BatchFileError(f"line {line.line}: {exc}") from None
    return requests
