"""User input checked once, by the same rules, for the CLI, the batch script, the panel and the Python API.

Numbers (seconds, seeds, steps, guidance, variants, threads, fps), prompt text, prompt files (one format for
``generate --prompts`` and the batch: plain text or MLD's ``<frames> <text>``), the user's JSON files (one reader:
size and depth limits, finite numbers of a sane size, no key given twice), the model's own length limits (read
from its config.json without loading weights) and output paths (never an input, another output, a folder, under
a file or in a folder that cannot be written). Every problem raises :class:`InputError` with one sentence the
user can act on.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

MODEL_FPS = 20
DEFAULT_MIN_SECONDS = 2.0  # the bundled model's min_frames / fps; a model's own limits take precedence
DEFAULT_MAX_SECONDS = 9.8
MAX_PROMPT_CHARS = 300
MAX_STEPS = 500  # DDIM; more steps buy nothing (and 1000 + steps_offset overflows the schedule)
MAX_VARIANTS = 16
MAX_GUIDANCE = 30.0
SEED_MAX = 2**31 - 1
MAX_THREADS = 1024
MAX_FPS = 1000.0
MAX_SIDE_REDRAWS = 8  # model config side_redraws: draws beyond a take's first when it misses its prompt's side
MAX_VERB_REDRAWS = 8  # model config verb_redraws: draws beyond a take's first when it misses its prompt's verb
MAX_JSON_BYTES = 64 * 2**20  # a user's JSON file (a root path of 100,000 points is about 3 MB)
MAX_JSON_DEPTH = 32  # nesting of arrays and objects; the deepest format here nests 6
MAX_JSON_NUMBER = 1e12  # beyond any frame, coordinate, seed or setting; larger numbers overflow later arithmetic


class InputError(ValueError):
    """The user's input cannot be used; the message says why and what to do."""


# -- numbers ------------------------------------------------------------------------------------------------------
def finite_number(value, what: str) -> float:
    """``value`` as a finite float (no bools, NaN, inf or text)."""
    if isinstance(value, bool):
        raise InputError(f"{what} must be a number, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise InputError(f"{what} must be a finite number, got {value!r}")
    return number


def whole_number(value, what: str) -> int:
    """``value`` as an int; 3.0 is fine, 1.7 is not."""
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    number = finite_number(value, what)
    if number != int(number):
        raise InputError(f"{what} must be a whole number, got {value!r}")
    return int(number)


def number_in_range(value, what: str, lo: float, hi: float) -> float:
    number = finite_number(value, what)
    if not lo <= number <= hi:
        raise InputError(f"{what} must be between {lo:g} and {hi:g}, got {number:g}")
    return number


def true_or_false(value, what: str) -> bool:
    """A JSON switch: only true or false (a string such as "false" would otherwise read as on)."""
    if not isinstance(value, bool):
        raise InputError(f"{what} must be true or false, got {value!r}")
    return value


def int_in_range(value, what: str, lo: int, hi: int) -> int:
    number = whole_number(value, what)
    if not lo <= number <= hi:
        raise InputError(f"{what} must be between {lo} and {hi}, got {number}")
    return number


def check_seed(seed, count: int = 1, what: str = "Seed") -> int:
    """A seed whose ``count`` consecutive seeds (variants, prompt lines) all stay in 0..SEED_MAX."""
    seed = whole_number(seed, what)
    top = SEED_MAX - max(int(count), 1) + 1
    if not 0 <= seed <= top:
        extra = f" (seeds {seed}..{seed + count - 1} are used)" if count > 1 else ""
        raise InputError(f"{what} must be between 0 and {top}{extra}, got {seed}")
    return seed


def check_steps(steps, what: str = "Steps") -> int:
    return int_in_range(steps, what, 1, MAX_STEPS)


def check_guidance(guidance, what: str = "Guidance") -> float | None:
    """None or 0 means the model's default; otherwise a finite scale in (0, MAX_GUIDANCE]."""
    if guidance is None:
        return None
    guidance = finite_number(guidance, what)
    if guidance < 0 or guidance > MAX_GUIDANCE:
        raise InputError(f"{what} must be between 0 (the model's default) and {MAX_GUIDANCE:g}, got {guidance:g}")
    return guidance or None


def check_threads(threads, what: str = "Threads") -> int:
    """0 or None: torch's default; else 1..MAX_THREADS."""
    if threads is None:
        return 0
    return int_in_range(threads, what, 0, MAX_THREADS)


def check_fps(fps, what: str = "fps") -> float | None:
    if fps is None:
        return None
    return number_in_range(fps, what, 1, MAX_FPS)


# -- the user's JSON files -------------------------------------------------------------------------------------------
class _Refused:
    """A JSON number the reader will not pass on (NaN, Infinity or a huge integer), kept as written so that the
    walk over the document can name the field that holds it."""

    def __init__(self, text: str):
        self.text = text if len(text) <= 24 else f"{text[:12]}...({len(text)} characters)"


class _Object(dict):
    """A JSON object; ``repeated`` names a key the file gives more than once (JSON would keep only the last)."""

    repeated: str | None = None


def _object(pairs: list) -> _Object:
    obj = _Object(pairs)
    if len(obj) != len(pairs):
        seen: set = set()
        obj.repeated = next(k for k, _ in pairs if k in seen or seen.add(k))
    return obj


def _float(text: str):
    number = float(text)
    return number if math.isfinite(number) else _Refused(text)


def _json_path(path: tuple) -> str:
    """A field's place in a document the way jq writes it: ``.jobs[0].seconds``."""
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" if p.isidentifier() else f"[{json.dumps(p)}]"
                   for p in path) or "the top level"


