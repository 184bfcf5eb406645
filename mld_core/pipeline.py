"""Text/action/unconditional motion generation with a trained MLD model folder.

    pipe = MLDPipeline.from_pretrained()            # the bundled default model
    out = pipe(["a person waves the right hand"], seconds=4, seed=0)
    out.joints  # (N, T, 22, 3) metres, Y up, facing +Z at frame 0

Paper symbols: z_T ~ N(0, I) the initial latent, eps_theta(z_t, t, c) the denoiser, s the guidance scale,
eps = eps(z_t, t, null) + s * (eps(z_t, t, c) - eps(z_t, t, null)), D the VAE decoder, x = D(z_0 / scale + mean).
"""

from __future__ import annotations

import time
import warnings
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from mld_core import content_anchor, inputs, side_contrast
from mld_core.coverage import INDEX_NAME, load_for_model, normalise, unavailable
from mld_core.inputs import InputError
from mld_core.checkpoint import (DEFAULT_MODEL_DIR, DRAFT_TEXT_WEIGHTS, CheckpointError, ModelConfig, load_config,
                                 load_weights)
from mld_core.models.denoiser import LatentDenoiser
from mld_core.constraints import bone_stretch, planted_feet, planted_foot_speed, root_speed
from mld_core.eval.quality import REAL_JERK_P95, seam_jerk
from mld_core.motion.features import FOOT_CONTACT, features_to_joints, mirror_text
from mld_core.motion.repair import RepairConfig, lock_feet, repair_features
from mld_core.models.transformer import native_bf16, packing_available
from mld_core.models.vae import MotionVAE
from mld_core.schedulers import DDIMScheduler, LCMScheduler
from mld_core.stepping import SteppingConfig, keep_cost, slide_cost, sliding_share, valid_frames


PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16}
DRAFT_PRECISIONS = ("auto", *PRECISIONS)


def draft_precision_for(choice: str, device: str | torch.device = "cpu") -> str:
    """The precision a Draft runs in: ``"auto"`` is bf16 on a CPU that computes bfloat16 natively (AVX512-BF16 or
    AMX: text encoder, denoiser and decoder each about 1.3-1.5x faster) and fp32 elsewhere."""
    if choice not in DRAFT_PRECISIONS:
        raise ValueError(f"draft_precision must be one of {', '.join(DRAFT_PRECISIONS)}, got {choice!r}")
    packs = torch.device(device).type == "cpu" and packing_available()  # bf16 products need oneDNN's packed ops
    if choice == "bf16" and not packs:
        warnings.warn("draft_precision bf16 needs a CPU with oneDNN: the Draft runs in fp32", stacklevel=3)
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
    draws: list | None = None  # per row, which z_T of its seed the take is (0: the first; side redraws: 1, 2, ...)
    seams: list | None = None  # per row of a sequence [(segment, largest joint jerk m/s^3 at its seam, within real)]

    def select(self, rows: Sequence[int]) -> "MLDOutput":
        """These rows, in this order (every per-row field follows them)."""
        rows = list(rows)

        def pick(values):
            return None if values is None else [values[i] for i in rows]

        return replace(self, features=self.features[rows], joints=self.joints[rows], lengths=self.lengths[rows],
                       prompts=pick(self.prompts), seeds=pick(self.seeds), badges=pick(self.badges),
                       residuals=pick(self.residuals), draws=pick(self.draws), seams=pick(self.seams))


