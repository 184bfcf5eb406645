"""Draft mode: distil a model folder's denoiser into a latent consistency model (LCM; MotionLCM's recipe).

    python -m mld_core train draft --data DIR --teacher MODEL_DIR --out RUN [--minutes 60] [--resume]

The student starts as a copy of the teacher with one more input, the guidance scale w (a zero-initialised MLP added
to the timestep embedding), so guided sampling costs one pass instead of two. Each step draws a real latent z_0,
noises it to a timestep t of the 50-point DDIM grid, lets the teacher take one guided DDIM step to t - skip, and
pulls the student's clean estimate at (z_t, t) towards the EMA target's estimate at (z_{t-skip}, t - skip):

    L = huber(f_student(z_t, t, c, w) - f_target(DDIM_teacher(z_t -> z_{t-skip}; w), t - skip, c, w))

The run folder is a copy of the teacher's model folder plus ``draft.safetensors`` and a ``draft`` section in
config.json, so it samples with ``pipe(..., draft=True)``; ``--install MODEL_DIR`` copies those two into a folder.
"""

from __future__ import annotations

import copy
import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from mld_core import inputs
from mld_core.condition import content_anchor
from mld_core.data import terms
from mld_core.checkpoint import DRAFT_TEXT_WEIGHTS, DraftConfig, load_config, load_weights, save_json, save_weights
from mld_core.inputs import InputError
from mld_core.models.denoiser import LatentDenoiser
from mld_core.models.text_encoder import TextEmbedding
from mld_core.models.vae import MotionVAE
from mld_core.schedulers import LCMScheduler
from mld_core.training import distributed
from mld_core.training.common import (Budget, balanced_weights, checked_budget, checked_folder_setting,
                                     load_train_state, lr_factor, run_training_data, save_train_state, set_lr,
                                     setup_torch)
from mld_core.training.verb_fold import check_foldable, load_verb_fold
from mld_core.training.denoiser import (LATENT_CACHE, TEXT_CACHE, _cached, cached_caption_embeddings, embed_captions,
                                       encode_latents, prepare_run_with_caches, text_units)

DRAFT_WEIGHTS = "draft.safetensors"


@dataclass
class DraftTrainConfig:
    data: str = ""
    teacher: str = ""  # a model folder with a text-conditioned denoiser
    out: str = ""
    seed: int = 0
    threads: int | None = None
    steps: int | None = None
    minutes: float | None = None
    batch_size: int = 128  # the whole batch, over all processes (torchrun): each takes its share
    lr: float = 1e-4
    decay_start: float = 0.5
    ema_decay: float = 0.95  # the target network (LCM's target_unet)
    guidance_min: float = 3.0
    guidance_max: float = 5.0
    default_guidance: float | None = 3.0  # the Draft's default scale (None: the model's); 3 measured best (draft.md)
    original_steps: int = 50
    huber_c: float = 0.001
    draft_steps: int = 2  # the Draft's default number of steps, written into config.json
    teacher_steps: int = 1  # ... the last of them guided steps of the teacher (config draft.teacher_steps; draft.md)
    fresh_noise: float = 0.0  # share of new noise when re-noising between steps (config draft.fresh_noise)
    teacher_guidance: float | None = 1.5  # the teacher steps' guidance scale (config draft.teacher_guidance; draft.md)
    timesteps: list | None = None  # the Draft's timesteps at draft_steps (config draft.timesteps); None: with 2
    #   steps and a teacher step the teacher takes over at the grid point 60% up (601 of 1..981, measured best:
    #   draft.md), otherwise spread evenly
    crops_per_clip: int = 6
    balance_power: float = 0.7
    save_every: int = 250
    bf16: bool = False
    caches_from: str | None = None  # a denoiser run of the same VAE and data: reuse its latent and caption caches
    init: str | None = None  # a model folder whose Draft the student starts from (the teacher fine-tuned since)
    device: str = "cpu"  # cpu, cuda, mps or auto (where this sitting trains; any sitting may resume on another)
    fp32: bool = False  # on CUDA, no mixed precision (default there: bf16 autocast, or fp16 with a gradient scaler)
    fold_verb_guide: bool = False  # the teacher's steps carry its verb denoiser's term on the captions naming a
    #   label (mld_core.training.verb_fold, scaled with w), so the Draft learns the verb-guided model

    def __post_init__(self):
        """Every setting checked before any work (a bad one would train nothing, or a Draft that cannot load), and
        kept as the checked number: "2" from a JSON --config is stored as 2, so config.json stays loadable."""
        self.steps, self.minutes = checked_budget(self.steps, self.minutes)
        for name, lo, hi in (("batch_size", 1, 65536), ("original_steps", 1, 1000), ("crops_per_clip", 1, 1000),
                             ("save_every", 1, 10**9)):
            setattr(self, name, inputs.int_in_range(getattr(self, name), name, lo, hi))
        self.caches_from = checked_folder_setting(self.caches_from, "caches_from")
        self.init = checked_folder_setting(self.init, "init")
        self.fold_verb_guide = inputs.true_or_false(self.fold_verb_guide, "fold_verb_guide")
        self.draft_steps = inputs.int_in_range(self.draft_steps, "draft_steps", 1, self.original_steps)
        self.teacher_steps = inputs.int_in_range(self.teacher_steps, "teacher_steps", 0, self.original_steps - 1)
        for name, lo, hi in (("lr", 1e-12, 1.0), ("ema_decay", 0.0, 0.999999), ("huber_c", 1e-12, 1.0),
                             ("decay_start", 0.0, 1.0), ("balance_power", 0.0, 1.0), ("fresh_noise", 0.0, 1.0)):
            setattr(self, name, inputs.number_in_range(getattr(self, name), name, lo, hi))
        self.guidance_min = inputs.finite_number(self.guidance_min, "guidance_min")
        self.guidance_max = inputs.finite_number(self.guidance_max, "guidance_max")
        if not 0 < self.guidance_min <= self.guidance_max:
            raise InputError("guidance_min must be above 0 and at most guidance_max")
        if self.teacher_guidance is not None:
            self.teacher_guidance = inputs.number_in_range(self.teacher_guidance, "teacher_guidance", 1.0, 100.0)
        if self.default_guidance is not None:
            self.default_guidance = inputs.number_in_range(self.default_guidance, "default_guidance",
                                                           self.guidance_min, self.guidance_max)