def _checked_tree(data, where: str):
    """Walk the parsed document (without recursion): refuse a depth beyond MAX_JSON_DEPTH, a refused or
    non-finite or too large number, and a repeated key, naming the field; return it with plain dicts."""
    root = [data]
    stack = [(root, 0, (), 0)]
    while stack:
        parent, key, path, depth = stack.pop()
        value = parent[key]
        if isinstance(value, (dict, list)):
            if depth >= MAX_JSON_DEPTH:
                raise InputError(f"{where} is nested more than {MAX_JSON_DEPTH} levels deep")
            if isinstance(value, _Object):
                if value.repeated is not None:
                    raise InputError(f"{where}: {_json_path(path)} gives {value.repeated!r} more than once")
                value = parent[key] = dict(value)
            keys = value.keys() if isinstance(value, dict) else range(len(value))
            stack.extend((value, k, (*path, k), depth + 1) for k in keys)
        elif isinstance(value, _Refused) or (isinstance(value, (int, float)) and not isinstance(value, bool)
                                             and not (math.isfinite(value) and abs(value) <= MAX_JSON_NUMBER)):
            shown = value.text if isinstance(value, _Refused) else value if isinstance(value, int) else f"{value:g}"
            raise InputError(f"{where}: {_json_path(path)} must be a finite number of at most {MAX_JSON_NUMBER:g} "
                             f"in size, got {shown}")
    return root[0]


def parse_json(text: str, where: str):
    """The JSON document ``text`` (``where`` names it in messages: the flag and the file), checked as
    :func:`read_json_file` says."""
    if len(text) > MAX_JSON_BYTES:
        raise InputError(f"{where} is {len(text) / 2**20:.0f} MB of JSON; the limit is {MAX_JSON_BYTES // 2**20} MB")
    try:
        data = json.loads(text, object_pairs_hook=_object, parse_constant=_Refused, parse_float=_float,
                          parse_int=lambda t: int(t) if len(t.lstrip("-")) <= 15 else _Refused(t))
    except RecursionError:
        raise InputError(f"{where} is nested more than {MAX_JSON_DEPTH} levels deep") from None
    except ValueError as exc:
        raise InputError(f"{where} is not valid JSON: {exc}") from None
    return _checked_tree(data, where)


