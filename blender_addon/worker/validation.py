"""The add-on's name for mld_core.inputs, which owns input validation for the CLI, the batch and the panel alike."""

from __future__ import annotations

from mld_core.inputs import (  # noqa: F401 - re-exported for the panel, operators and batch
    DEFAULT_MAX_SECONDS,
    DEFAULT_MIN_SECONDS,
    MAX_GUIDANCE,
    MAX_PROMPT_CHARS,
    MAX_STEPS,
    MAX_VARIANTS,
    MODEL_FPS,
    SEED_MAX,
    GenerateRequest,
    InputError as RequestError,
    clean_prompt,
    model_limits,
    validate_request,
)
