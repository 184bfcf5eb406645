"""Model folders: ``config.json`` (every config, skeleton, fps, normalisation stats, provenance), one safetensors file per
component and a ``MODEL_CARD.md``. Loading never unpickles; a missing or corrupt file raises ``CheckpointError`` naming it.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from mld_core.bundled import DEFAULT_NAME, MODEL_FORMAT, WEIGHTS_DIR
from mld_core.condition import side_contrast
from mld_core.condition.content_anchor import ContentAnchorConfig
from mld_core.data import terms
from mld_core.fileio import atomic_write
from mld_core.inputs import MAX_SIDE_REDRAWS, MAX_VERB_REDRAWS
from mld_core.models.denoiser import DenoiserConfig
from mld_core.models.vae import VAEConfig
from mld_core.take_fixes.repair import RepairConfig
from mld_core.schedulers import LCMScheduler, SchedulerConfig
from mld_core.take_fixes.stepping import SteppingConfig

FORMAT = MODEL_FORMAT
FORMAT_VERSION = 1
DEFAULT_MODEL_DIR = WEIGHTS_DIR / DEFAULT_NAME
PROJECT_ROOT = DEFAULT_MODEL_DIR.parents[2]  # the checkout that holds mld_core


def recorded_path(path: str | None) -> str | None:
    """A path as a model's provenance records it: relative to the project's checkout when inside it (the bundled
    model is ``mld_core/weights/default`` on every machine), else as given."""
    if path is None:
        return None
    resolved = Path(path).resolve()
    return resolved.relative_to(PROJECT_ROOT).as_posix() if resolved.is_relative_to(PROJECT_ROOT) else str(path)


class CheckpointError(Exception):
    """A model folder that cannot be used; the message names the file and what is wrong."""


DRAFT_TEXT_WEIGHTS = "draft_text.safetensors"  # the Draft's distilled text encoder layers (draft.text_layers)
VERB_WEIGHTS = "verb_denoiser.safetensors"  # the verb denoiser (verb_guide)


@dataclass
class DraftConfig:
    """The Draft denoiser (``draft.safetensors``): a latent consistency model distilled from the model's denoiser
    (mld_core.training.draft); it takes the guidance scale as an input and samples in a few steps."""

    denoiser: DenoiserConfig = field(default_factory=lambda: DenoiserConfig(guidance_input=True))
    num_inference_steps: int = 2
    original_steps: int = 50  # the DDIM grid it was distilled on
    timestep_scaling: float = 10.0
    sigma_data: float = 0.5
    guidance_min: float = 3.0  # the guidance scales it was distilled for (an input of its denoiser)
    guidance_max: float = 5.0
    guidance_scale: float | None = None  # the Draft's default scale (None: the model's guidance_scale)
    fresh_noise: float = 1.0  # share of new noise when re-noising between steps (LCMScheduler; 1: LCM's sampler)
    teacher_steps: int = 0  # the last steps of a Draft (all but the first at most) are guided DDIM steps of the
    #                         model's own denoiser, which the Draft was distilled from: they finish the sample
    teacher_guidance: float | None = None  # the guidance scale of the teacher steps (None: the Draft's scale)
    text_layers: int | None = None  # the Draft encodes prompts with this many distilled layers of the model's
    #                                 MiniLM (draft_text.safetensors; mld_core.training.draft_text); None: all of it
    timesteps: list | None = None  # the timesteps of its num_inference_steps steps, points of the grid (descending);
    #                                None: spread evenly. With a teacher step, the last is where the teacher takes over
    teacher_verb_guide: bool = False  # the teacher steps carry the verb denoiser's term too (config verb_guide), at
    #                                   its scale x teacher_guidance / the model's guidance_scale
    verb_redraws: int | None = None  # a Draft take's verb redraws (None: the model's verb_redraws); a Draft's draw
    #                                  costs about a tenth of the Final's, so it can afford more

    def __post_init__(self):
        if isinstance(self.denoiser, dict):
            self.denoiser = DenoiserConfig(**self.denoiser)


@dataclass
class VerbGuideConfig:
    """A verb denoiser (``verb_denoiser.safetensors``): an action-conditioned denoiser on the model's own latents
    whose label guides, at ``scale``, the Final takes of prompts that name it by a checked verb
    (mld_core.condition.verb_guide)."""

    denoiser: DenoiserConfig = field(default_factory=lambda: DenoiserConfig(cond="action"))
    actions: list = field(default_factory=list)  # its labels, in the order of its class embedding
    scale: float = 8.0

    def __post_init__(self):
        if isinstance(self.denoiser, dict):
            self.denoiser = DenoiserConfig(**self.denoiser)
        if self.denoiser.cond != "action" or len(self.actions) != self.denoiser.num_actions:
            raise ValueError(f"verb_guide: an action denoiser with one label per class, got cond "
                             f"{self.denoiser.cond!r} with {self.denoiser.num_actions} classes and "
                             f"{len(self.actions)} labels")


@dataclass
class ModelConfig:
    """Everything needed to rebuild a model from its folder (saved as config.json)."""

    model_id: str = "mld-untrained"
    vae: VAEConfig = field(default_factory=VAEConfig)
    denoiser: DenoiserConfig | None = None
    scheduler: SchedulerConfig = field(default_factory=SchedulerConfig)
    text_encoder: dict = field(default_factory=lambda: {"kind": "minilm", "path": None})
    fps: int = 20
    min_frames: int = 20
    max_frames: int = 196
    mean: list = field(default_factory=list)
    std: list = field(default_factory=list)
    latent_scale: float = 1.0  # z_diffusion = latent_scale * (mu - latent_mean)
    latent_mean: float = 0.0
    actions: list = field(default_factory=list)
    guidance_scale: float = 4.0
    num_inference_steps: int = 50
    skeleton: dict = field(default_factory=dict)
    repair: RepairConfig = field(default_factory=RepairConfig)  # mld_core.take_fixes.repair, on free 263-d takes
    stepping: SteppingConfig = field(default_factory=SteppingConfig)  # mld_core.take_fixes.stepping: latents step
    side_redraws: int = 2  # a free take that misses the side its prompt names is drawn again, at most this often
    verb_redraws: int = 0  # a free take that does not show the checked verbs its prompt names: drawn again, as often
    content_anchor: ContentAnchorConfig = field(default_factory=ContentAnchorConfig)  # prompts' vectors moved
    side_contrast: float = 0.0  # a sided prompt's vector pushed from its mirror's (mld_core.condition.side_contrast)
    # a bare command ("jump") encoded as the captions word it ("a person jumps"; mld_core.condition.wording)
    commands_as_sentences: bool = True
    draft: DraftConfig | None = None  # a Draft denoiser in draft.safetensors (pipe(..., draft=True))
    verb_guide: VerbGuideConfig | None = None  # a verb denoiser in verb_denoiser.safetensors (Final's text takes)
    # whose terms the weights carry: every data folder and model its weights were trained on or from
    # (mld_core.data.terms); None: not recorded (its terms unknown)
    training_data: list | None = None
    provenance: dict = field(default_factory=dict)

    def __post_init__(self):
        if isinstance(self.content_anchor, dict):
            self.content_anchor = ContentAnchorConfig(**self.content_anchor)
        elif not isinstance(self.content_anchor, ContentAnchorConfig):
            raise ValueError(f"content_anchor must be a JSON object, got {self.content_anchor!r}")
        if isinstance(self.repair, dict):
            self.repair = RepairConfig(**self.repair)
        elif not isinstance(self.repair, RepairConfig):
            raise ValueError(f"repair must be a JSON object, got {self.repair!r}")
        if isinstance(self.stepping, dict):
            self.stepping = SteppingConfig(**self.stepping)
        elif not isinstance(self.stepping, SteppingConfig):
            raise ValueError(f"stepping must be a JSON object, got {self.stepping!r}")
        if isinstance(self.vae, dict):
            self.vae = VAEConfig(**self.vae)
        if isinstance(self.denoiser, dict):
            self.denoiser = DenoiserConfig(**self.denoiser)
        if isinstance(self.scheduler, dict):
            self.scheduler = SchedulerConfig(**self.scheduler)
        if isinstance(self.draft, dict):
            self.draft = DraftConfig(**self.draft)
        if isinstance(self.verb_guide, dict):
            self.verb_guide = VerbGuideConfig(**self.verb_guide)
        if self.training_data is not None:
            self.training_data = terms.checked(self.training_data)

    def to_dict(self) -> dict:
        return {"format": FORMAT, "format_version": FORMAT_VERSION, **asdict(self)}

    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        data = {k: v for k, v in data.items() if k not in ("format", "format_version")}
        known = set(cls.__dataclass_fields__)
        return cls(**{k: v for k, v in data.items() if k in known})

    @property
    def mean_std(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.mean, np.float32), np.asarray(self.std, np.float32)


def skeleton_info() -> dict:
    from mld_core.motion import skeleton

    return {"joint_names": list(skeleton.JOINT_NAMES), "parents": [int(p) for p in skeleton.PARENTS],
            "reference_offsets": np.asarray(skeleton.REFERENCE_OFFSETS).round(6).tolist()}


def save_json(path: Path, data: dict) -> None:
    atomic_write(Path(path), lambda tmp: Path(tmp).write_text(json.dumps(data, indent=2) + "\n"))


def save_weights(path: Path, module: torch.nn.Module, dtype: torch.dtype | None = None) -> None:
    state = {k: (v.to(dtype) if dtype is not None and v.is_floating_point() else v).detach().contiguous().cpu()
             for k, v in module.state_dict().items()}
    atomic_write(Path(path), lambda tmp: save_file(state, tmp, metadata={"format": "pt"}))


def load_weights(path: Path, module: torch.nn.Module) -> None:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"missing weights file: {path}")
    try:
        state = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"corrupt weights file {path}: {exc}") from None
    expected = module.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise CheckpointError(f"weights file {path} does not match its config.json: "
                              f"missing {missing[:5]}, unexpected {unexpected[:5]}")
    for key, value in state.items():
        if value.shape != expected[key].shape:
            raise CheckpointError(f"weights file {path}: {key} has shape {tuple(value.shape)}, "
                                  f"config.json expects {tuple(expected[key].shape)}")
    module.load_state_dict({k: v.to(expected[k].dtype) for k, v in state.items()})


def load_config(model_dir: Path) -> ModelConfig:
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise CheckpointError(f"model folder not found: {model_dir}")
    path = model_dir / "config.json"
    if not path.is_file():
        raise CheckpointError(f"missing {path} (not a model folder?)")
    try:
        data = json.loads(path.read_text())
        if not isinstance(data, dict):
            raise ValueError(f"expected a JSON object, got a {type(data).__name__}")
        if data.get("format") != FORMAT:
            raise ValueError(f"format is {data.get('format')!r}, expected {FORMAT!r}")
        for name in ("vae", "denoiser", "scheduler", "text_encoder", "draft", "verb_guide"):
            if data.get(name) is not None and not isinstance(data[name], dict):
                raise ValueError(f"{name} must be an object, got {data[name]!r}")
        config = ModelConfig.from_dict(data)
        check_config(config)
        return config
    except RecursionError:
        raise CheckpointError(f"corrupt {path}: nested too deeply") from None
    except (ValueError, TypeError, KeyError, AttributeError, OSError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"corrupt {path}: {exc}") from None


def check_config(config: ModelConfig) -> None:
    """Values a model cannot run with: non-positive or non-integer lengths and fps, non-finite or zero stats."""
    for name in ("fps", "min_frames", "max_frames", "num_inference_steps"):
        value = getattr(config, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive whole number, got {value!r}")
    if config.min_frames > config.max_frames:
        raise ValueError(f"min_frames ({config.min_frames}) is above max_frames ({config.max_frames})")
    for name in ("guidance_scale", "latent_scale", "latent_mean"):
        value = getattr(config, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
    mean, std = (np.asarray(v, np.float64) for v in (config.mean, config.std))
    if not (np.isfinite(mean).all() and np.isfinite(std).all()):
        raise ValueError("mean/std hold non-finite values (NaN or inf)")
    if (std <= 0).any():
        raise ValueError("std must be positive")
    _check_repair(config.repair)
    _check_stepping(config.stepping)
    for name, most in (("side_redraws", MAX_SIDE_REDRAWS), ("verb_redraws", MAX_VERB_REDRAWS)):
        redraws = getattr(config, name)
        if isinstance(redraws, bool) or not isinstance(redraws, int) or not 0 <= redraws <= most:
            raise ValueError(f"{name} must be a whole number in 0..{most}, got {redraws!r}")
    config.content_anchor.check()
    side_contrast.check_weight(config.side_contrast)
    if not isinstance(config.commands_as_sentences, bool):
        raise ValueError(f"commands_as_sentences must be true or false, got {config.commands_as_sentences!r}")
    if config.draft is not None:
        _check_draft(config.draft, config.scheduler)
    if config.verb_guide is not None:
        _check_verb_guide(config.verb_guide, config.vae)


def _check_verb_guide(guide: VerbGuideConfig, vae: VAEConfig) -> None:
    scale = guide.scale
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0 <= scale < 100:
        raise ValueError(f"verb_guide.scale must be a number in [0, 100), got {scale!r}")
    den = guide.denoiser
    if (den.latent_tokens, den.latent_dim) != (vae.latent_tokens, vae.latent_dim):
        raise ValueError(f"verb_guide: its denoiser's latent {den.latent_tokens} x {den.latent_dim} is not the "
                         f"VAE's {vae.latent_tokens} x {vae.latent_dim}")


def _check_draft(draft: DraftConfig, scheduler: SchedulerConfig) -> None:
    train_timesteps = scheduler.num_train_timesteps
    grid = draft.original_steps
    if isinstance(grid, bool) or not isinstance(grid, int) or not 1 <= grid <= train_timesteps:
        raise ValueError(f"draft.original_steps must be a whole number in 1..{train_timesteps}, got {grid!r}")
    steps = draft.num_inference_steps
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= grid:
        raise ValueError(f"draft.num_inference_steps must be a whole number in 1..{grid}, got {steps!r}")
    for name in ("timestep_scaling", "sigma_data", "guidance_min", "guidance_max"):
        value = getattr(draft, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
            raise ValueError(f"draft.{name} must be a finite number above 0, got {value!r}")
    if draft.guidance_min > draft.guidance_max:
        raise ValueError("draft.guidance_min must be at most draft.guidance_max")
    scale = draft.guidance_scale
    if scale is not None and (isinstance(scale, bool) or not isinstance(scale, (int, float))
                              or not draft.guidance_min <= scale <= draft.guidance_max):
        raise ValueError(f"draft.guidance_scale must be null or between draft.guidance_min and guidance_max, "
                         f"got {scale!r}")
    teacher = draft.teacher_steps
    if isinstance(teacher, bool) or not isinstance(teacher, int) or not 0 <= teacher < grid:
        raise ValueError(f"draft.teacher_steps must be a whole number in 0..{grid - 1}, got {teacher!r}")
    fresh = draft.fresh_noise
    if isinstance(fresh, bool) or not isinstance(fresh, (int, float)) or not 0.0 <= fresh <= 1.0:
        raise ValueError(f"draft.fresh_noise must be a number in 0..1, got {fresh!r}")
    guidance = draft.teacher_guidance
    if guidance is not None and (isinstance(guidance, bool) or not isinstance(guidance, (int, float))
                                 or not math.isfinite(guidance) or guidance < 1.0):
        raise ValueError(f"draft.teacher_guidance must be null or a finite number of at least 1, got {guidance!r}")
    layers = draft.text_layers
    if layers is not None and (isinstance(layers, bool) or not isinstance(layers, int) or layers < 1):
        raise ValueError(f"draft.text_layers must be null or a whole number above 0, got {layers!r}")
    if not isinstance(draft.teacher_verb_guide, bool):
        raise ValueError(f"draft.teacher_verb_guide must be true or false, got {draft.teacher_verb_guide!r}")
    redraws = draft.verb_redraws
    if redraws is not None and (isinstance(redraws, bool) or not isinstance(redraws, int)
                                or not 0 <= redraws <= MAX_VERB_REDRAWS):
        raise ValueError(f"draft.verb_redraws must be null or a whole number in 0..{MAX_VERB_REDRAWS}, got {redraws!r}")
    if draft.timesteps is not None:
        try:
            LCMScheduler(scheduler, grid).checked_timesteps(
                draft.timesteps, steps)
        except ValueError as exc:
            raise ValueError(f"draft.timesteps: {exc}") from None
    if not draft.denoiser.guidance_input:
        raise ValueError("draft.denoiser must take the guidance scale as an input (guidance_input true)")


def _check_repair(repair: RepairConfig) -> None:
    for name in ("bone_lengths", "plant_feet", "lock_feet", "on_floor"):
        if not isinstance(getattr(repair, name), bool):
            raise ValueError(f"repair.{name} must be true or false, got {getattr(repair, name)!r}")
    for name in ("contact_height_m", "model_weight", "smooth_frames", "max_correction_m",
                 "keep_travel_frames", "min_travel_kept", "min_travel_m", "lock_release", "max_lock_shift_m",
                 "lock_min_knee_deg", "lock_max_double_support"):
        value = getattr(repair, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
            raise ValueError(f"repair.{name} must be a finite number >= 0, got {value!r}")
    if repair.model_weight <= 0:
        raise ValueError("repair.model_weight must be above 0")
    for name in ("lock_release", "lock_max_double_support"):
        if getattr(repair, name) > 1:
            raise ValueError(f"repair.{name} must be between 0 and 1, got {getattr(repair, name)!r}")
    if repair.lock_min_knee_deg >= 90:
        raise ValueError(f"repair.lock_min_knee_deg must be below 90, got {repair.lock_min_knee_deg!r}")


def _check_stepping(stepping: SteppingConfig) -> None:
    steps = stepping.steps
    if isinstance(steps, bool) or not isinstance(steps, int) or not 0 <= steps <= 1000:
        raise ValueError(f"stepping.steps must be a whole number in 0..1000, got {steps!r}")
    for name in ("lr", "contact_height_m", "contact_softness_m", "slide_m", "velocity_weight", "turn_weight",
                 "stride_weight", "support_weight", "prior_weight", "min_slide_share"):
        value = getattr(stepping, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
            raise ValueError(f"stepping.{name} must be a finite number >= 0, got {value!r}")
    for name in ("lr", "contact_softness_m", "slide_m"):
        if getattr(stepping, name) <= 0:
            raise ValueError(f"stepping.{name} must be above 0")
    if not isinstance(stepping.keep_if_less_skating, bool):
        raise ValueError(f"stepping.keep_if_less_skating must be true or false, got {stepping.keep_if_less_skating!r}")


def save_model(model_dir: Path, config: ModelConfig, vae: torch.nn.Module, denoiser: torch.nn.Module | None = None,
               dtype: torch.dtype | None = None, card: str | None = None) -> Path:
    """Write a complete model folder (weights first, config.json last, each file atomically)."""
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    save_weights(model_dir / "vae.safetensors", vae, dtype)
    if denoiser is not None:
        save_weights(model_dir / "denoiser.safetensors", denoiser, dtype)
    if card is not None:
        atomic_write(model_dir / "MODEL_CARD.md", lambda tmp: Path(tmp).write_text(card))
    save_json(model_dir / "config.json", config.to_dict())
    return model_dir