def read_json_file(path, what: str):
    """The JSON document in the user's file ``path`` (``what`` names it: "--keys", "job file"): UTF-8, at most
    MAX_JSON_BYTES, nested at most MAX_JSON_DEPTH deep, every number finite and at most MAX_JSON_NUMBER in size,
    no key repeated in an object. Booleans stay JSON booleans; check a switch with :func:`true_or_false`."""
    path = Path(path)
    where = f"{what} {path}"
    if not path.exists():
        raise InputError(f"{where}: file not found")
    if not path.is_file():
        raise InputError(f"{where}: not a file")
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(f"cannot read {where}: {exc.strerror or exc}") from None
    if size > MAX_JSON_BYTES:
        raise InputError(f"{where} is {size / 2**20:.0f} MB; the limit is {MAX_JSON_BYTES // 2**20} MB")
    return parse_json(read_utf8(path, where, encoding="utf-8-sig"), where)


def read_utf8(path, where: str, shown: str | None = None, encoding: str = "utf-8") -> str:
    """A user's text file's contents; one InputError naming ``where`` when it cannot be read, and ``shown`` (default
    ``where``) with the line when it is not UTF-8 text."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read {where}: {exc.strerror or exc}") from None
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise InputError(f"{shown or where}, line {line}: not UTF-8 text ({exc.reason} at byte {exc.start}); save it "
                         "as UTF-8") from None


# -- the model's limits ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ModelLimits:
    """Lengths a model can make, from its config.json (fps, min_frames, max_frames)."""

    fps: int = MODEL_FPS
    min_frames: int = int(round(DEFAULT_MIN_SECONDS * MODEL_FPS))
    max_frames: int = int(round(DEFAULT_MAX_SECONDS * MODEL_FPS))
    draft_guidance: tuple[float, float] | None = None  # the guidance scales its Draft learnt (None: no Draft)

    @property
    def min_seconds(self) -> float:
        return self.min_frames / self.fps

    @property
    def max_seconds(self) -> float:
        return self.max_frames / self.fps


def model_limits(model_dir=None) -> ModelLimits:
    """The limits of ``model_dir`` (None: the bundled model); the defaults when its config cannot be read (loading
    the model reports that problem properly)."""
    from mld_core.bundled import UnknownModel, model_folder
    from mld_core.model_route import is_auto

    if is_auto(model_dir):  # the bundled models share the default's lengths
        model_dir = None
    try:
        data = json.loads((model_folder(model_dir) / "config.json").read_text(encoding="utf-8"))
        draft = data.get("draft")
        limits = ModelLimits(int(data.get("fps", MODEL_FPS)), int(data.get("min_frames", 40)),
                             int(data.get("max_frames", 196)),
                             (float(draft.get("guidance_min", 3.0)), float(draft.get("guidance_max", 5.0)))
                             if isinstance(draft, dict) else None)
    except (OSError, ValueError, TypeError, AttributeError, RecursionError, UnknownModel):
        return ModelLimits()
    if limits.fps < 1 or not 1 <= limits.min_frames <= limits.max_frames:
        return ModelLimits()
    return limits


def check_seconds(seconds, limits: ModelLimits | None = None, what: str = "Length") -> float:
    """Seconds within the model's range, rounded to whole model frames."""
    limits = limits or ModelLimits()
    seconds = finite_number(seconds, f"{what} (seconds)")
    if not limits.min_seconds - 1e-6 <= seconds <= limits.max_seconds + 1e-6:
        raise InputError(f"{what} must be between {limits.min_seconds:g} and {limits.max_seconds:g} seconds for "
                         f"this model, got {seconds:g}")
    return int(round(seconds * limits.fps)) / limits.fps


# -- prompt text and prompt files -------------------------------------------------------------------------------------
def clean_prompt(prompt) -> str:
    """Collapse whitespace; the prompt as the model will see it."""
    if not isinstance(prompt, str):
        raise InputError(f"The prompt must be text, not {type(prompt).__name__}")
    return " ".join(prompt.split())