def _as_list(value, n: int, name: str) -> list:
    if isinstance(value, (str, int, float, np.integer, np.floating)) or value is None:
        return [value] * n
    value = list(value)
    if len(value) != n:
        raise ValueError(f"{name} has {len(value)} entries for {n} prompts")
    return value


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
        self._text_cache: OrderedDict = OrderedDict()  # prompt -> its TextEmbedding (one row, its own tokens)
        self._draft_text_cache: OrderedDict = OrderedDict()  # the same for the Draft's text encoder
        self.coverage_index = None  # mld_core.coverage.CoverageIndex, from the model folder's coverage_index.npz
        self.content_anchor = None  # mld_core.content_anchor.ContentAnchor, from content_anchor.safetensors
        self._quality = None  # mld_core.eval.quality.QualityScorer, loaded on first use
        mean, std = config.mean_std
        self.mean, self.std = mean, std

    # -- loading ----------------------------------------------------------------------------------------------
    @classmethod
    def from_pretrained(cls, path: str | Path | None = None, device: str = "cpu", text_encoder=None,
                        precision: str = "fp32", draft_precision: str = "auto") -> "MLDPipeline":
        """Load a model folder (None: the bundled default). ``text_encoder`` overrides the one named in config.json.
        ``precision="bf16"`` runs the denoiser in bfloat16: faster on CPUs with native bfloat16 (AVX512-BF16, AMX),
        samples close to but not bit-equal to float32's. ``draft_precision`` is the Draft's (draft_precision_for)."""
        model_dir = Path(path) if path is not None else DEFAULT_MODEL_DIR
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

    # -- normalisation ------------------------------------------------------------------------------------------
    def normalize(self, features: np.ndarray) -> np.ndarray:
        return (features - self.mean) / self.std

    def denormalize(self, features: np.ndarray) -> np.ndarray:
        return features * self.std + self.mean

    @torch.inference_mode()
    def features_to_latents(self, features: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        """Denormalised feature clips [(T_i, F)] -> their VAE means in diffusion space (B, n, d) and lengths (B,):
        the inverse of ``latents_to_features`` (a reconstruction is one after the other)."""
        lengths = torch.tensor([len(f) for f in features])
        x = np.zeros((len(features), int(lengths.max()), self.config.vae.feature_dim), np.float32)  # (B, T, F)
        for i, f in enumerate(features):
            x[i, : len(f)] = self.normalize(f)
        mu, _ = self.vae.encode(torch.from_numpy(x).to(self.device), lengths.to(self.device))  # (B, n, d)
        return (mu.float() - self.config.latent_mean) * self.config.latent_scale, lengths

    @torch.no_grad()
    def latents_to_features(self, z: torch.Tensor, lengths: torch.Tensor, draft: bool = False) -> np.ndarray:
        """Diffusion-space latents (B, n, d) -> denormalised features (B, T, F), zero beyond each length; ``draft``
        decodes with the Draft's decoder (its precision)."""
        vae = self.draft_vae if draft else self.vae
        mu = z / self.config.latent_scale + self.config.latent_mean
        x = vae.decode(mu, lengths).float().cpu().numpy()
        feats = self.denormalize(x)
        for i, n in enumerate(lengths.tolist()):
            feats[i, n:] = 0.0
        return feats.astype(np.float32)

    def _decode_with_grad(self, latent: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """Normalised features (B, max length, F) of diffusion-space latents (B, n, d), differentiable (fp32)."""
        x = self.vae.decode(latent / self.config.latent_scale + self.config.latent_mean, lengths).float()
        return x[:, : int(lengths.max())]

    def step_feet(self, z: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """Sampled latents z_0 (B, n, d) refined so that the takes step instead of sliding (config ``stepping``;
        mld_core.stepping): Adam steps through the decoder on the feet's ground slide, keeping each take's root
        velocity, turning and stride. Takes that hardly slide are returned as sampled; each row is refined on its
        own (a batch equals single runs)."""
        cfg = self.config.stepping
        with torch.inference_mode(False), torch.enable_grad():
            mean, std = (torch.tensor(a, dtype=torch.float32, device=self.device) for a in (self.mean, self.std))
            z0 = z.detach().clone()

            def joints_of(latent, n):  # (b, n, d) -> differentiable joints (b, T, 22, 3)
                return features_to_joints(self._decode_with_grad(latent, n) * std + mean)

            sample = joints_of(z0, lengths).detach()
            valid = valid_frames(lengths, sample.shape[1])
            rows = torch.nonzero(sliding_share(sample, valid, cfg) >= cfg.min_slide_share).flatten()
            if not len(rows):
                return z
            n = lengths[rows].clone()
            sample, valid = sample[rows][:, : int(n.max())], valid[rows][:, : int(n.max())]
            start = z0[rows]
            latent = start.clone().requires_grad_(True)
            best, best_loss = start.clone(), torch.full((len(rows),), float("inf"), device=z.device)
            opt = torch.optim.Adam([latent], lr=cfg.lr)
            for k in range(cfg.steps + 1):  # the last pass only scores the last step
                with torch.set_grad_enabled(k < cfg.steps):
                    joints = joints_of(latent, n)
                    loss = (slide_cost(joints, valid, cfg) + keep_cost(joints, sample, valid, cfg)
                            + cfg.prior_weight * ((latent - start) ** 2).mean(dim=(1, 2)))  # (b,)
                better = loss.detach() < best_loss  # each row keeps its best latent: never worse than sampled
                best[better], best_loss[better] = latent.detach()[better], loss.detach()[better]
                if k < cfg.steps:
                    opt.zero_grad()
                    # rows independent: each row's gradient is its own loss's; only the latent's (the decoder's
                    # weights need none: that would cost about 30% more per step)
                    loss.sum().backward(inputs=[latent])
                    opt.step()
            out = z0.clone()
            out[rows] = best
        return out

    def keep_less_skating(self, sampled: torch.Tensor, stepped: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """Per free take, its stepped latent (B, n, d) unless the take, decoded and repaired, skates more than its
        sampled latent decoded and repaired; then the sampled one (config ``stepping.keep_if_less_skating``).
        Stepping lowers the slide of the unrepaired feet; some samples' feet the repairs plant better unstepped."""
        from mld_core.eval.quality import foot_skating_ratio

        rows = torch.nonzero((stepped != sampled).flatten(1).any(1)).flatten()
        if not len(rows):
            return stepped
        n = lengths[rows].tolist()

        def skating(z: torch.Tensor) -> np.ndarray:  # (b,) the repaired takes' foot skating ratios
            with torch.inference_mode():
                features = self.latents_to_features(z, lengths[rows])
            joints = self.joints_from_features(self.repair_rows(features, n), n)
            return np.array([foot_skating_ratio(j[:k], self.config.fps) for j, k in zip(joints, n)])

        worse = torch.as_tensor(skating(stepped[rows]) > skating(sampled[rows]))
        out = stepped.clone()
        out[rows[worse]] = sampled[rows[worse]]
        return out

    def meet_stepped_or_not(self, sampled: torch.Tensor, stepped: torch.Tensor, lengths: torch.Tensor,
                            constraints) -> np.ndarray:
        """Features (B, T, F) of constrained takes: the constraints met from each stepped latent (B, n, d) with the
        feet's slide in the cost, unless met from its sampled latent without it they meet as many constraints and
        skate less; then those (config ``stepping.keep_if_less_skating``). Both are met in one batch of 2B rows
        (rows are independent: a batch equals single runs); every take is met twice, even one whose latent stepping
        left as sampled."""
        B = len(sampled)
        with_slide = torch.arange(2 * B) < B
        both = self.meet_constraints(torch.cat([stepped, sampled]), torch.cat([lengths, lengths]), constraints,
                                     self.config.stepping, slide_rows=with_slide)  # (2B, T, F)
        return self.keep_less_skating_met(both[:B], both[B:], lengths, constraints)

    def keep_less_skating_met(self, features: np.ndarray, unstepped: np.ndarray, lengths: torch.Tensor,
                              constraints) -> np.ndarray:
        """Per constrained take, ``features`` (B, T, F: met from its stepped latent) unless ``unstepped`` (met from
        its sampled latent without the slide cost) meets as many constraints and skates less; then that."""
        n = int(lengths[0])
        out = features.copy()
        for i in range(len(features)):
            (met_s, skate_s), (met_u, skate_u) = (self._met_and_skating(f[:n], constraints)
                                                  for f in (features[i], unstepped[i]))
            if met_u >= met_s and skate_u < skate_s:
                out[i] = unstepped[i]
        return out

    def _met_and_skating(self, features: np.ndarray, constraints) -> tuple[int, float]:
        """A take's (number of constraints met, foot skating ratio); features (T, F)."""
        from mld_core.eval.quality import foot_skating_ratio

        joints = self.joints_from_features(features[None], [len(features)])[0]  # (T, 22, 3)
        met = sum(bool(ok) for _, _, ok in constraints.residuals(joints))
        return met, foot_skating_ratio(joints, self.config.fps)

    def meet_constraints(self, z: torch.Tensor, lengths: torch.Tensor, constraints,
                         stepping: SteppingConfig | None = None, slide_rows: torch.Tensor | None = None) -> np.ndarray:
        """Denormalised features (B, T, F) of the sampled latents z (B, n, d) refined to meet ``constraints``: first
        Adam steps on the latent through the decoder (the motion stays one the model makes; with ``stepping``, the
        feet's ground slide costs too, so that a stepped take keeps stepping: in the rows ``slide_rows`` (B,) bool
        marks, default all), then on the decoded features themselves with a smoothness term (what a latent of this
        size cannot reach exactly). All rows must have one length."""
        if len(set(lengths.tolist())) != 1:
            raise InputError("constraints need every motion of a call to have the same length")
        constraints.check_frames(int(lengths[0]))
        n = int(lengths[0])
        with torch.inference_mode(False), torch.enable_grad():
            mean, std = (torch.tensor(a, dtype=torch.float32, device=self.device) for a in (self.mean, self.std))
            lengths = lengths.clone()
            z0 = z.detach().clone()

            def decode(latent):  # (B, n, d) -> normalised features (B, T, F)
                return self._decode_with_grad(latent, lengths)

            slide_weight = constraints.latent_slide_weight()
            if stepping is not None:  # (B,) the slide's weight per row
                on = torch.ones(len(z0), dtype=torch.bool) if slide_rows is None else torch.as_tensor(slide_rows)
                row_slide = slide_weight * on.to(device=z0.device, dtype=torch.float32)
            z_opt = z0.clone().requires_grad_(True)
            opt = torch.optim.Adam([z_opt], lr=constraints.lr)
            for _ in range(constraints.steps):  # 5a. the latent
                opt.zero_grad()
                joints = features_to_joints(decode(z_opt) * std + mean)  # (B, T, 22, 3), differentiable
                loss = constraints.cost(joints) + constraints.prior_weight * ((z_opt - z0) ** 2).mean()
                if stepping is not None:
                    valid = valid_frames(lengths, joints.shape[1])
                    loss = loss + (row_slide * slide_cost(joints, valid, stepping)).mean()
                # x B: every term is a mean over the takes, so each take's gradient is its own cost's, whatever the
                # batch (a batch equals single runs); the latent's gradient only, not the decoder's weights'
                (loss * len(z0)).backward(inputs=[z_opt])
                opt.step()
            x0 = decode(z_opt).detach()
            contacts = planted_feet(x0 * std + mean, constraints.planted_toe_height_m)  # (B, T, 4) feet held still
            x = x0.clone().requires_grad_(True)
            opt = torch.optim.Adam([x], lr=constraints.feature_lr)
            change_only = constraints.change_only_rows(root_speed(x0 * std + mean))  # (B,) True: the change only
            origin = x0 * torch.as_tensor(change_only, dtype=x0.dtype, device=x0.device)[:, None, None]  # x0 or 0
            for _ in range(constraints.feature_steps):  # 5b. the features, kept smooth and near the decoded ones
                opt.zero_grad()
                moved = x - origin  # the change, or the features themselves
                accel = moved[:, 2:] - 2 * moved[:, 1:-1] + moved[:, :-2]
                joints = features_to_joints(x * std + mean)
                loss = (constraints.cost(joints) + constraints.smooth_weight * (accel ** 2).mean()
                        + constraints.prior_weight * ((x - x0) ** 2).mean()
                        + constraints.planted_weight * planted_foot_speed(joints, contacts)
                        + constraints.bone_weight * bone_stretch(joints))
                (loss * len(x0)).backward()  # each take's gradient its own cost's (above)
                opt.step()
            features = (x.detach() * std + mean).cpu().numpy()
        out = np.zeros((len(features), int(lengths.max()), features.shape[-1]), np.float32)
        out[:, :n] = features
        return out

    # -- conditions ---------------------------------------------------------------------------------------------
    def _condition(self, prompts: list, actions: list | None, kind: str, denoiser: LatentDenoiser,
                   draft: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(cond tokens, null tokens) of ``denoiser``, each (B, C, d); ``draft``: from the Draft's text encoder."""
        B = len(prompts)
        if kind == "text":
            text = self.text_embeddings(prompts, draft=draft)
            text = type(text)(**{k: v.to(self.device) for k, v in vars(text).items()})
            cond = denoiser.condition_tokens(B, text=text)
        elif kind == "action":
            ids = torch.tensor([self._action_id(a) for a in actions], device=self.device)
            cond = denoiser.condition_tokens(B, actions=ids)
        else:
            cond = denoiser.null_tokens(B)
        return cond, denoiser.null_tokens(B)

    TEXT_CACHE_SIZE = 256

    def text_embeddings(self, prompts: list, draft: bool = False):
        """The text encoder's embeddings of ``prompts`` (a TextEmbedding, one row per prompt); ``draft``: the Draft's
        encoder's. Each prompt is encoded once per encoder and kept (the last TEXT_CACHE_SIZE): re-generating a
        prompt with other seconds or seeds, as the live preview does, skips the text encoder."""
        from mld_core.models.text_encoder import TextEmbedding

        encoder = self.draft_text_encoder if draft else self.text_encoder
        cache = self._draft_text_cache if draft and encoder is not self.text_encoder else self._text_cache
        rows = {p: cache[p] for p in prompts if p in cache}
        new = [p for p in dict.fromkeys(prompts) if p not in rows]
        if new:
            emb = self._side_contrasted(new, self._anchored(new, encoder(new), encoder), encoder)
            for i, p in enumerate(new):
                n = int(emb.mask[i].sum())
                rows[p] = TextEmbedding(emb.pooled[i:i + 1], emb.tokens[i:i + 1, :n], emb.mask[i:i + 1, :n])
        for p in dict.fromkeys(prompts):
            cache[p] = rows[p]
            cache.move_to_end(p)
        while len(cache) > self.TEXT_CACHE_SIZE:
            cache.popitem(last=False)
        return TextEmbedding.cat([rows[p] for p in prompts])

    def _anchored(self, prompts: list, emb, encoder):
        """``emb`` (``encoder``'s embeddings of ``prompts``) with its pooled vectors moved by the content anchor
        (mld_core.content_anchor), when the model has one and config ``content_anchor.weight`` is above 0. The Draft's
        text encoder, distilled from the Final's, shares its vector space and so its anchor. Runs on the CPU."""
        settings = self.config.content_anchor
        if self.content_anchor is None or settings.weight == 0 or self.content_anchor.dim != emb.pooled.shape[-1]:
            return emb
        plain = encoder([normalise(p) or p for p in prompts]).pooled.float().cpu()
        plain = torch.nn.functional.normalize(plain, dim=-1)  # (B, D) the prompts without side and style words
        scores = None
        if settings.full_below is not None:  # from_pretrained made sure the folder has a coverage index
            scores = torch.from_numpy(self.coverage_index.nearest_scores(plain.numpy()))
        pooled = self.content_anchor.anchored(emb.pooled.cpu(), plain, settings.strengths(scores))
        return type(emb)(pooled.to(emb.pooled.device), emb.tokens, emb.mask)

    def _side_contrasted(self, prompts: list, emb, encoder):
        """``emb`` (``encoder``'s anchored embeddings of ``prompts``) with the pooled vector of each prompt that names
        a side pushed away from its mirrored wording's (mld_core.side_contrast), when config ``side_contrast`` is
        above 0."""
        weight = self.config.side_contrast
        if not weight:
            return emb
        mirrored = [mirror_text(p) for p in prompts]
        rows = [i for i, (p, m) in enumerate(zip(prompts, mirrored)) if p != m]
        if not rows:
            return emb
        others = [mirrored[i] for i in rows]
        mirrored_pooled = self._anchored(others, encoder(others), encoder).pooled  # (R, D)
        pooled = emb.pooled.clone()
        pooled[rows] = side_contrast.contrasted(emb.pooled[rows], mirrored_pooled, weight)
        return type(emb)(pooled, emb.tokens, emb.mask)

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
        """Per prompt a ``mld_core.coverage.Coverage``: score, verdict known / near / unknown, the 3 nearest training
        captions and the model's known contents (verdict "unavailable" for a folder without a coverage index)."""
        prompts = [prompts] if isinstance(prompts, str) else list(prompts)
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
                 step: bool | None = None, draw: int = 0, side_redraws: int | None = None) -> MLDOutput:
        """Generate ``num_variants`` motions per prompt; row i*num_variants + v uses seed ``seed + v``, or
        ``seed[i] + v`` when ``seed`` is a sequence (one per prompt). Any row equals the single run with its seed. (A
        Draft in bf16: to within bf16 rounding, up to about 2 cm.) ``unconditional`` samples with the null
        condition (the prompts then only label the rows). ``rank`` scores every row (``out.badges``) and orders
        each prompt's variants best first (mld_core.eval.quality.best_first). ``constraints`` (a
        ``mld_core.constraints.Constraints``: poses to hit, a root path, a loop) refines each sampled latent to
        meet them; ``out.residuals`` says how well each row did. ``repair`` applies the model's repairs (config
        ``repair``: one skeleton, planted feet; mld_core.motion.repair) to free takes. ``step`` (default: as
        ``repair``) refines each Final take's sampled latent until its feet step (config ``stepping``); the
        constraints are then met with the feet's slide in their cost. ``draft`` samples with
        the model's Draft denoiser (config ``draft``: a few consistency steps, the last of them guided steps of
        the model's own denoiser, and its own text encoder when it has one; about 10x faster). ``draw`` k starts
        each row from the (k+1)-th z_T of its seed. ``side_redraws`` (default: config ``side_redraws``): a free take
        whose prompt names a side (a turn, a drift, a wave, a raised hand: mld_core.eval.named_side) that it did
        not use is drawn again, at most this often (``out.draws`` says which draw each row is)."""
        if self.denoiser is None:
            raise CheckpointError("this model folder has only a VAE; sample with sample_prior() or train a denoiser")
        if draft and self.draft_denoiser is None:
            raise CheckpointError(f"Draft mode is unavailable: {self.draft_problem}" if self.draft_problem else
                                  f"the model {self.model_id} has no Draft denoiser (draft.safetensors); make one with "
                                  "`python -m mld_core train draft`")
        timings = {}
        t_start = time.perf_counter()
        cond_kind = "none" if unconditional else self.denoiser.config.cond
        # 1. Inputs: one row per (prompt, variant); each row has its own seed and generator.
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
        steps = inputs.int_in_range(steps, "num_inference_steps", 1, self.config.draft.original_steps if draft else 1000)
        s = inputs.finite_number(self.default_guidance(draft) if guidance_scale is None else guidance_scale,
                                 "guidance_scale")
        if draft and cond_kind != "none":  # the Draft takes the scale as an input: only the scales it learnt
            d = self.config.draft
            inputs.check_draft(s, inputs.ModelLimits(draft_guidance=(d.guidance_min, d.guidance_max)))
        num_variants = inputs.int_in_range(num_variants, "num_variants", 1, 1024)
        rows = [(i, v) for i in range(n_prompts) for v in range(num_variants)]
        row_prompts = [prompts[i] for i, _ in rows]
        row_actions = [actions[i] for i, _ in rows] if actions is not None else None
        base = [inputs.check_seed(x, num_variants, "seed") for x in _as_list(seed, n_prompts, "seed")]
        draw = inputs.int_in_range(draw, "draw", 0, 1000)
        redraws = self.config.side_redraws if side_redraws is None else \
            inputs.int_in_range(side_redraws, "side_redraws", 0, inputs.MAX_SIDE_REDRAWS)
        seeds = [base[i] + v for i, v in rows]
        lengths = torch.tensor([frames[i] for i, _ in rows], device=self.device)
        B = len(rows)

        # 2. Condition c and the null condition for classifier-free guidance.
        t0 = time.perf_counter()
        denoiser = self.draft_denoiser if draft else self.denoiser
        cond, null = self._condition(row_prompts, row_actions, cond_kind, denoiser, draft)
        teacher_steps = min(self.config.draft.teacher_steps, steps - 1) if draft else 0
        if teacher_steps:  # the teacher's own condition tokens for its steps
            t_cond, t_null = self._condition(row_prompts, row_actions, cond_kind, self.draft_teacher, draft)
        timings["condition_s"] = time.perf_counter() - t0

        # 3. z_T ~ N(0, I), drawn per row from its own generator (seeded per row) so a batch equals single runs;
        #    draw k skips the generator's first k draws.
        n, d = self.config.vae.latent_tokens, self.config.vae.latent_dim
        generators = [torch.Generator().manual_seed(sd) for sd in seeds]
        for g in generators:
            for _ in range(draw):
                torch.randn(n, d, generator=g)
        z = torch.stack([torch.randn(n, d, generator=g) for g in generators]).to(self.device)  # (B, n, d)

        # 4. Denoising. Final: DDIM, eps = eps_null + s * (eps_c - eps_null). Draft: consistency steps of the
        #    distilled denoiser, which takes s as an input (one pass per step), re-noised between steps; its last
        #    ``teacher_steps`` are guided DDIM steps of the denoiser it was distilled from, which finish the sample.
        t0 = time.perf_counter()
        if draft:  # the Draft's own timesteps (config draft.timesteps) at its default number of steps
            scheduler, own = self.draft_scheduler, self.config.draft
            scheduler.set_timesteps(steps, own.timesteps if steps == own.num_inference_steps else None)
        else:
            scheduler = self.scheduler
            scheduler.set_timesteps(steps)
        scale = s if s != 1.0 and cond_kind != "none" else None  # None: the condition alone, no guidance
        t_s = self.config.draft.teacher_guidance if draft and self.config.draft.teacher_guidance is not None else s
        teacher_scale = t_s if t_s != 1.0 and cond_kind != "none" else None
        total = len(scheduler.timesteps)
        for k, t in enumerate(scheduler.timesteps):
            if not draft:  # 4a. a DDIM step of the denoiser
                eps = _guided_eps(self.denoiser, z, t, cond, null, lengths, scale)
                z, _ = scheduler.step(eps, t, z)
            elif k < total - teacher_steps:  # 4b. a consistency step of the Draft denoiser
                dtype = denoiser.latent_in.weight.dtype
                scales = torch.full((B,), s if cond_kind != "none" else 1.0, device=self.device)
                t_batch = torch.full((B,), int(t), device=self.device)
                eps = denoiser(z.to(dtype), t_batch, cond.to(dtype), lengths, guidance=scales).float()
                noise = (torch.stack([torch.randn(n, d, generator=g) for g in generators]).to(self.device)
                         if k + 1 < total and scheduler.needs_noise else None)
                z, _ = scheduler.step(eps, t, z, noise)
            else:  # 4c. a guided DDIM step of its teacher (at config draft.teacher_guidance, when set)
                eps = _guided_eps(self.draft_teacher, z, t, t_cond, t_null, lengths, teacher_scale)
                z = scheduler.ddim_step(eps, t, scheduler.next_timestep(t), z)
            if callback is not None and callback(k + 1, total) is False:
                raise Cancelled(f"cancelled at step {k + 1} of {total}")
        timings["diffusion_s"] = time.perf_counter() - t0

        # 5. Decode x = D(z_0); with constraints, refine z_0 and then x until they are met (see meet_constraints).
        #    A Final take's z_0 is first refined so that its feet step instead of sliding (step_feet), free or
        #    constrained; a free one keeps the sample where that, repaired, skates less (keep_less_skating: also
        #    with repair=False and step=True, as a sequence's first segment is made, repaired once joined), a
        #    constrained one where the sample, met without stepping, skates less and meets as much (both met in one
        #    batch: meet_stepped_or_not).
        t0 = time.perf_counter()
        stepped = ((repair if step is None else step) and not draft and self.config.stepping.steps > 0
                   and self.config.vae.feature_dim == 263)
        if stepped:
            sampled, z = z, self.step_feet(z, lengths)
            if self.config.stepping.keep_if_less_skating and not constraints:
                z = self.keep_less_skating(sampled, z, lengths)
            timings["stepping_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()  # decode_s below: the decoding alone (AITS), or meeting the constraints
        if constraints and stepped and self.config.stepping.keep_if_less_skating:
            features = self.meet_stepped_or_not(sampled, z, lengths, constraints)
            timings["constraints_s"] = time.perf_counter() - t0
        elif constraints:
            features = self.meet_constraints(z, lengths, constraints, self.config.stepping if stepped else None)
            timings["constraints_s"] = time.perf_counter() - t0
        else:
            features = self.latents_to_features(z, lengths, draft)
        timings["decode_s"] = time.perf_counter() - t0

        # 5b. Repairs of free takes: one skeleton, planted feet (constraints already place the root and joints).
        if repair and not constraints:
            t0 = time.perf_counter()
            features = self.repair_rows(features, lengths.tolist())
            timings["repair_s"] = time.perf_counter() - t0

        # 6. Joints from the features.
        joints = self.joints_from_features(features, lengths.tolist())
        out = MLDOutput(features, joints, lengths.cpu().numpy(), row_prompts, seeds, self.config.fps,
                        self.model_id, timings, draws=[draw] * B)
        if constraints:
            out.residuals = [constraints.residuals(joints[i, :n]) for i, n in enumerate(out.lengths)]
        # 6b. Side redraws: a free take that misses the side its prompt names is drawn again (redraw_off_side).
        if redraws and cond_kind == "text" and not constraints:
            t0 = time.perf_counter()
            out = self.redraw_off_side(out, [secs[i] for i, _ in rows], redraws, num_inference_steps=steps,
                                       guidance_scale=s, callback=callback, repair=repair, draft=draft, step=step)
            timings["side_redraws_s"] = time.perf_counter() - t0
        if rank:  # 7. Badges per row; each prompt's variants best first.
            from mld_core.eval.quality import rank_output

            t0 = time.perf_counter()
            out = rank_output(out, self.quality_scorer(), num_variants, None if cond_kind == "text" else [])
            timings["rank_s"] = time.perf_counter() - t0
        timings["total_s"] = time.perf_counter() - t_start
        return out

    def redraw_off_side(self, out: MLDOutput, seconds: list, redraws: int, **kwargs) -> MLDOutput:
        """``out`` with each row whose prompt names a side that the take did not use (side badge "opposite" or
        "neither") replaced by the first of its seed's next ``redraws`` draws that uses it, else by the first that
        is at least not on the opposite side; ``out.draws`` records the draw kept. ``kwargs``: the first draw's
        sampling arguments (steps, guidance, repair, ...), so that each draw is made as it was."""
        from mld_core.eval.quality import side_badge

        def side(o: MLDOutput, r: int) -> str | None:
            return side_badge(o.prompts[r], o.joints[r, : int(o.lengths[r])], o.fps)

        verdicts = [side(out, r) for r in range(len(out.lengths))]
        first = out.draws[0] if out.draws else 0
        for k in range(first + 1, first + redraws + 1):
            rows = [r for r, v in enumerate(verdicts) if v in ("opposite", "neither")]
            if not rows:
                break
            again = self([out.prompts[r] for r in rows], [seconds[r] for r in rows],
                         seed=[out.seeds[r] for r in rows], draw=k, side_redraws=0, **kwargs)
            for j, r in enumerate(rows):
                v = side(again, j)
                if v == "named" or (v == "neither" and verdicts[r] == "opposite"):
                    n = again.features.shape[1]  # (B', T', F): T' <= this output's T
                    out.features[r] = 0.0
                    out.features[r, :n] = again.features[j]
                    out.joints[r, :n] = again.joints[j]
                    out.joints[r, n:] = again.joints[j, int(again.lengths[j]) - 1]  # (frames past the length repeat)
                    out.draws[r], verdicts[r] = k, v
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
        from mld_core.constraints import Constraints, Continuation

        t_start = time.perf_counter()
        segments = [(str(p), float(s)) for p, s in segments]
        if not segments:
            raise InputError("a sequence needs at least one (prompt, seconds) segment")
        overlap = int(round(overlap_s * self.config.fps))
        repair = kwargs.pop("repair", True)  # per segment, once they are joined (below)
        kwargs["side_redraws"] = 0  # joined segments are not drawn again (a side is asked of a segment, not the take)
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
            features = np.concatenate([self.repair_rows(features[None, a:b], [b - a], per_segment)[0]
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

    def repair_rows(self, features: np.ndarray, lengths: list, config: RepairConfig | None = None) -> np.ndarray:
        """Each row's first ``lengths[i]`` frames with the repairs of ``config`` (default: the model's) applied (a
        copy; 263-d features only)."""
        cfg = config or self.config.repair
        if features.shape[-1] != 263 or not (cfg.bone_lengths or cfg.plant_feet or cfg.lock_feet):
            return features
        out = features.copy()
        for i, n in enumerate(lengths):
            out[i, :n] = repair_features(features[i, :n], cfg)
        return out

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

    @staticmethod
    def joints_from_features(features: np.ndarray, lengths: list) -> np.ndarray:
        B, T = features.shape[:2]
        joints = np.zeros((B, T, 22, 3), np.float32)
        for i, n in enumerate(lengths):
            joints[i, :n] = features_to_joints(features[i, :n])
            joints[i, n:] = joints[i, n - 1]
        if not np.isfinite(joints).all():  # never hand a take of NaN/inf joints to a writer
            raise InputError("the model produced non-finite motion (NaN or inf): check the guidance scale and the "
                             "model's config.json (mean/std)")
        return joints


def _vae_copy(vae: MotionVAE, config, device: torch.device, dtype: torch.dtype) -> MotionVAE:
    """A copy of ``vae`` for decoding whose decoder's matrix products (and so its attention) run in ``dtype``; layer
    norms, the residual stream and the output stay float32 (a decoder wholly in bfloat16 rounds the features it
    outputs, and its takes measured 11% more jerk)."""
    copy = MotionVAE(config)
    copy.load_state_dict(vae.state_dict())
    copy = copy.eval().to(device)
    copy.decoder.pack_for_cpu_inference(dtype)
    return copy


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


def _guided_eps(denoiser: LatentDenoiser, z: torch.Tensor, t, cond: torch.Tensor, null: torch.Tensor,
                lengths: torch.Tensor, scale: float | None) -> torch.Tensor:
    """The denoiser's noise prediction at z_t (B, n, d) in float32: with ``scale``, classifier-free guidance
    eps_null + s * (eps_c - eps_null) from one pass over the 2B rows [null; cond]; without, the condition alone."""
    dtype = denoiser.latent_in.weight.dtype
    if scale is None:
        t_batch = torch.full((len(z),), int(t), device=z.device)
        return denoiser(z.to(dtype), t_batch, cond.to(dtype), lengths).float()
    t_batch = torch.full((2 * len(z),), int(t), device=z.device)
    eps = denoiser(torch.cat([z, z]).to(dtype), t_batch, torch.cat([null, cond]).to(dtype),
                   torch.cat([lengths, lengths])).float()
    eps_null, eps_cond = eps.chunk(2)  # each (B, n, d)
    return eps_null + scale * (eps_cond - eps_null)


def _denoiser_copy(denoiser: LatentDenoiser, config, device: torch.device, dtype: torch.dtype) -> LatentDenoiser:
    """A float32 copy of ``denoiser`` whose transformer layers' products run in ``dtype``: a Draft's teacher."""
    copy = LatentDenoiser(config)
    copy.load_state_dict({k: v.float() for k, v in denoiser.state_dict().items()})
    copy = copy.eval().to(device)
    copy.transformer.pack_for_cpu_inference(dtype)
    return copy