TEACHER_TAKES_OVER = 0.6  # where on the grid a 2-step Draft's teacher step starts by default (docs/draft.md)


def draft_timesteps(cfg: DraftTrainConfig, scheduler: LCMScheduler) -> list | None:
    """The timesteps the Draft's config gets: ``cfg.timesteps`` checked against the grid; by default, for 2 steps
    with a teacher step, the largest grid point and the one TEACHER_TAKES_OVER up the grid; else None (even)."""
    if cfg.timesteps is not None:
        return scheduler.checked_timesteps(cfg.timesteps, cfg.draft_steps).tolist()
    if cfg.draft_steps == 2 and cfg.teacher_steps >= 1:
        grid = scheduler.grid.tolist()
        return [grid[-1], grid[min(int(TEACHER_TAKES_OVER * len(grid)), len(grid) - 2)]]
    return None


def _starting_draft(init: str, base) -> Path:
    """The Draft weights of model folder ``init``, checked to fit a Draft of the teacher ``base``."""
    init_cfg = load_config(Path(init))
    weights = Path(init) / DRAFT_WEIGHTS
    if init_cfg.draft is None or not weights.is_file():
        raise ValueError(f"init {init} has no Draft to start from")
    mine = {**init_cfg.draft.denoiser.to_dict(), "guidance_input": False}
    if mine != base.denoiser.to_dict():
        raise ValueError(f"init {init}: its Draft's denoiser differs from the teacher's (another architecture)")
    return weights


def huber(diff: torch.Tensor, c: float) -> torch.Tensor:
    """Pseudo-Huber loss per element: sqrt(d^2 + c^2) - c."""
    return (diff.float() ** 2 + c**2).sqrt() - c


class _DraftLoss(torch.nn.Module):
    """The student's consistency loss as a module's forward, so DistributedDataParallel can wrap it."""

    def __init__(self, student: LatentDenoiser, lcm: LCMScheduler, huber_c: float):
        super().__init__()
        self.student, self.lcm, self.huber_c = student, lcm, huber_c

    def forward(self, z_t, t, emb, lengths, w, goal):
        eps = self.student(z_t, t, self.student.condition_tokens(len(z_t), text=emb), lengths, w)
        return huber(self.lcm.denoised(eps.float(), t, z_t) - goal, self.huber_c).mean()