def check_prompt(prompt) -> str:
    text = clean_prompt(prompt)
    if not text:
        raise InputError("Type a prompt describing the motion, e.g. 'a person walks forward and waves'")
    if len(text) > MAX_PROMPT_CHARS:
        raise InputError(f"The prompt is {len(text)} characters long; keep it under {MAX_PROMPT_CHARS}")
    if not any(ch.isalpha() for ch in text):
        raise InputError(f"The prompt {text!r} has no words; describe the motion in words")
    return text


@dataclass(frozen=True)
class PromptLine:
    line: int  # 1-based line number in the file (0: a prompt given on the command line)
    text: str
    frames: int | None  # from a "<frames> <text>" line at MODEL_FPS; None: use the default length

    def seconds(self, default: float) -> float:
        return default if self.frames is None else self.frames / MODEL_FPS


_LEADING_NUMBER = re.compile(r"^([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)(?:\s+(.*))?$")


def parse_prompt_lines(text: str, source: str = "prompts") -> list[PromptLine]:
    """One prompt per line; MLD's ``<frames> <text>`` sets the length in frames at 20 fps. Blank lines and ``#``
    comments are skipped. A line starting with a number that is not a positive whole frame count is refused."""
    lines = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{source}, line {number}"
        if "\x00" in line:
            raise InputError(f"{where}: not text")
        frames, prompt = _split_frames(line, where)
        try:
            lines.append(PromptLine(number, check_prompt(prompt), frames))
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
    if not lines:
        raise InputError(f"{source}: no prompts (one per line, optionally '<frames> <text>')")
    return lines


def _split_frames(line: str, where: str) -> tuple[int | None, str]:
    match = _LEADING_NUMBER.match(line)
    if not match:
        return None, line
    token, prompt = match.group(1), (match.group(2) or "").strip()
    if not token.isdigit() or int(token) <= 0:
        raise InputError(f"{where}: the length must be a positive whole number of frames at {MODEL_FPS} fps "
                         f"('<frames> <text>'), got {token!r}")
    if not prompt:
        raise InputError(f"{where}: a length ({token} frames) but no prompt text")
    return int(token), prompt


def read_prompt_file(path) -> list[PromptLine]:
    """Read and parse a UTF-8 prompt file."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"prompt file not found: {path}")
    if not path.is_file():
        raise InputError(f"cannot read prompt file {path}: not a file")
    return parse_prompt_lines(read_utf8(path, f"prompt file {path}", str(path)), str(path))


# -- one generation request ----------------------------------------------------------------------------------------
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
    draft: bool = False  # the model's Draft denoiser (a few consistency steps) instead of DDIM with ``steps``
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


def validate_request(prompt, seconds=4.0, seed=0, steps=50, guidance=None, variants=1, *, model_dir=None,
                     device="cpu", threads=0, min_seconds: float | None = None,
                     max_seconds: float | None = None, draft: bool = False) -> GenerateRequest:
    """Check every field and return a normalised :class:`GenerateRequest` (seconds rounded to whole frames).
    The length limits are ``min_seconds``/``max_seconds`` when given, else those of ``model_dir``'s config."""
    text = check_prompt(prompt)
    limits = model_limits(model_dir or None)
    if min_seconds is not None or max_seconds is not None:
        lo = limits.min_seconds if min_seconds is None else float(min_seconds)
        hi = limits.max_seconds if max_seconds is None else float(max_seconds)
        limits = ModelLimits(MODEL_FPS, int(round(lo * MODEL_FPS)), int(round(hi * MODEL_FPS)), limits.draft_guidance)
    seconds = check_seconds(seconds, limits)
    variants = int_in_range(variants, "Variants", 1, MAX_VARIANTS)
    seed = check_seed(seed, variants)
    steps = check_steps(steps)
    guidance = check_guidance(guidance)
    threads = check_threads(threads)
    if draft:
        check_draft(guidance, limits)
    device = str(device or "cpu").strip().lower()
    if device not in {"cpu", "cuda", "mps", "auto"}:
        raise InputError(f"Unknown device {device!r}; use cpu, cuda, mps or auto")
    model_dir = str(model_dir).strip() if model_dir else None
    return GenerateRequest(prompt=text, seconds=seconds, seed=seed, steps=steps, guidance=guidance,
                           variants=variants, model_dir=model_dir or None, device=device, threads=threads,
                           draft=bool(draft))


