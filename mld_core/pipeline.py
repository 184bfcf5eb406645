"""Text/action/unconditional motion generation with a trained MLD model folder.

    pipe = MLDPipeline.from_pretrained()            # the bundled default model
    out = pipe(["a person waves the right hand"], seconds=4, seed=0)
    out.joints  # (N, T, 22, 3) metres, Y up, facing +Z at frame 0

A call is six stages (``MLDPipeline.__call__``): the inputs checked; prompt -> condition (mld_core.condition); z_T;
the denoising loop (mld_core.sampling: Final or Draft); decode and take fixes in their order (mld_core.decode,
mld_core.take_fixes); the output, ranked when asked.

Paper symbols: z_T ~ N(0, I) the initial latent, eps_theta(z_t, t, c) the denoiser, s the guidance scale,
eps = eps(z_t, t, null) + s * (eps(z_t, t, c) - eps(z_t, t, null)), D the VAE decoder, x = D(z_0 / scale + mean).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np
import torch

from mld_core import inputs
from mld_core.bundled import UnknownModel, model_folder
from mld_core.checkpoint import (DEFAULT_MODEL_DIR, DRAFT_TEXT_WEIGHTS, VERB_WEIGHTS, CheckpointError, ModelConfig,
                                 load_config, load_weights)
from mld_core.condition import content_anchor
from mld_core.condition import text as text_condition
from mld_core.condition import verb_hint
from mld_core.condition.coverage import INDEX_NAME, load_for_model, unavailable
from mld_core.condition.verb_guide import VerbGuide
from mld_core.decode import LatentDecoder
from mld_core.eval.quality import REAL_JERK_P95, seam_jerk
from mld_core.inputs import InputError
from mld_core.models.denoiser import LatentDenoiser
from mld_core.models.transformer import native_bf16, packing_available, packs_in
from mld_core.models.vae import MotionVAE
from mld_core.motion.features import features_to_joints
from mld_core.sampling import Conditions, DraftSampler, FinalSampler, VerbGuidance, initial_latents
from mld_core.schedulers import DDIMScheduler, LCMScheduler
from mld_core.take_fixes.constraints import Constraints, brief
from mld_core.take_fixes.order import Takes, fixes_for
from mld_core.take_fixes.repair import lock_feet, repair_rows


PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16}
DRAFT_PRECISIONS = ("auto", *PRECISIONS)


def draft_precision_for(choice: str, device: str | torch.device = "cpu") -> str:
    """The precision a Draft runs in: ``"auto"`` is bf16 on a CPU that computes bfloat16 natively (AVX512-BF16 or
    AMX: text encoder, denoiser and decoder each about 1.3-1.5x faster) and fp32 elsewhere."""
    if choice not in DRAFT_PRECISIONS:
        raise ValueError(f"draft_precision must be one of {', '.join(DRAFT_PRECISIONS)}, got {choice!r}")
    # bf16 products need oneDNN's packed ops, which pack bfloat16 only with AVX512-BW/VL/DQ or AVX-NE-CONVERT
    packs = torch.device(device).type == "cpu" and packing_available() and packs_in(torch.bfloat16)
    if choice == "bf16" and not packs:
        warnings.warn("draft_precision bf16 needs a CPU whose oneDNN packs bfloat16: the Draft runs in fp32",
                      stacklevel=3)
    if choice != "auto":
        return choice if packs else "fp32"
    return "bf16" if packs and native_bf16() else "fp32"


class Cancelled(Exception):
    """Raised when the progress callback returns False."""


@dataclass
class MLDOutput:
    features: np.ndarray  # (N, T, F) float32, denormalised, zero beyond each length
    joints: np.ndarray  # (N, T, 22, 3) float32 metres; frames beyond a length repeat its last frame
    lengths: np.ndarray  # (N,) int frames
    prompts: list
    seeds: list
    fps: int = 20
    model_id: str = ""
    timings: dict = field(default_factory=dict)
    badges: list | None = None  # per row a mld_core.eval.quality.Badges when generated with rank=True
    residuals: list | None = None  # per row [(kind, metres, met)] when generated with constraints
    draws: list | None = None  # per row, which z_T of its seed the take is (0: the first; redraws: 1, 2, ...)
    # per row, the redraw that drew it again ("side", "verb"), or found no draw that met its prompt (either + " missed")
    redrawn_for: list | None = None
    seams: list | None = None  # per row of a sequence [(segment, largest joint jerk m/s^3 at its seam, within real)]

    def select(self, rows: Sequence[int]) -> "MLDOutput":
        """These rows, in this order (every per-row field follows them)."""
        rows = list(rows)

        def pick(values):
            return None if values is None else [values[i] for i in rows]

        return replace(self, features=self.features[rows], joints=self.joints[rows], lengths=self.lengths[rows],
                       prompts=pick(self.prompts), seeds=pick(self.seeds), badges=pick(self.badges),
                       residuals=pick(self.residuals), draws=pick(self.draws), redrawn_for=pick(self.redrawn_for),
                       seams=pick(self.seams))


def _prompt_list(prompts) -> list[str]:
    """A prompt or a list of prompts as a list; anything but text refused."""
    if prompts is None or isinstance(prompts, bytes) or not isinstance(prompts, (str, Sequence)):
        raise InputError(f"prompts must be a string or a list of strings, got {type(prompts).__name__}")
    prompts = [prompts] if isinstance(prompts, str) else list(prompts)
    for n, prompt in enumerate(prompts, start=1):
        if not isinstance(prompt, str):
            raise InputError(f"prompt {n} must be text, not {type(prompt).__name__}")
    return prompts


def _check_constraints(constraints, frames: list[int]) -> None:
    """``constraints`` (None or a Constraints) fit takes of ``frames`` model frames: one length, no frame beyond it."""
    if constraints is None:
        return
    if not isinstance(constraints, Constraints):
        raise InputError("constraints must be a mld_core.take_fixes.constraints.Constraints, e.g. "
                         f"Constraints([Loop()]), got {type(constraints).__name__}")
    if constraints and len(set(frames)) > 1:
        raise InputError("constraints need every motion of a call to have the same length")
    if constraints:
        constraints.check_frames(frames[0])


def _as_list(value, n: int, name: str) -> list:
    if isinstance(value, (str, int, float, np.integer, np.floating)) or value is None:
        return [value] * n
    value = list(value)
    if len(value) != n:
        raise ValueError(f"{name} has {len(value)} entries for {n} prompts")
    return value


@dataclass
class _Call:
    """One call's inputs, checked: one row per (prompt, variant)."""

    cond_kind: str  # "text", "action" or "none" (unconditional)
    draft: bool
    prompts: list  # per row
    actions: list | None  # per row
    seconds: list  # per row
    seeds: list  # per row
    lengths: torch.Tensor  # (B,) frames
    steps: int
    guidance: float
    teacher_steps: int  # a Draft's last steps, made by its teacher
    num_variants: int
    draw: int
    side_redraws: int  # 0 for a model not conditioned on text
    verb_redraws: int  # 0 for a model not conditioned on text