def train_draft(cfg: DraftTrainConfig, resume: bool = False) -> Path:
    from mld_core.data.dataset import load_split
    from mld_core.models.text_encoder import load_text_encoder

    out, teacher_dir = Path(cfg.out), Path(cfg.teacher)
    base = load_config(teacher_dir)
    if base.denoiser is None or base.denoiser.cond != "text":
        raise ValueError(f"--teacher {teacher_dir} has no text-conditioned denoiser to distil")
    if base.denoiser.verb_hints:
        raise ValueError(f"--teacher {teacher_dir} reads verb hints: a Draft is not distilled from such a model yet")
    timesteps = draft_timesteps(cfg, LCMScheduler(base.scheduler, cfg.original_steps))  # checked before any work
    if cfg.fold_verb_guide:
        check_foldable(teacher_dir, base, teacher_dir)
    start = _starting_draft(cfg.init, base) if cfg.init and not resume else None
    rt = distributed.runtime(cfg.device, cfg.bf16, cfg.fp32, (cfg.batch_size, "batch_size"))  # before any writing
    rt.on_main(lambda: prepare_run_with_caches(out, resume, cfg.caches_from))
    setup_torch(cfg.seed, cfg.threads)

    # 1. Real latents z_0 of the training split and caption embeddings (cached by rank 0; the teacher's VAE and
    #    normalisation).
    mean, std = base.mean_std
    units = text_units(load_split(cfg.data, "train"), base.fps)
    if not units:
        raise ValueError(f"{cfg.data}: the train split is empty")
    captions = sorted({c for u in units for c in u.captions})

    def make_caches():
        vae = MotionVAE(base.vae)
        load_weights(teacher_dir / "vae.safetensors", vae)
        _cached(out / LATENT_CACHE, lambda: encode_latents(vae.to(rt.device), units, mean, std, cfg.crops_per_clip,
                                                           base.min_frames, base.max_frames, cfg.seed))
        cached_caption_embeddings(out / TEXT_CACHE, captions, lambda: embed_captions(
            load_text_encoder(base.text_encoder).to(rt.device), captions, base.denoiser.max_text_tokens))

    rt.on_main(make_caches)
    lat = _cached(out / LATENT_CACHE, lambda: None)  # as rank 0 wrote them
    text = cached_caption_embeddings(out / TEXT_CACHE, captions, lambda: None)
    text = {k: v.to(rt.device) for k, v in text.items() if k != "captions_sha256"}
    z0_all = ((lat["mu"] - base.latent_mean) * base.latent_scale).to(rt.device)  # (N, n, d)
    lengths, unit_of = lat["lengths"].to(rt.device), lat["unit"]
    caption_index = {c: i for i, c in enumerate(captions)}
    unit_captions = [np.array([caption_index[c] for c in u.captions]) for u in units]

    # 2. Teacher (frozen), student (the teacher plus a guidance input), its EMA target.
    fold = load_verb_fold(teacher_dir, base, teacher_dir, captions, rt.device) if cfg.fold_verb_guide else None
    teacher = fold.teacher if fold is not None else LatentDenoiser(base.denoiser)  # the fold loads the teacher
    if fold is None:
        load_weights(teacher_dir / "denoiser.safetensors", teacher)
    teacher.eval().requires_grad_(False)
    draft = DraftConfig(denoiser=copy.deepcopy(base.denoiser), num_inference_steps=cfg.draft_steps,
                        original_steps=cfg.original_steps, guidance_min=cfg.guidance_min,
                        guidance_max=cfg.guidance_max, guidance_scale=cfg.default_guidance,
                        teacher_steps=cfg.teacher_steps, fresh_noise=cfg.fresh_noise,
                        teacher_guidance=cfg.teacher_guidance, timesteps=timesteps)
    draft.denoiser.guidance_input = True
    student = LatentDenoiser(draft.denoiser)
    student.load_state_dict(teacher.state_dict(), strict=False)  # all but the new guidance MLP
    if start is not None:
        load_weights(start, student)
    target = copy.deepcopy(student).eval().requires_grad_(False)  # goals without dropout
    teacher.to(rt.device), student.to(rt.device), target.to(rt.device)
    opt = torch.optim.AdamW(student.parameters(), lr=cfg.lr, weight_decay=0.0)
    step, _ = load_train_state(out, student, opt) if resume else (0, {})
    if resume and (out / DRAFT_WEIGHTS).is_file():
        load_weights(out / DRAFT_WEIGHTS, target)
    lcm = LCMScheduler(base.scheduler, cfg.original_steps, draft.timestep_scaling, draft.sigma_data).to(rt.device)
    weights = balanced_weights([units[u].label for u in unit_of.tolist()], cfg.balance_power)
    unit_list = unit_of.tolist()

    config = copy.deepcopy(base)
    config.draft = draft
    config.provenance = {**base.provenance, "draft_training": asdict(cfg)}
    config.training_data = run_training_data(cfg.data, [base, load_config(Path(cfg.init)) if start else None], out,
                                             resume)
    if not resume and rt.is_main:
        for name in ("vae.safetensors", "denoiser.safetensors", "coverage_index.npz", content_anchor.FILE_NAME,
                     "MODEL_CARD.md"):
            if (teacher_dir / name).is_file():
                shutil.copyfile(teacher_dir / name, out / name)
    if rt.is_main:
        save_json(out / "train_config.json", {**asdict(cfg), "stage": "draft", "run": rt.describe(cfg.batch_size,
                                                                                                   "latents")})

    def save():
        config.provenance["draft_steps"] = step
        save_weights(out / DRAFT_WEIGHTS, target)
        save_json(out / "config.json", config.to_dict())
        save_train_state(out, student, opt, step)

    # 3. Consistency distillation: every process draws the whole batch and distils on its rows of it.
    budget = rt.budget(Budget(cfg.steps, cfg.minutes))
    log = open(out / "log.jsonl", "a") if rt.is_main else None
    model = rt.wrap(_DraftLoss(student, lcm, cfg.huber_c), unused=True)  # the null condition
    student.train()
    running, B = None, cfg.batch_size
    n, d = base.vae.latent_tokens, base.vae.latent_dim
    while not budget.done(step):
        set_lr(opt, cfg.lr * lr_factor(budget.progress(step), cfg.decay_start))
        rng, gen = distributed.step_rng(cfg.seed, step)
        idx = rng.choice(len(z0_all), size=B, p=weights)
        cap = torch.tensor([int(rng.choice(unit_captions[unit_list[i]])) for i in idx])
        t = lcm.grid.cpu()[torch.randint(1, len(lcm.grid), (B,), generator=gen)]  # (B,) each with t - skip on the grid
        w = cfg.guidance_min + (cfg.guidance_max - cfg.guidance_min) * torch.rand(B, generator=gen)
        noise = torch.randn(B, n, d, generator=gen)  # (B, n, d)
        mine = rt.rows(B)
        rows = torch.from_numpy(idx[mine]).to(rt.device)
        cap, t, w, noise = (rt.to_device(v[mine]) for v in (cap, t, w, noise))
        b = len(mine)
        z0, L = z0_all[rows], lengths[rows]
        emb = TextEmbedding(pooled=text["pooled"][cap], tokens=text["tokens"][cap].float(), mask=text["mask"][cap])
        z_t = lcm.add_noise(z0, noise, t)
        with torch.no_grad(), rt.autocast():
            cond = teacher.condition_tokens(b, text=emb)
            eps_null, eps_cond = teacher(torch.cat([z_t, z_t]), torch.cat([t, t]),
                                         torch.cat([teacher.null_tokens(b), cond]), torch.cat([L, L])).float().chunk(2)
            eps = eps_null + w[:, None, None] * (eps_cond - eps_null)  # (B, n, d)
            if fold is not None:
                eps = fold.with_verb_term(eps, z_t, t, L, cap, w)
            z_prev = lcm.teacher_step(eps, t, z_t)
            t_prev = t - lcm.skip
            goal = lcm.denoised(target(z_prev, t_prev, target.condition_tokens(b, text=emb), L, w).float(),
                                t_prev, z_prev)
        with rt.autocast():
            loss = model(z_t, t, emb, L, w, goal)
        rt.step(loss * rt.share(B), opt, list(student.parameters()))
        with torch.no_grad():
            for pt, p in zip(target.parameters(), student.parameters()):
                pt.lerp_(p, 1 - cfg.ema_decay)
        step += 1
        running = loss.item() if running is None else 0.98 * running + 0.02 * loss.item()
        if (step % cfg.save_every == 0 or budget.done(step)) and rt.is_main:
            log.write(json.dumps({"step": step, "loss": running, "minutes": round(budget.minutes, 2)}) + "\n")
            log.flush()
            save()
    if rt.is_main:
        log.close()
        if not (out / "config.json").is_file():
            save()
    rt.barrier()
    return out