def check_draft(guidance: float | None, limits: ModelLimits) -> None:
    """Draft mode needs a model with a Draft, and a guidance scale (None: the model's) among those it learnt."""
    if limits.draft_guidance is None:
        raise InputError("This model has no Draft denoiser: use Final, or make one with `python -m mld_core train "
                         "draft` (docs/draft.md)")
    lo, hi = limits.draft_guidance
    if guidance is not None and not lo <= guidance <= hi:
        raise InputError(f"Guidance {guidance:g} is outside the {lo:g}-{hi:g} this model's Draft was distilled for: "
                         "pick one in that range, or use Final")


# -- output paths -------------------------------------------------------------------------------------------------
def check_outputs(outputs: dict[str, Path], inputs: dict[str, Path] | None = None, overwrite: bool = False) -> None:
    """Refuse an output that is a folder, lies under a file, equals an input or another output, exists (without
    ``overwrite``) or would go in a folder that cannot be written. ``outputs``/``inputs`` map a name for the
    message (e.g. "--out") to a path."""
    seen: dict[Path, str] = {}
    for name, path in (inputs or {}).items():
        if path is not None:
            seen[_key(path)] = name
    for name, path in outputs.items():
        path = Path(path)
        key = _key(path)
        if key in seen:
            raise InputError(f"{name} {path} is the same file as {seen[key]}; choose another path")
        seen[key] = name
        if path.is_dir():
            raise InputError(f"{name} {path} is a folder; name a file")
        blocker = _file_ancestor(path)
        if blocker is not None:
            raise InputError(f"{name} {path}: {blocker} is a file, not a folder")
        if path.exists() and not overwrite:
            raise InputError(f"{path} exists; pass --overwrite to replace it")
        check_writable_folder(path.expanduser().absolute().parent, name, path)


def check_output_folder(path: Path, name: str = "--out", files: dict[str, Path] | None = None,
                        staged_beside: bool = False) -> None:
    """An output folder may exist (as a folder) or be created; no file may stand where a folder is needed, and it
    must be writable (with ``staged_beside``, for writers that build a new folder beside it and swap it in, the
    folder that holds it too). ``files`` (a name for the message -> a path: the run's input and output files) may
    not be the folder or lie above it (an output file about to be written where the folder goes)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{name} {path} exists and is not a folder")
    blocker = _file_ancestor(path)
    if blocker is not None:
        raise InputError(f"{name} {path}: {blocker} is a file, not a folder")
    key = _key(path)
    for other, file in (files or {}).items():
        if file is not None and (_key(file) == key or _key(file) in key.parents):
            raise InputError(f"{name} {path} is the file {other} {file}, or under it; choose another folder")
    path_abs = path.expanduser().absolute()
    if staged_beside or not path.is_dir():
        check_writable_folder(path_abs.parent, name, path)
    if path.is_dir():
        check_writable_folder(path_abs, name, path)


def check_writable_folder(folder: Path, name: str = "--out", path: Path | None = None) -> None:
    """Files can be made in ``folder``, or in the nearest folder above it that exists (it will be made there): not
    read-only (permissions, a read-only mount, an immutable folder). ``path``: the output named in the message
    (default: the folder itself)."""
    path = folder if path is None else path
    folder = Path(folder).expanduser().absolute()
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if folder.is_dir() and not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"{name} {path}: the folder {folder} cannot be written (read-only or no permission); choose another place")


def _key(path) -> Path:
    return Path(path).expanduser().resolve()


def _file_ancestor(path: Path) -> Path | None:
    for parent in Path(path).expanduser().absolute().parents:
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


# -- where the work runs: devices, torchrun's processes, shards ------------------------------------------------------
DEVICES = ("cpu", "cuda", "mps", "auto")
MAX_SHARDS = 100_000


def check_device(device, what: str = "--device") -> str:
    """``device`` (cpu, cuda, mps or auto) as the device torch will use: auto is CUDA, then MPS, then the CPU; a
    device this machine's torch cannot use is refused with what to do instead."""
    import torch

    name = str(device if device is not None else "cpu").strip().lower()
    if name not in DEVICES:
        raise InputError(f"{what} {device!r} is not a device: use cpu, cuda, mps or auto")
    mps = getattr(torch.backends, "mps", None)
    has_mps = mps is not None and mps.is_available()
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "mps" if has_mps else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        why = (f"this torch ({torch.__version__}) is built without CUDA" if torch.version.cuda is None
               else "no CUDA GPU is visible (check the driver and CUDA_VISIBLE_DEVICES)")
        raise InputError(f"{what} cuda: {why}; use {what} cpu, or auto to take a GPU where there is one")
    if name == "mps" and not has_mps:
        raise InputError(f"{what} mps: Metal (MPS) is not available on this machine; use {what} cpu or auto")
    return name


