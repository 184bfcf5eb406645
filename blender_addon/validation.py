"""Generation requests and their validation (bpy-free).

A :class:`GenerateRequest` is what the panel, the operator and the batch script hand to the job runner.
:func:`validate_request` turns raw user values into a request or raises :class:`RequestError` with one
sentence the user can act on (it is shown as a report and in the panel, never as a traceback).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

# The model works on HumanML3D lengths: 20 fps, up to 196 frames (9.8 s). A loaded pipeline's own
# min_seconds / max_seconds take precedence when known.
MODEL_FPS = 20
DEFAULT_MIN_SECONDS = 1.0
DEFAULT_MAX_SECONDS = 9.8
MAX_PROMPT_CHARS = 300
MAX_STEPS = 500  # DDIM; more steps buy nothing (and 1000 + steps_offset overflows the schedule)
MAX_VARIANTS = 16
MAX_GUIDANCE = 30.0
SEED_MAX = 2**31 - 1


class RequestError(ValueError):
    """The user's input cannot be generated; the message says why and what to do."""


@dataclass(frozen=True)
class GenerateRequest:
    prompt: str
    seconds: float = 4.0
    seed: int = 0
    steps: int = 50
    guidance: float | None = None  # None: the model's own default
    variants: int = 1
    model_dir: str | None = None  # None: the bundled default model
    device: str = "cpu"
    threads: int = 0  # 0: leave torch's default
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def frames(self) -> int:
        """Length in model frames (20 fps)."""
        return int(round(self.seconds * MODEL_FPS))

    def to_dict(self) -> dict:
        data = asdict(self)
        data.pop("extra")
        return data

    def with_(self, **changes) -> "GenerateRequest":
        return replace(self, **changes)


def clean_prompt(prompt) -> str:
    """Collapse whitespace; the prompt as the model will see it."""
    if not isinstance(prompt, str):
        raise RequestError(f"The prompt must be text, not {type(prompt).__name__}")
    return " ".join(prompt.split())


def validate_request(
    prompt,
    seconds=4.0,
    seed=0,
    steps=50,
    guidance=None,
    variants=1,
    *,
    model_dir=None,
    device="cpu",
    threads=0,
    min_seconds: float | None = None,
    max_seconds: float | None = None,
) -> GenerateRequest:
    """Check every field and return a normalised :class:`GenerateRequest`.

    ``guidance`` of None or <= 0 means the model's default. ``seconds`` is rounded to whole model frames.
    """
    text = clean_prompt(prompt)
    if not text:
        raise RequestError("Type a prompt describing the motion, e.g. 'a person walks forward and waves'")
    if len(text) > MAX_PROMPT_CHARS:
        raise RequestError(f"The prompt is {len(text)} characters long; keep it under {MAX_PROMPT_CHARS}")
    if not any(ch.isalpha() for ch in text):
        raise RequestError(f"The prompt {text!r} has no words; describe the motion in words")

    lo = DEFAULT_MIN_SECONDS if min_seconds is None else float(min_seconds)
    hi = DEFAULT_MAX_SECONDS if max_seconds is None else float(max_seconds)
    seconds = _number(seconds, "Length (seconds)")
    if not lo - 1e-6 <= seconds <= hi + 1e-6:
        raise RequestError(f"Length must be between {lo:g} and {hi:g} seconds, got {seconds:g}")
    frames = int(round(seconds * MODEL_FPS))
    seconds = frames / MODEL_FPS

    seed = _integer(seed, "Seed")
    if not 0 <= seed <= SEED_MAX:
        raise RequestError(f"Seed must be between 0 and {SEED_MAX}, got {seed}")
    steps = _integer(steps, "Steps")
    if not 1 <= steps <= MAX_STEPS:
        raise RequestError(f"Steps must be between 1 and {MAX_STEPS}, got {steps}")
    variants = _integer(variants, "Variants")
    if not 1 <= variants <= MAX_VARIANTS:
        raise RequestError(f"Variants must be between 1 and {MAX_VARIANTS}, got {variants}")
    if guidance is not None:
        guidance = _number(guidance, "Guidance")
        if guidance <= 0:
            guidance = None
        elif guidance > MAX_GUIDANCE:
            raise RequestError(f"Guidance must be at most {MAX_GUIDANCE:g} (0 = the model's default), got {guidance:g}")
    threads = _integer(threads, "Threads")
    if threads < 0:
        raise RequestError(f"Threads must be 0 (automatic) or more, got {threads}")
    device = str(device or "cpu").strip().lower()
    if device not in {"cpu", "cuda", "mps", "auto"}:
        raise RequestError(f"Unknown device {device!r}; use cpu, cuda, mps or auto")
    model_dir = str(model_dir).strip() if model_dir else None
    return GenerateRequest(
        prompt=text,
        seconds=seconds,
        seed=seed,
        steps=steps,
        guidance=guidance,
        variants=variants,
        model_dir=model_dir or None,
        device=device,
        threads=threads,
    )


def _number(value, what: str) -> float:
    if isinstance(value, bool):
        raise RequestError(f"{what} must be a number, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise RequestError(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise RequestError(f"{what} must be a finite number, got {value!r}")
    return number


def _integer(value, what: str) -> int:
    number = _number(value, what)
    if number != int(number):
        raise RequestError(f"{what} must be a whole number, got {value!r}")
    return int(number)