def install_draft(run: Path, model_dir: Path) -> None:
    """Copy a distilled Draft (draft.safetensors, fp16, and config.json's ``draft``) into a model folder whose VAE,
    denoiser and normalisation it was distilled from."""
    run_cfg, cfg = load_config(run), load_config(model_dir)
    if run_cfg.draft is None:
        raise ValueError(f"{run} has no Draft denoiser")
    if (run_cfg.latent_mean, run_cfg.latent_scale) != (cfg.latent_mean, cfg.latent_scale):
        raise ValueError(f"{run} was distilled from another model than {model_dir} (latent normalisation differs)")
    student = LatentDenoiser(run_cfg.draft.denoiser)
    load_weights(Path(run) / DRAFT_WEIGHTS, student)
    save_weights(Path(model_dir) / DRAFT_WEIGHTS, student, torch.float16)
    text_layers = cfg.draft.text_layers if cfg.draft is not None and (Path(model_dir) / DRAFT_TEXT_WEIGHTS).is_file() \
        else None  # the Draft's distilled text encoder (train draft-text) belongs to the text encoder: it stays
    cfg.draft = run_cfg.draft
    cfg.draft.text_layers = text_layers
    cfg.provenance["draft_training"] = run_cfg.provenance.get("draft_training", {})
    cfg.provenance["draft_steps"] = run_cfg.provenance.get("draft_steps", 0)
    terms.add_to(cfg, terms.of_model(run_cfg))
    save_json(Path(model_dir) / "config.json", cfg.to_dict())