@dataclass(frozen=True)
class World:
    """This process's place among torchrun's: rank (0 .. size - 1) across all machines, local_rank on this one."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0


def check_world(env, device: str = "cpu") -> World:
    """torchrun's RANK, WORLD_SIZE and LOCAL_RANK (``env``: a mapping such as os.environ) checked; no WORLD_SIZE is
    one process. Several processes need torchrun's rendezvous (MASTER_ADDR, MASTER_PORT), a CPU or CUDA device (gloo
    or NCCL; MPS has no collective backend) and, on CUDA, a GPU per process of the machine."""
    if env.get("WORLD_SIZE") in (None, ""):
        return World()
    values = {}
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK"):
        text = str(env.get(name, "")).strip()
        if not text.isdigit():
            raise InputError(f"{name}={env.get(name, '')!r} is not a whole number: start several processes with "
                             "torchrun --nproc_per_node N (it sets RANK, WORLD_SIZE and LOCAL_RANK)")
        values[name] = int(text)
    size, rank, local = values["WORLD_SIZE"], values["RANK"], values["LOCAL_RANK"]
    if not 1 <= size <= MAX_SHARDS:
        raise InputError(f"WORLD_SIZE={size} is not a number of processes (1 to {MAX_SHARDS})")
    if rank >= size or local > rank:
        raise InputError(f"RANK={rank}, LOCAL_RANK={local} do not fit WORLD_SIZE={size}: start the run with torchrun")
    if size > 1:
        missing = [name for name in ("MASTER_ADDR", "MASTER_PORT") if not env.get(name)]
        if missing:
            raise InputError(f"WORLD_SIZE={size} but {' and '.join(missing)} not set: start the run with torchrun")
        if device == "mps":
            raise InputError("--device mps runs in one process (MPS has no collective backend): train on cpu or "
                             "cuda under torchrun")
        if device == "cuda":
            import torch

            if local >= torch.cuda.device_count():
                raise InputError(f"LOCAL_RANK={local} but this machine has {torch.cuda.device_count()} CUDA GPU(s): "
                                 "start at most one process per GPU (torchrun --nproc_per_node)")
    return World(rank, size, local)


def check_shard(shard, what: str = "--shard") -> tuple[int, int]:
    """``I/N`` (shard I of N, counted from 0) as (I, N)."""
    text = str(shard).strip()
    match = re.fullmatch(r"(\d+)\s*/\s*(\d+)", text)
    if match is None:
        raise InputError(f"{what} {shard!r} is not I/N: give the shard's index (from 0) and the number of shards, "
                         "e.g. 0/4")
    index, count = int(match.group(1)), int(match.group(2))
    if not 1 <= count <= MAX_SHARDS:
        raise InputError(f"{what} {text}: the number of shards must be 1 to {MAX_SHARDS}")
    if index >= count:
        raise InputError(f"{what} {text}: the index must be 0 to {count - 1} (shards are counted from 0)")
    return index, count
