"""Stage 1: train the motion VAE on a HumanML3D-format folder.

    python -m mld_core train vae --data DIR --out RUN [--minutes 60] [--resume]

Each batch draws one crop length L (uniform in [min_frames, max_frames]) and clips at least L long, sampled with
content-balanced weights, so no compute goes to padding. Validation: root-relative MPJPE (mm) on the val split.
``frames_per_batch`` is the whole batch's, split between torchrun's processes (mld_core.training.distributed); the
clips' features sit on the training device, where each batch is cut from them.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from mld_core import inputs
from mld_core.checkpoint import (ModelConfig, load_config, load_weights, recorded_path, save_json, save_weights,
                                 skeleton_info)
from mld_core.models.vae import MotionVAE, VAEConfig, grow_latent
from mld_core.motion import skeleton as sk
from mld_core.motion.features import FOOT_CONTACT, ROOT_ROT_VEL, ROOT_Y, features_to_joints
from mld_core.training import distributed
from mld_core.training.common import (Budget, boosted_weights, check_resumed_modules, checked_budget,
                                     checked_label_boost, checked_module_names, load_train_state, lr_factor,
                                     run_training_data, save_train_state, set_lr, setup_torch, trainable_parameters,
                                     warmup_factor)

ROOT_CHANNELS = slice(ROOT_ROT_VEL.start, ROOT_Y.stop)  # yaw velocity, xz velocity (facing frame), root height
HORIZONTAL = [0, 2]  # x and z of a joint position (y is up)
GROWTH_NOISE = 0.003  # std of the noise on a grown latent's copied tokens (a trained token's entries: ~0.03)


@dataclass
class VAETrainConfig:
    data: str = ""
    out: str = ""
    seed: int = 0
    threads: int | None = None
    steps: int | None = None
    minutes: float | None = None
    frames_per_batch: int = 2048  # the whole batch's frames, over all processes (torchrun): each takes its share
    lr: float = 3e-4
    min_frames: int = 40
    max_frames: int = 196
    balance_power: float = 0.5
    # {label: factor}: the sampling weight of the train clips with that action label, times factor, on top of the
    # balance (e.g. {"kick": 6, "throw": 6}: more of the rare fast-limb clips in every batch)
    label_boost: dict | None = None
    decay_start: float = 0.5  # cosine learning-rate decay over the second half of the budget (--steps/--minutes)
    warmup_steps: int = 0  # the rate ramped up linearly over the run's first steps (a fresh optimiser on --init weights)
    val_every: int = 250
    val_clips: int = 200
    bf16: bool = False  # bfloat16 autocast for forward/backward (fp32 weights and optimiser); ~2x on AVX512-BF16 CPUs
    init: str | None = None  # a model folder to continue from (fine-tuning): its VAE's config and weights
    # the KL term's weight; None keeps the VAE's own (``vae.kl_weight``, or the --init model's). A lower weight lets the
    # latent carry more (fast limb swings); a fine-tune that lowers it changes the latents a denoiser learned
    kl_weight: float | None = None
    # the scale of the posterior draw z = mu + latent_noise * sigma * eps during training: 1 is the VAE's own sampling;
    # below 1 the decoder sees mu more sharply and learns to use more of the latent (0: a plain autoencoder on mu)
    latent_noise: float = 1.0
    # with --init: grow the init VAE's latent to this many tokens (models.vae.grow_latent: the new tokens start as
    # noisy copies of its own); the grown latent needs a denoiser of its own shape
    grow_latent_tokens: int | None = None
    # geometric terms (MDM, Tevet et al. 2023) on the decoded joints, metres; 0 turns a term off
    joint_weight: float = 0.0  # MSE of the global joints (includes the integrated root trajectory)
    velocity_weight: float = 0.0  # MSE of the joints' frame-to-frame velocity
    contact_weight: float = 0.0  # squared horizontal velocity of foot joints where the real clip says contact
    bone_weight: float = 0.0  # squared error of every bone's length against the real clip's
    # weight of the root channels (yaw velocity, xz velocity, height) in the feature MSE; their integral is the
    # take's global trajectory, so 1 (one channel among 263) lets the latent drop most of the turning
    root_weight: float = 1.0
    # share of crops that start at their clip's first frame: the only frame whose yaw channel holds the turn from the
    # clip's canonical facing to its smoothed facing (a spike of ~5 degrees that random crops almost never show)
    clip_start_share: float = 0.0
    select_by: str = "mpjpe"  # the checkpoint kept as best: lowest val "mpjpe" (root-relative) or "mpjpe_sum" (+ global)
    # the VAE's top-level modules to train; None: all. The decoder side alone (latent_positions, decoder, head) keeps
    # the encoder and so every latent a denoiser learned: the fine-tuned decoder pairs with that denoiser unchanged
    train_modules: list | None = None
    device: str = "cpu"  # cpu, cuda, mps or auto (where this sitting trains; any sitting may resume on another)
    fp32: bool = False  # on CUDA, no mixed precision (default there: bf16 autocast, or fp16 with a gradient scaler)
    vae: VAEConfig = field(default_factory=VAEConfig)

    def __post_init__(self):
        self.steps, self.minutes = checked_budget(self.steps, self.minutes)
        self.warmup_steps = inputs.int_in_range(self.warmup_steps, "warmup_steps", 0, 1_000_000)
        if isinstance(self.vae, dict):
            self.vae = VAEConfig(**self.vae)
        if self.select_by not in ("mpjpe", "mpjpe_sum"):
            raise ValueError(f"select_by must be 'mpjpe' or 'mpjpe_sum', got {self.select_by!r}")
        self.clip_start_share = inputs.number_in_range(self.clip_start_share, "clip_start_share", 0.0, 1.0)
        self.root_weight = inputs.number_in_range(self.root_weight, "root_weight", 1e-6, 1e6)
        if self.kl_weight is not None:
            self.kl_weight = inputs.number_in_range(self.kl_weight, "kl_weight", 0.0, 1.0)
        self.latent_noise = inputs.number_in_range(self.latent_noise, "latent_noise", 0.0, 1.0)
        if self.grow_latent_tokens is not None:
            self.grow_latent_tokens = inputs.int_in_range(self.grow_latent_tokens, "grow_latent_tokens", 1, 64)
        self.train_modules = checked_module_names(self.train_modules)
        self.label_boost = checked_label_boost(self.label_boost)


def feature_weights(feature_dim: int, root_weight: float) -> torch.Tensor | None:
    """(F,) weights of the feature MSE: ``root_weight`` on the root channels of 263-d features, 1 elsewhere."""
    if root_weight == 1.0:
        return None
    if feature_dim != sk.FEATURE_DIM:
        raise ValueError(f"root_weight needs {sk.FEATURE_DIM}-d features (root channels first), got {feature_dim}")
    weights = torch.ones(feature_dim)
    weights[ROOT_CHANNELS] = root_weight
    return weights


class GeometricLoss:
    """The geometric training terms on decoded joints: each weighted term is added to the VAE's feature loss."""

    def __init__(self, cfg: VAETrainConfig, mean: np.ndarray, std: np.ndarray):
        self.weights = {"joints": cfg.joint_weight, "velocity": cfg.velocity_weight, "contact": cfg.contact_weight,
                        "bones": cfg.bone_weight}
        self.mean, self.std = torch.from_numpy(mean).float(), torch.from_numpy(std).float()

    def __bool__(self) -> bool:
        return any(w > 0 for w in self.weights.values())

    def __call__(self, recon: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """recon, x: (B, L, F) normalised features of equal-length crops."""
        self.mean, self.std = self.mean.to(x.device), self.std.to(x.device)
        pred = features_to_joints(recon.float() * self.std + self.mean)  # (B, L, 22, 3)
        real = features_to_joints(x.float() * self.std + self.mean)
        parents = list(sk.PARENTS[1:])
        terms = {"joints": ((pred - real) ** 2).sum(-1).mean()}
        vel_pred, vel_real = pred[:, 1:] - pred[:, :-1], real[:, 1:] - real[:, :-1]  # (B, L-1, 22, 3)
        terms["velocity"] = ((vel_pred - vel_real) ** 2).sum(-1).mean()
        feet = list(sk.FOOT_LEFT) + list(sk.FOOT_RIGHT)
        contact = ((x.float() * self.std + self.mean)[:, :-1, FOOT_CONTACT] > 0.5).float()  # (B, L-1, 4)
        slide = vel_pred[:, :, feet][..., HORIZONTAL]  # (B, L-1, 4, 2): a planted foot may still lift, not slide
        terms["contact"] = ((slide ** 2).sum(-1) * contact).mean()
        bone_pred = (pred[:, :, 1:] - pred[:, :, parents]).norm(dim=-1)  # (B, L, 21)
        bone_real = (real[:, :, 1:] - real[:, :, parents]).norm(dim=-1)
        terms["bones"] = ((bone_pred - bone_real) ** 2).mean()
        total = sum(self.weights[k] * v for k, v in terms.items() if self.weights[k] > 0)
        return total, {f"geo_{k}": v.item() for k, v in terms.items()}


class CropSampler:
    """Batches of equal-length random crops: (B, L, F) normalised features, cut from one bank of every clip's frames
    (on the training device where it fits, else in pinned CPU memory)."""

    def __init__(self, clips, mean, std, min_frames, max_frames, frames_per_batch, balance_power,
                 clip_start_share: float = 0.0, device: torch.device | str = "cpu", label_boost: dict | None = None):
        feats = [((c.features - mean) / std).astype(np.float32) for c in clips]
        self.lengths = np.array([len(f) for f in feats])
        self.offsets = np.concatenate([[0], np.cumsum(self.lengths)[:-1]])
        labels = [c.action or "?" for c in clips]
        self.weights = boosted_weights(labels, balance_power, label_boost)
        self.min_frames = min(min_frames, int(self.lengths.max()))
        self.max_frames = min(max_frames, int(self.lengths.max()))
        self.frames_per_batch = frames_per_batch
        self.clip_start_share = clip_start_share
        self.bank = _bank(torch.from_numpy(np.concatenate(feats)), torch.device(device))  # (frames, F)

    def draw(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, int]:
        """One whole batch: (clip of each row, its crop's first frame, the crop length L)."""
        L = int(rng.integers(self.min_frames, self.max_frames + 1))
        ok = self.lengths >= L
        w = self.weights * ok
        B = max(4, self.frames_per_batch // L)
        idx = rng.choice(len(self.lengths), size=B, p=w / w.sum())
        starts = np.array([int(rng.integers(0, self.lengths[i] - L + 1)) for i in idx])
        if self.clip_start_share > 0:
            starts = np.where(rng.random(B) < self.clip_start_share, 0, starts)
        return idx, starts, L

    def crops(self, idx: np.ndarray, starts: np.ndarray, L: int, device: torch.device) -> torch.Tensor:
        """The crops (B, L, F) on ``device``."""
        first = torch.from_numpy(self.offsets[idx] + starts)  # (B,)
        frames = first[:, None] + torch.arange(L)  # (B, L) rows of the bank
        x = self.bank[frames.to(self.bank.device)]
        return x if x.device == device else x.to(device, non_blocking=True)

    def sample(self, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        idx, starts, L = self.draw(rng)
        return self.crops(idx, starts, L, self.bank.device), torch.full((len(idx),), L)


def _bank(frames: torch.Tensor, device: torch.device) -> torch.Tensor:
    """The frames on ``device`` when they take at most half of its free memory, else (CUDA) pinned CPU memory."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        nbytes = frames.numel() * frames.element_size()
        return frames.to(device) if nbytes <= free // 2 else frames.pin_memory()
    return frames.to(device)


class _VAELoss(torch.nn.Module):
    """The VAE's loss as a module's forward, so DistributedDataParallel can wrap it."""

    def __init__(self, vae: MotionVAE):
        super().__init__()
        self.vae = vae

    def forward(self, x, lengths, weights, noise):
        return self.vae.loss(x, lengths, return_recon=True, feature_weights=weights, noise=noise)


@torch.no_grad()
def validate_mpjpe(vae: MotionVAE, clips, mean, std, max_frames: int, batch: int = 32) -> tuple[float, float]:
    """Root-relative and global MPJPE in mm of encode(mu) -> decode on the first max_frames of each clip."""
    vae.eval()
    device = next(vae.parameters()).device
    errors, global_errors = [], []
    items = [((c.features[:max_frames] - mean) / std).astype(np.float32) for c in clips]
    order = np.argsort([len(x) for x in items])
    for k in range(0, len(order), batch):
        group = [items[i] for i in order[k:k + batch]]
        lengths = torch.tensor([len(g) for g in group])
        T = int(lengths.max())
        x = torch.zeros(len(group), T, group[0].shape[-1])
        for i, g in enumerate(group):
            x[i, : len(g)] = torch.from_numpy(g)
        mu, _ = vae.encode(x.to(device), lengths.to(device))
        recon = vae.decode(mu, lengths.to(device), max_len=T).float().cpu()
        mean_t, std_t = torch.from_numpy(mean), torch.from_numpy(std)
        for i, n in enumerate(lengths.tolist()):
            j_true = features_to_joints(x[i, :n] * std_t + mean_t)
            j_pred = features_to_joints(recon[i, :n] * std_t + mean_t)
            global_errors.append(float((j_true - j_pred).norm(dim=-1).mean()) * 1000.0)
            j_true = j_true - j_true[:, :1]
            j_pred = j_pred - j_pred[:, :1]
            errors.append(float((j_true - j_pred).norm(dim=-1).mean()) * 1000.0)
    vae.train()
    return float(np.mean(errors)), float(np.mean(global_errors))


def selection_metric(record: dict, select_by: str, step: int) -> float:
    """The number the best checkpoint minimises: val root-relative MPJPE, or its sum with the global one; without
    validation the latest step."""
    if "val_mpjpe_mm" not in record:
        return -step
    if select_by == "mpjpe_sum":
        return record["val_mpjpe_mm"] + record["val_global_mpjpe_mm"]
    return record["val_mpjpe_mm"]


def sittings_before(init: ModelConfig | None) -> list[dict]:
    """The VAE training a fine-tune starts from, oldest first: the --init folder's own lineage, then that folder's
    last sitting (its model id, steps and settings); [] for a VAE from nothing."""
    if init is None:
        return []
    prov = init.provenance
    own = {"model_id": init.model_id, "steps": prov.get("vae_steps"), "training": prov.get("vae_training")}
    return [*prov.get("vae_lineage", []), own]


def model_config_for(cfg: VAETrainConfig, mean, std, actions: list, model_id: str,
                     keep_from: ModelConfig | None = None, lineage: list | None = None,
                     training_data: list | None = None) -> ModelConfig:
    """The run's model config. A fine-tuned VAE keeps the decoding settings of ``keep_from`` (the model folder it
    started from), the repairs and the stepping, which act on its output: a fine-tune of the bundled model steps.
    ``lineage`` (``sittings_before``) records the training the run started from, so a VAE carried from one machine
    or sitting to the next still says what it has had; ``training_data`` (``run_training_data``) whose terms it
    carries."""
    settings = {k: v for k, v in asdict(cfg).items() if k != "vae"}
    provenance = {"vae_training": {**settings, "init": recorded_path(cfg.init)}}
    if lineage:
        provenance["vae_lineage"] = lineage
    config = ModelConfig(model_id=model_id, vae=cfg.vae, min_frames=cfg.min_frames, max_frames=cfg.vae.max_frames,
                         mean=np.asarray(mean).tolist(), std=np.asarray(std).tolist(), actions=actions,
                         skeleton=skeleton_info() if cfg.vae.feature_dim == 263 else {}, provenance=provenance,
                         training_data=training_data)
    if keep_from is not None:
        config.repair, config.stepping = keep_from.repair, keep_from.stepping
    return config


def prepare_run_dir(out: Path, resume: bool) -> None:
    if resume:
        if not (out / "train_state.pt").is_file():
            raise FileNotFoundError(f"--resume: {out} has no train_state.pt to resume from")
        return
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} exists and is not empty: pass --resume to continue it, or choose another --out")
    out.mkdir(parents=True, exist_ok=True)


def train_vae(cfg: VAETrainConfig, resume: bool = False) -> Path:
    from mld_core.data.dataset import load_mean_std, load_split

    out = Path(cfg.out)
    rt = distributed.runtime(cfg.device, cfg.bf16, cfg.fp32,  # checked before anything is written
                             (max(4, cfg.frames_per_batch // cfg.max_frames),
                              "a batch of the longest crops (frames_per_batch // max_frames clips, at least 4)"))
    rt.on_main(lambda: prepare_run_dir(out, resume))
    setup_torch(cfg.seed, cfg.threads)
    mean, std = load_mean_std(cfg.data)
    mean, std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
    init = load_config(Path(cfg.init)) if cfg.init else None  # fine-tuning: the model folder's config,
    if init is not None and not resume:  # its architecture, then its weights (below)
        cfg.vae = init.vae
        if cfg.vae.feature_dim != int(mean.shape[0]):
            raise ValueError(f"--init {cfg.init} works on {cfg.vae.feature_dim}-d features, {cfg.data} has "
                             f"{int(mean.shape[0])}")
    if cfg.grow_latent_tokens is not None and init is None:
        raise ValueError("grow_latent_tokens grows the latent of the --init model; give --init MODEL")
    if resume and (out / "train_config.json").is_file():  # a resumed run keeps the architecture it started with
        cfg.vae = VAEConfig(**json.loads((out / "train_config.json").read_text())["vae"])
    elif cfg.kl_weight is not None:  # a resumed run keeps the weight its first sitting trained with
        cfg.vae.kl_weight = cfg.kl_weight
    cfg.vae.feature_dim = int(mean.shape[0])
    trainable_parameters(MotionVAE(cfg.vae), cfg.train_modules, "VAE")  # names checked before the slow steps
    if resume:
        check_resumed_modules(out, cfg.train_modules)
    # the repairs and stepping the run's model keeps: its first sitting's when resumed, else the fine-tuned folder's
    keep_from = load_config(out) if resume and (out / "config.json").is_file() else init
    data_terms = run_training_data(cfg.data, [init], out, resume)
    train = load_split(cfg.data, "train", captioned=False)  # uncaptioned motion teaches the autoencoder too
    val = load_split(cfg.data, "val", captioned=False)
    if not train:
        raise ValueError(f"{cfg.data}: the train split is empty")
    rng = np.random.default_rng(cfg.seed)
    val = [val[i] for i in sorted(rng.choice(len(val), size=min(cfg.val_clips, len(val)), replace=False))] if val else []
    vae = MotionVAE(cfg.vae)
    if init is not None and not resume:
        load_weights(Path(cfg.init) / "vae.safetensors", vae)
        if cfg.grow_latent_tokens is not None:
            vae = grow_latent(vae, cfg.grow_latent_tokens, noise=GROWTH_NOISE, seed=cfg.seed)
            cfg.vae = vae.config
    trained = trainable_parameters(vae, cfg.train_modules, "VAE")
    vae.to(rt.device)
    opt = torch.optim.AdamW(trained, lr=cfg.lr, weight_decay=0.0)
    step, extra = (load_train_state(out, vae, opt) if resume else (0, {}))
    # kept in the train state; a state saved without one takes the --init given on resuming
    lineage = extra["vae_lineage"] if resume and "vae_lineage" in extra else sittings_before(init)
    geometric = GeometricLoss(cfg, mean, std)
    weights = feature_weights(cfg.vae.feature_dim, cfg.root_weight)
    weights = weights.to(rt.device) if weights is not None else None
    sampler = CropSampler(train, mean, std, cfg.min_frames, cfg.max_frames, cfg.frames_per_batch,
                          cfg.balance_power, cfg.clip_start_share, rt.device, cfg.label_boost)
    # the best so far, measured the way this sitting selects (a sitting that selects otherwise starts afresh)
    best = extra.get("best_mpjpe_mm", float("inf")) if extra.get("select_by", "mpjpe") == cfg.select_by else float("inf")
    actions = sorted({c.action for c in train if c.action})
    if rt.is_main:
        save_json(out / "train_config.json", {**asdict(cfg), "stage": "vae",
                                              "run": rt.describe(cfg.frames_per_batch, "frames")})
    budget = rt.budget(Budget(cfg.steps, cfg.minutes))
    log = open(out / "log.jsonl", "a") if rt.is_main else None
    bar = tqdm(total=cfg.steps, initial=step, desc="vae", unit="step", dynamic_ncols=True, disable=not rt.is_main)
    model = rt.wrap(_VAELoss(vae))
    vae.train()
    frames_seen, t0 = 0, time.monotonic()
    while not budget.done(step):
        rng, gen = distributed.step_rng(cfg.seed, step)
        idx, starts, L = sampler.draw(rng)  # the whole batch, the same in every process
        noise = torch.randn(len(idx), cfg.vae.latent_tokens, cfg.vae.latent_dim, generator=gen)  # (B, n, d)
        noise = noise * cfg.latent_noise
        mine = rt.rows(len(idx))  # this process's rows
        x = sampler.crops(idx[mine], starts[mine], L, rt.device)  # (b, L, F)
        lengths = torch.full((len(mine),), L, device=rt.device)
        rate = lr_factor(budget.progress(step), cfg.decay_start) * warmup_factor(step, cfg.warmup_steps)
        set_lr(opt, cfg.lr * rate)
        with rt.autocast():
            loss, parts, recon = model(x, lengths, weights, rt.to_device(noise[mine]))
        if geometric:
            extra_loss, extra_parts = geometric(recon, x)
            loss, parts = loss + extra_loss, {**parts, **extra_parts}
        rt.step(loss * rt.share(len(idx)), opt, trained)
        step += 1
        frames_seen += x.shape[0] * x.shape[1] * rt.size
        bar.update(1)
        bar.set_postfix(loss=f"{loss.item():.4f}", kl=f"{parts['kl']:.1f}", fps=f"{frames_seen / (time.monotonic() - t0):.0f}")
        last = budget.done(step)
        if (step % cfg.val_every == 0 or last) and rt.is_main:
            record = {"step": step, "loss": loss.item(), **parts, "lr": opt.param_groups[0]["lr"],
                      "minutes": round(budget.minutes, 2), "seconds": round(budget.minutes * 60, 3)}
            if val:
                record["val_mpjpe_mm"], record["val_global_mpjpe_mm"] = validate_mpjpe(vae, val, mean, std,
                                                                                       cfg.vae.max_frames)
                bar.write(f"step {step}: val MPJPE {record['val_mpjpe_mm']:.1f} mm root-relative, "
                          f"{record['val_global_mpjpe_mm']:.1f} mm global")
            log.write(json.dumps(record) + "\n")
            log.flush()
            metric = selection_metric(record, cfg.select_by, step)
            if metric <= best or not val:
                best = metric
                config = model_config_for(cfg, mean, std, actions, f"{out.name}-vae", keep_from, lineage,
                                          data_terms)
                config.provenance["vae_val_mpjpe_mm"] = record.get("val_mpjpe_mm")
                config.provenance["vae_val_global_mpjpe_mm"] = record.get("val_global_mpjpe_mm")
                config.provenance["vae_steps"] = step
                save_weights(out / "vae.safetensors", vae)
                save_json(out / "config.json", config.to_dict())
            save_train_state(out, vae, opt, step, {"best_mpjpe_mm": best, "select_by": cfg.select_by,
                                                   "vae_lineage": lineage})
    bar.close()
    if rt.is_main:
        log.close()
        if not (out / "config.json").exists():
            save_weights(out / "vae.safetensors", vae)
            config = model_config_for(cfg, mean, std, actions, f"{out.name}-vae", keep_from, lineage,
                                      data_terms)
            save_json(out / "config.json", config.to_dict())
    rt.barrier()
    return out