class MLDPipeline:
    def __init__(self, config: ModelConfig, vae: MotionVAE, denoiser: LatentDenoiser | None, text_encoder=None,
                 device: str | torch.device = "cpu", precision: str = "fp32",
                 draft_denoiser: LatentDenoiser | None = None, draft_precision: str = "auto",
                 draft_text_encoder=None):
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        self.config = config
        self.device = torch.device(device)
        self.precision = precision
        self.vae = vae.eval().to(self.device)
        self.vae.decoder.pack_for_cpu_inference()  # no-op off CPU
        # The Draft runs in its own precision (draft_precision_for); in bf16 it keeps its own copies of the decoder
        # and the teacher (bf16 products) and of the text encoder (when given), so Final's takes never change.
        self.draft_precision = draft_precision_for(draft_precision, self.device)
        self.draft_vae, self.draft_text_encoder, self.draft_teacher = self.vae, text_encoder, None
        if config.draft is not None and draft_denoiser is not None and denoiser is not None \
                and config.draft.teacher_steps and (self.draft_precision != "fp32" or precision != "fp32"):
            self.draft_teacher = _denoiser_copy(denoiser, config.denoiser, self.device,
                                                PRECISIONS[self.draft_precision])  # from the float32 weights
        # The denoiser runs 2 x 50 times per prompt: in bf16 its weights are cast once (text encoder, VAE and the
        # DDIM update stay in float32).
        self.denoiser = denoiser.eval().to(self.device, PRECISIONS[precision]) if denoiser is not None else None
        if self.denoiser is not None:
            self.denoiser.transformer.pack_for_cpu_inference()  # no-op off CPU
        self.text_encoder = text_encoder
        if hasattr(text_encoder, "pack_for_cpu_inference") and self.device.type == "cpu":
            text_encoder.pack_for_cpu_inference()
        self.scheduler = DDIMScheduler(config.scheduler)
        self.draft_denoiser = None  # the Draft (consistency-distilled) denoiser, from draft.safetensors
        self.draft_problem = ""  # why a model folder's Draft could not be loaded (from_pretrained)
        self.draft_scheduler = None
        if config.draft is not None and draft_denoiser is not None:
            # Its denoisers keep float32 weights; their transformer layers' products run in the Draft's precision
            # (the small projections and MLPs run faster unpacked in float32 than in bfloat16).
            draft_dtype = PRECISIONS[self.draft_precision]
            self.draft_denoiser = draft_denoiser.eval().to(self.device)
            self.draft_denoiser.transformer.pack_for_cpu_inference(draft_dtype)
            if self.draft_teacher is None:  # runs a Draft's teacher steps (config draft.teacher_steps)
                self.draft_teacher = self.denoiser
            if draft_dtype != torch.float32:
                self.draft_vae = _vae_copy(vae, config.vae, self.device, draft_dtype)
            if draft_text_encoder is not None:  # its own: distilled layers (draft.text_layers) and/or bf16
                self.draft_text_encoder = draft_text_encoder
                if hasattr(draft_text_encoder, "pack_for_cpu_inference") and self.device.type == "cpu":
                    draft_text_encoder.pack_for_cpu_inference()
            d = config.draft
            self.draft_scheduler = LCMScheduler(config.scheduler, d.original_steps, d.timestep_scaling, d.sigma_data,
                                                d.fresh_noise).to(self.device)
        self._text_cache = text_condition.TextCache()  # prompt -> its TextEmbedding (one row, its own tokens)
        self._draft_text_cache = text_condition.TextCache()  # the same for the Draft's text encoder
        self.coverage_index = None  # mld_core.condition.coverage.CoverageIndex, from coverage_index.npz
        self.content_anchor = None  # mld_core.condition.content_anchor.ContentAnchor, from content_anchor.safetensors
        self.verb_guide = None  # mld_core.condition.verb_guide.VerbGuide: a verb denoiser guiding Final's text takes
        self._quality = None  # mld_core.eval.quality.QualityScorer, loaded on first use
        mean, std = config.mean_std
        self.mean, self.std = mean, std
        self.decoder = LatentDecoder(config, self.vae, self.draft_vae, self.device, mean, std)  # the decode stage

    # -- loading ----------------------------------------------------------------------------------------------
    @classmethod
    def from_pretrained(cls, path: str | Path | None = None, device: str = "cpu", text_encoder=None,
                        precision: str = "fp32", draft_precision: str = "auto") -> "MLDPipeline":
        """Load a model folder (None: the bundled default; a bundled model's name, e.g. "v4_preview", names its
        folder: mld_core.bundled). ``text_encoder`` overrides the one named in config.json.
        ``precision="bf16"`` runs the denoiser in bfloat16: faster on CPUs with native bfloat16 (AVX512-BF16, AMX),
        samples close to but not bit-equal to float32's. ``draft_precision`` is the Draft's (draft_precision_for)."""
        try:
            model_dir = model_folder(path)
        except UnknownModel as exc:
            raise CheckpointError(str(exc)) from None
        config = load_config(model_dir)
        vae = MotionVAE(config.vae)
        load_weights(model_dir / "vae.safetensors", vae)
        denoiser, own_text = None, text_encoder is None  # own_text: the Draft may load its own copy in bf16
        if config.denoiser is not None:
            denoiser = LatentDenoiser(config.denoiser)
            load_weights(model_dir / "denoiser.safetensors", denoiser)
            if config.denoiser.cond == "text" and text_encoder is None:
                from mld_core.models.text_encoder import load_text_encoder

                try:
                    text_encoder = load_text_encoder(config.text_encoder)
                except (ValueError, TypeError) as exc:
                    raise CheckpointError(f"{model_dir / 'config.json'}: text_encoder: {exc}") from None
        draft_precision = draft_precision_for(draft_precision, device)  # resolved once (and warned once)
        draft, draft_problem, draft_text = None, "", None
        if config.draft is not None and denoiser is not None:
            try:  # a broken Draft costs only the Draft: Final still samples
                draft = LatentDenoiser(config.draft.denoiser)
                load_weights(model_dir / "draft.safetensors", draft)
            except CheckpointError as exc:
                draft, draft_problem = None, str(exc)
                warnings.warn(f"Draft mode is unavailable: {exc}", stacklevel=2)
            if draft is not None and own_text and text_encoder is not None:
                draft_text = _draft_text_encoder(model_dir, config, draft_precision)
        if len(config.mean) != config.vae.feature_dim or len(config.std) != config.vae.feature_dim:
            raise CheckpointError(f"{model_dir / 'config.json'}: mean/std must have {config.vae.feature_dim} values")
        pipe = cls(config, vae, denoiser, text_encoder, device, precision, draft, draft_precision, draft_text)
        pipe.draft_problem = draft_problem
        if config.verb_guide is not None and denoiser is not None and config.denoiser.cond == "text":
            pipe.verb_guide = _verb_guide(model_dir, config, pipe.device, PRECISIONS[precision])
        try:
            pipe.coverage_index = load_for_model(model_dir)
            pipe.content_anchor = content_anchor.load_for_model(model_dir)
        except ValueError as exc:
            raise CheckpointError(str(exc)) from None
        anchor = config.content_anchor
        if anchor.weight and denoiser is not None and pipe.content_anchor is None:
            raise CheckpointError(f"{model_dir / 'config.json'}: content_anchor.weight is {anchor.weight} but the "
                                  f"folder has no {content_anchor.FILE_NAME}")
        if anchor.weight and anchor.full_below is not None and pipe.coverage_index is None:
            raise CheckpointError(f"{model_dir / 'config.json'}: content_anchor.full_below needs the folder's "
                                  f"coverage index ({INDEX_NAME}), which it does not have")
        return pipe

    # -- sizes --------------------------------------------------------------------------------------------------
    @property
    def model_id(self) -> str:
        return self.config.model_id

    @property
    def fps(self) -> int:
        return self.config.fps

    @property
    def min_seconds(self) -> float:
        return self.config.min_frames / self.config.fps

    @property
    def max_seconds(self) -> float:
        return self.config.max_frames / self.config.fps

    @property
    def draft_text_layers(self) -> int | None:
        """How many layers the Draft's text encoder runs (draft.text_layers, or all of the model's; None: an
        encoder without layers)."""
        layers = getattr(self.draft_text_encoder, "layers", None)
        return len(layers) if layers is not None else None

    def frames_for(self, seconds: float) -> int:
        if not np.isfinite(seconds) or not self.min_seconds <= seconds <= self.max_seconds:
            raise ValueError(f"seconds must be between {self.min_seconds:g} and {self.max_seconds:g}, got {seconds}")
        return int(round(seconds * self.config.fps))

    # -- decoding (mld_core.decode) -----------------------------------------------------------------------------
    def normalize(self, features: np.ndarray) -> np.ndarray:
        return self.decoder.normalize(features)

    def denormalize(self, features: np.ndarray) -> np.ndarray:
        return self.decoder.denormalize(features)

    def features_to_latents(self, features: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        """Denormalised feature clips [(T_i, F)] -> their VAE means in diffusion space (B, n, d) and lengths (B,)."""
        return self.decoder.latents(features)

    def latents_to_features(self, z: torch.Tensor, lengths: torch.Tensor, draft: bool = False) -> np.ndarray:
        """Diffusion-space latents (B, n, d) -> denormalised features (B, T, F), zero beyond each length; ``draft``
        decodes with the Draft's decoder (its precision)."""
        return self.decoder.features(z, lengths, draft)

    joints_from_features = staticmethod(LatentDecoder.joints)

    # -- conditions ---------------------------------------------------------------------------------------------
    def _condition(self, prompts: list, actions: list | None, kind: str, denoiser: LatentDenoiser,
                   draft: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(cond tokens, null tokens) of ``denoiser``, each (B, C, d); ``draft``: from the Draft's text encoder."""
        B = len(prompts)
        if kind == "text":
            text = self.text_embeddings(prompts, draft=draft)
            text = type(text)(**{k: v.to(self.device) for k, v in vars(text).items()})
            verbs = verb_hint.verb_ids(prompts, denoiser.config.verb_hints, self.device)  # (B,), 0: none named
            cond = denoiser.condition_tokens(B, text=text, verbs=verbs)
        elif kind == "action":
            ids = torch.tensor([self._action_id(a) for a in actions], device=self.device)
            cond = denoiser.condition_tokens(B, actions=ids)
        else:
            cond = denoiser.null_tokens(B)
        return cond, denoiser.null_tokens(B)

    def text_embeddings(self, prompts: list, draft: bool = False):
        """The text encoder's embeddings of ``prompts`` (a TextEmbedding, one row per prompt), their sentence vectors
        moved by the model's conditioning tricks (mld_core.condition.text); ``draft``: the Draft's encoder's. Each
        prompt is encoded once per encoder and kept (the last TextCache.SIZE): re-generating a prompt with other
        seconds or seeds, as the live preview does, skips the text encoder."""
        encoder = self.draft_text_encoder if draft else self.text_encoder
        cache = self._draft_text_cache if draft and encoder is not self.text_encoder else self._text_cache
        return cache.embeddings(prompts, lambda new: text_condition.encode(new, encoder, self.config,
                                                                           self.content_anchor, self.coverage_index))

    def clear_text_cache(self) -> None:
        """Forget every cached prompt embedding (the next call of a prompt runs its text encoder again)."""
        self._text_cache.clear()
        self._draft_text_cache.clear()

    def _action_id(self, action) -> int:
        names = self.config.actions
        if isinstance(action, (int, np.integer)) and 0 <= int(action) < len(names):
            return int(action)
        if action in names:
            return names.index(action)
        raise ValueError(f"unknown action {action!r}; this model knows: {', '.join(names)}")

    # -- prompt coverage and take quality ------------------------------------------------------------------------
    def coverage(self, prompts: str | Sequence[str]) -> list:
        """Per prompt a ``mld_core.condition.coverage.Coverage``: score, verdict known / near / unknown, the 3 nearest
        training captions and the model's known contents (verdict "unavailable" for a folder without a coverage
        index)."""
        prompts = _prompt_list(prompts)
        index = self.coverage_index
        if index is None or self.text_encoder is None:
            return [unavailable(p, self.config.actions) for p in prompts]
        return index.query(prompts, self.text_encoder)

    def quality_scorer(self):
        """The take-quality scorer (the bundled evaluator and its real-data reference), loaded once."""
        if self._quality is None:
            from mld_core.eval.quality import QualityScorer

            self._quality = QualityScorer.from_pretrained(text_encoder=self.text_encoder)
        return self._quality

    def default_guidance(self, draft: bool = False) -> float:
        """The guidance scale a call without one uses: the Draft's own (config ``draft.guidance_scale``) in Draft
        mode, else the model's."""
        if draft and self.config.draft is not None and self.config.draft.guidance_scale is not None:
            return float(self.config.draft.guidance_scale)
        return float(self.config.guidance_scale)

    # -- sampling -------------------------------------------------------------------------------------------------
    @torch.inference_mode()
    def __call__(self, prompts: str | Sequence[str], seconds: float | Sequence[float] = 4.0, *,
                 actions: Sequence | None = None, num_inference_steps: int | None = None,
                 guidance_scale: float | None = None, seed: int | Sequence[int] = 0, num_variants: int = 1,
                 callback: Callable[[int, int], bool | None] | None = None, unconditional: bool = False,
                 rank: bool = False, constraints=None, repair: bool = True, draft: bool = False,
                 step: bool | None = None, draw: int = 0, side_redraws: int | None = None,
                 verb_redraws: int | None = None) -> MLDOutput:
        """Generate ``num_variants`` motions per prompt; row i*num_variants + v uses seed ``seed + v``, or
        ``seed[i] + v`` when ``seed`` is a sequence (one per prompt). Any row equals the single run with its seed (a
        Draft in bf16: to within bf16 rounding, up to about 2 cm).

        - ``draft``: the model's Draft (config ``draft``: a few consistency steps, about 10x faster).
        - ``unconditional``: the null condition (the prompts then only label the rows).
        - ``constraints``: a ``mld_core.take_fixes.constraints.Constraints`` (poses to hit, a root path, a loop) each
          take is refined to meet; ``out.residuals`` says how well each row did.
        - ``step`` (default: as ``repair``): a Final take's feet made to step (config ``stepping``).
        - ``repair``: a free take's repairs (config ``repair``: one skeleton, planted feet).
        - ``side_redraws`` (default: config ``side_redraws``): a free take that misses the side its prompt names is
          drawn again, at most this often; ``draw`` k starts each row from the (k+1)-th z_T of its seed
          (``out.draws`` says which draw each row is, ``out.redrawn_for`` which redraw drew it).
        - ``verb_redraws`` (default: config ``verb_redraws``, a Draft's ``draft.verb_redraws`` where set): a free take
          that does not show the checked verbs its prompt names (mld_core.take_fixes.verb_redraw) is drawn again, at
          most this often.
        - ``rank``: every row scored (``out.badges``), each prompt's variants best first."""
        t_start, timings = time.perf_counter(), {}
        # 1. Inputs, checked before any work: one row per (prompt, variant), each with its own seed.
        call = self._call_rows(prompts, seconds, actions, num_inference_steps, guidance_scale, seed, num_variants,
                               unconditional, constraints, draft, draw, side_redraws, verb_redraws)
        # 2. Condition c and the null condition for classifier-free guidance (mld_core.condition.text: each prompt
        #    encoded once and kept, its sentence vector anchored and its named side made louder).
        t0 = time.perf_counter()
        conditions = self._conditions(call)
        timings["condition_s"] = time.perf_counter() - t0
        # 3. z_T ~ N(0, I), drawn per row from its own seeded generator, so that a batch equals single runs.
        z, generators = initial_latents(call.seeds, call.draw, self.config.vae.latent_tokens,
                                        self.config.vae.latent_dim, self.device)
        # 4. Denoising, one step at a time (mld_core.sampling): Final's DDIM steps or the Draft's consistency steps.
        t0 = time.perf_counter()
        sampler = self._sampler(call, conditions, generators)
        total = len(sampler.timesteps)
        for k, t in enumerate(sampler.timesteps):
            z = sampler.step(k, t, z)
            if callback is not None and callback(k + 1, total) is False:
                raise Cancelled(f"cancelled at step {k + 1} of {total}")
        timings["diffusion_s"] = time.perf_counter() - t0
        # 5. Decode and fix the takes in their order (mld_core.take_fixes.order): stepping, constraints (or the plain
        #    decode x = D(z_0)), repair, side redraw, verb redraw; each where it applies.
        takes = Takes(z, z, call.lengths, call.prompts, [call.draw] * len(call.seeds), draft)
        redo = partial(self._redraw, call, dict(callback=callback, repair=repair, draft=draft, step=step))
        for fix in fixes_for(self.config, draft=draft, step=repair if step is None else step, repair=repair,
                             constraints=constraints, side_redraws=call.side_redraws, redo=redo,
                             verb_redraws=call.verb_redraws, draw=call.draw):
            t0 = time.perf_counter()
            takes = fix.apply(takes, self.decoder)
            timings.update(dict.fromkeys(fix.timings, time.perf_counter() - t0))
        # 6. Output: joints; with constraints, how well each row met them; with rank, badges and variants best first.
        out = self._output(call, takes, constraints, timings)
        if rank:
            out = self._ranked(out, call, timings)
        timings["total_s"] = time.perf_counter() - t_start
        return out

    def _call_rows(self, prompts, seconds, actions, num_inference_steps, guidance_scale, seed, num_variants,
                   unconditional, constraints, draft, draw, side_redraws, verb_redraws) -> _Call:
        """Stage 1: a call's arguments checked and spread over its rows (errors before any work)."""
        if self.denoiser is None:
            raise CheckpointError("this model folder has only a VAE; sample with sample_prior() or train a denoiser")
        if draft and self.draft_denoiser is None:
            raise CheckpointError(f"Draft mode is unavailable: {self.draft_problem}" if self.draft_problem else
                                  f"the model {self.model_id} has no Draft denoiser (draft.safetensors); make one with "
                                  "`python -m mld_core train draft`")
        cond_kind = "none" if unconditional else self.denoiser.config.cond
        if prompts is None or not isinstance(prompts, (str, Sequence)):
            raise InputError(f"prompts must be a string or a list of strings, got {type(prompts).__name__}")
        prompts = [prompts] if isinstance(prompts, str) else list(prompts)
        if actions is not None and isinstance(actions, (str, int)):
            actions = [actions]
        n_prompts = len(actions) if (cond_kind == "action" and actions is not None and not prompts) else len(prompts)
        if n_prompts == 0:
            raise ValueError("no prompts given")
        if cond_kind == "action" and actions is None:
            raise ValueError("this model is conditioned on actions: pass actions=[...]")
        if cond_kind == "text" and any(not isinstance(p, str) or not p.strip() for p in prompts):
            raise ValueError("empty prompt")
        prompts = prompts or [""] * n_prompts
        actions = _as_list(actions, n_prompts, "actions") if actions is not None else None
        secs = _as_list(seconds, n_prompts, "seconds")
        frames = [self.frames_for(float(s)) for s in secs]
        default_steps = self.config.draft.num_inference_steps if draft else self.config.num_inference_steps
        steps = default_steps if num_inference_steps is None else num_inference_steps
        most = self.config.draft.original_steps if draft else 1000
        steps = inputs.int_in_range(steps, "num_inference_steps", 1, most)
        s = inputs.finite_number(self.default_guidance(draft) if guidance_scale is None else guidance_scale,
                                 "guidance_scale")
        if draft and cond_kind != "none":  # the Draft takes the scale as an input: only the scales it learnt
            d = self.config.draft
            inputs.check_draft(s, inputs.ModelLimits(draft_guidance=(d.guidance_min, d.guidance_max)))
        num_variants = inputs.int_in_range(num_variants, "num_variants", 1, 1024)
        rows = [(i, v) for i in range(n_prompts) for v in range(num_variants)]
        base = [inputs.check_seed(x, num_variants, "seed") for x in _as_list(seed, n_prompts, "seed")]
        draw = inputs.int_in_range(draw, "draw", 0, 1000)
        redraws = self.config.side_redraws if side_redraws is None else \
            inputs.int_in_range(side_redraws, "side_redraws", 0, inputs.MAX_SIDE_REDRAWS)
        verb_redraws = self.default_verb_redraws(draft) if verb_redraws is None else \
            inputs.int_in_range(verb_redraws, "verb_redraws", 0, inputs.MAX_VERB_REDRAWS)
        _check_constraints(constraints, frames)
        return _Call(cond_kind, draft, prompts=[prompts[i] for i, _ in rows],
                     actions=[actions[i] for i, _ in rows] if actions is not None else None,
                     seconds=[secs[i] for i, _ in rows], seeds=[base[i] + v for i, v in rows],
                     lengths=torch.tensor([frames[i] for i, _ in rows], device=self.device), steps=steps, guidance=s,
                     teacher_steps=min(self.config.draft.teacher_steps, steps - 1) if draft else 0,
                     num_variants=num_variants, draw=draw, side_redraws=redraws if cond_kind == "text" else 0,
                     verb_redraws=verb_redraws if cond_kind == "text" else 0)

    def default_verb_redraws(self, draft: bool) -> int:
        """A call's verb redraws when it names none: a Draft's own (config draft.verb_redraws), else the model's."""
        own = self.config.draft.verb_redraws if draft and self.config.draft is not None else None
        return self.config.verb_redraws if own is None else own

    def _conditions(self, call: _Call) -> Conditions:
        """Stage 2: the sampling denoiser's condition and null tokens, and a Draft's teacher's own."""
        denoiser = self.draft_denoiser if call.draft else self.denoiser
        cond, null = self._condition(call.prompts, call.actions, call.cond_kind, denoiser, call.draft)
        if not call.teacher_steps:
            return Conditions(cond, null)
        return Conditions(cond, null, *self._condition(call.prompts, call.actions, call.cond_kind, self.draft_teacher,
                                                       call.draft))

    def _sampler(self, call: _Call, conditions: Conditions, generators: list) -> FinalSampler | DraftSampler:
        """Stage 4's sampler, its scheduler set to the call's steps (a Draft at its default number of steps on its
        own timesteps, config draft.timesteps); s = 1 or no condition: the condition alone, unguided."""
        guided = call.cond_kind != "none"
        if not call.draft:
            self.scheduler.set_timesteps(call.steps)
            scale = call.guidance if call.guidance != 1.0 and guided else None
            return FinalSampler(self.denoiser, self.scheduler, conditions, call.lengths, scale,
                                self._verb_guidance(call) if scale is not None else None)
        own = self.config.draft
        self.draft_scheduler.set_timesteps(call.steps, own.timesteps if call.steps == own.num_inference_steps else None)
        t_s = own.teacher_guidance if own.teacher_guidance is not None else call.guidance
        teacher_scale = t_s if t_s != 1.0 and guided else None
        verb = None
        if own.teacher_verb_guide and call.teacher_steps and teacher_scale is not None and self.verb_guide is not None:
            verb = self._verb_guidance(call, self.verb_guide.scale * teacher_scale / self.config.guidance_scale)
        return DraftSampler(self.draft_denoiser, self.draft_scheduler, conditions, call.lengths,
                            call.guidance if guided else 1.0, generators, self.draft_teacher, teacher_scale,
                            call.teacher_steps, verb)

    def _verb_guidance(self, call: _Call, scale: float | None = None) -> VerbGuidance | None:
        """The verb denoiser's term on the rows whose prompt names one of its labels, at ``scale`` (default: its
        own; None: no such row)."""
        guide = self.verb_guide
        if guide is None or not guide.scale or call.cond_kind != "text":
            return None
        rows, labels = guide.rows_and_labels(call.prompts, self.device)
        if not len(rows):
            return None
        cond = guide.denoiser.condition_tokens(len(rows), actions=labels)
        return VerbGuidance(guide.denoiser, rows, cond, guide.denoiser.null_tokens(len(rows)),
                            guide.scale if scale is None else scale)

    def _redraw(self, call: _Call, kwargs: dict, rows: list, draw: int) -> MLDOutput:
        """Rows ``rows`` of ``call`` made again from draw ``draw`` of their seeds, as they were first made but without
        redraws (the side and verb redraws' ``redo``)."""
        return self([call.prompts[r] for r in rows], [call.seconds[r] for r in rows],
                    seed=[call.seeds[r] for r in rows], draw=draw, side_redraws=0, verb_redraws=0,
                    num_inference_steps=call.steps,
                    guidance_scale=call.guidance, **kwargs)

    def _output(self, call: _Call, takes: Takes, constraints, timings: dict) -> MLDOutput:
        """Stage 6: the takes as an MLDOutput (joints made here unless a fix made them)."""
        joints = takes.joints
        if joints is None:
            joints = self.decoder.joints(takes.features, call.lengths.tolist())
        out = MLDOutput(takes.features, joints, call.lengths.cpu().numpy(), call.prompts, call.seeds, self.config.fps,
                        self.model_id, timings, draws=takes.draws, redrawn_for=takes.redrawn_for)
        if constraints:
            out.residuals = [constraints.residuals(joints[i, :n]) for i, n in enumerate(out.lengths)]
        return out

    def _ranked(self, out: MLDOutput, call: _Call, timings: dict) -> MLDOutput:
        """Badges per row; each prompt's variants best first (mld_core.eval.quality.rank_output)."""
        from mld_core.eval.quality import rank_output

        t0 = time.perf_counter()
        out = rank_output(out, self.quality_scorer(), call.num_variants, None if call.cond_kind == "text" else [])
        timings["rank_s"] = time.perf_counter() - t0
        return out

    def sequence(self, segments: Sequence[tuple[str, float]], *, seed: int = 0, overlap_s: float = 0.5,
                 **kwargs) -> MLDOutput:
        """One motion from ``[(prompt, seconds), ...]``: each segment continues the previous one (its first
        ``overlap_s`` seconds are constrained to the previous one's last pose, by refining the features only: the
        latent stays the segment prompt's sample, and only the change is kept smooth, so its own motion is not
        damped; the features cross-fade there); the root velocities join, so position and facing carry over and
        each segment moves as its prompt says. Segment k uses seed ``seed + k`` and is stepped and repaired as a
        free take of its own. Returns one row; ``timings["segments"]`` holds each segment's first frame, and
        ``seams`` each seam's largest joint jerk on the joined take against real motion's (``quality.seam_jerk``):
        that, not the Continuation's residual before the fade, is what the seam looks like."""
        from mld_core.take_fixes.constraints import Continuation

        t_start = time.perf_counter()
        segments, overlap = self._sequence_segments(segments, overlap_s)
        repair = kwargs.pop("repair", True)  # per segment, once they are joined (below)
        # joined segments are not drawn again (a side or a verb is asked of a segment, not of the take)
        kwargs["side_redraws"] = kwargs["verb_redraws"] = 0
        step = kwargs.pop("step", repair)  # each segment's sample, before it is joined
        first = self(segments[0][0], segments[0][1], seed=seed, repair=False, step=step, **kwargs)
        features = first.features[0, : int(first.lengths[0])]  # (T, F)
        starts = [0]
        for k, (prompt, seconds) in enumerate(segments[1:], start=1):
            tail = features_to_joints(features[-overlap:])  # the last frames, in their own frame
            # the pose only (no planted-feet term: that would hold the root back where the legs do not carry it)
            join = Constraints([Continuation(tail)], steps=0, planted_weight=0.0)
            out = self(prompt, seconds + overlap / self.config.fps, seed=seed + k, repair=False, step=step,
                       constraints=join, **kwargs)
            starts.append(len(features) - overlap)
            new = out.features[0, : int(out.lengths[0])]
            w = np.linspace(0.0, 1.0, overlap)[:, None]  # cross-fade the overlap: both are nearly the same frames
            seam = (1 - w) * features[-overlap:] + w * new[:overlap]
            features = np.concatenate([features[:-overlap], seam, new[overlap:]])  # (T, F)
        if repair:  # planted per segment (a walk backwards keeps its travel after a long run), then feet locked
            bounds = starts[1:] + [len(features)]  # over the whole take: a foot held across a seam stays held
            per_segment = replace(self.config.repair, lock_feet=False)
            features = np.concatenate([repair_rows(features[None, a:b], [b - a], per_segment)[0]
                                       for a, b in zip(starts, bounds)])
            if self.config.repair.lock_feet and features.shape[-1] == 263:
                spans = list(zip(starts, bounds))  # a shuffling segment is not held (lock_feet)
                features = lock_feet(features, self.config.repair, spans).astype(features.dtype)
        joints = self.joints_from_features(features[None], [len(features)])
        timings = {"segments": starts, "total_s": time.perf_counter() - t_start}
        seams = []
        for k, start in enumerate(starts[1:], start=1):
            jerk = seam_jerk(joints[0], start, overlap, self.config.fps)
            seams.append((k, jerk, jerk <= REAL_JERK_P95))
        return MLDOutput(features[None].astype(np.float32), joints, np.array([len(features)]),
                         [" | ".join(p for p, _ in segments)], [seed], self.config.fps, self.model_id, timings,
                         seams=[seams])

    def _sequence_segments(self, segments, overlap_s) -> tuple[list[tuple[str, float]], int]:
        """A sequence's ``[(prompt, seconds), ...]`` checked before any work (prompts text with words, each later
        segment's seconds with the overlap it also makes within the model's lengths) and the overlap in frames (at
        least one, at most the first segment's)."""
        if isinstance(segments, (str, bytes, Mapping)) or not isinstance(segments, Iterable):
            raise InputError("a sequence is a list of (prompt, seconds) segments, e.g. [('a person walks', 3.0)], "
                             f"got {type(segments).__name__}")
        segments = list(segments)
        if not segments:
            raise InputError("a sequence needs at least one (prompt, seconds) segment")
        fps = self.config.fps
        overlap_s = inputs.finite_number(overlap_s, "overlap_s")
        overlap = int(round(overlap_s * fps))
        if overlap < 1:
            raise InputError(f"overlap_s must be at least one frame ({1 / fps:g} s), got {overlap_s:g}")
        limits = inputs.ModelLimits(fps, self.config.min_frames, self.config.max_frames)
        checked = []
        for k, segment in enumerate(segments, start=1):
            at = f"sequence segment {k}"
            if isinstance(segment, (str, bytes)) or not isinstance(segment, Sequence) or len(segment) != 2:
                raise InputError(f"{at} must be a (prompt, seconds) pair, got {brief(segment)}")
            prompt, seconds = segment
            try:
                inputs.check_prompt(prompt)
            except InputError as exc:
                raise InputError(f"{at}: {exc}") from None
            extra = overlap / fps if k > 1 else 0.0  # a later segment also makes the previous one's last frames
            seconds = inputs.finite_number(seconds, f"{at}: seconds")
            what = f"{at}: length" + (f" (+ {extra:g} s overlap)" if extra else "")
            inputs.check_seconds(seconds + extra, limits, what)
            checked.append((prompt, seconds))
        if len(checked) > 1 and overlap > self.frames_for(checked[0][1]):
            raise InputError(f"overlap_s {overlap_s:g} is longer than sequence segment 1 ({checked[0][1]:g} s)")
        return checked, overlap

    @torch.inference_mode()
    def sample_prior(self, seconds: float = 4.0, num: int = 1, seed: int = 0) -> MLDOutput:
        """Unconditional generation by decoding z ~ N(0, I) from the VAE prior (no denoiser)."""
        frames = self.frames_for(float(seconds))
        seeds = [int(seed) + i for i in range(num)]
        n, d = self.config.vae.latent_tokens, self.config.vae.latent_dim
        mu = torch.stack([torch.randn(n, d, generator=torch.Generator().manual_seed(sd)) for sd in seeds])
        lengths = torch.full((num,), frames)
        z = (mu - self.config.latent_mean) * self.config.latent_scale
        features = self.latents_to_features(z.to(self.device), lengths.to(self.device))
        joints = self.joints_from_features(features, lengths.tolist())
        return MLDOutput(features, joints, lengths.numpy(), [""] * num, seeds, self.config.fps, self.model_id)

def _vae_copy(vae: MotionVAE, config, device: torch.device, dtype: torch.dtype) -> MotionVAE:
    """A copy of ``vae`` for decoding whose decoder's matrix products (and so its attention) run in ``dtype``; layer
    norms, the residual stream and the output stay float32 (a decoder wholly in bfloat16 rounds the features it
    outputs, and its takes measured 11% more jerk)."""
    copy = MotionVAE(config)
    copy.load_state_dict(vae.state_dict())
    copy = copy.eval().to(device)
    copy.decoder.pack_for_cpu_inference(dtype)
    return copy


def _verb_guide(model_dir: Path, config: ModelConfig, device: torch.device, dtype: torch.dtype) -> VerbGuide:
    """The folder's verb denoiser (config verb_guide), in the precision of the model's denoiser."""
    g = config.verb_guide
    denoiser = LatentDenoiser(g.denoiser)
    load_weights(model_dir / VERB_WEIGHTS, denoiser)
    denoiser = denoiser.eval().to(device, dtype)
    denoiser.transformer.pack_for_cpu_inference()  # no-op off CPU
    return VerbGuide(denoiser, list(g.actions), g.scale)


def _draft_text_encoder(model_dir: Path, config: ModelConfig, precision: str):
    """The Draft's own text encoder, or None where it shares Final's: the model's encoder with its distilled layers
    (config ``draft.text_layers``, draft_text.safetensors) and/or in bfloat16 (``precision`` "bf16"). Layers that
    cannot be read leave the Draft the model's full encoder, with a warning (the Draft is then slower, not wrong); a
    kind of encoder without a ``dtype`` option leaves it Final's."""
    from mld_core.models.text_encoder import TextEncoderError, load_text_encoder

    dtype = {"dtype": "bfloat16"} if precision == "bf16" else {}
    if config.draft.text_layers:
        layers = {"layer_file": str(model_dir / DRAFT_TEXT_WEIGHTS)}
        try:
            return load_text_encoder({**config.text_encoder, **dtype, **layers})
        except (TypeError, TextEncoderError) as exc:
            warnings.warn(f"the Draft's distilled text encoder is unavailable ({exc}): the Draft encodes prompts "
                          "with the model's full text encoder", stacklevel=3)
    if not dtype:
        return None
    try:
        return load_text_encoder({**config.text_encoder, **dtype})
    except TypeError:
        return None


def _denoiser_copy(denoiser: LatentDenoiser, config, device: torch.device, dtype: torch.dtype) -> LatentDenoiser:
    """A float32 copy of ``denoiser`` whose transformer layers' products run in ``dtype``: a Draft's teacher."""
    copy = LatentDenoiser(config)
    copy.load_state_dict({k: v.float() for k, v in denoiser.state_dict().items()})
    copy = copy.eval().to(device)
    copy.transformer.pack_for_cpu_inference(dtype)
    return copy
