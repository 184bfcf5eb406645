"""Stage 2: train the latent denoiser on latents of the frozen VAE encoder.

    python -m mld_core train denoiser --data DIR --vae RUN --cond text|action|none --out RUN2 [--minutes 60] [--resume]

Latents are precomputed once (the encoder means of ``crops_per_clip`` random crops per clip plus the whole clip) and
cached in the run folder, as are the frozen text encoder's embeddings of every caption. DDPM training with epsilon
prediction, condition dropout for classifier-free guidance, content-balanced sampling and an EMA of the weights;
with ``fold_verb_guide`` the target is a verb-guided model's own guided noise instead (``verb_fold``). The run
folder is a complete model folder (config.json, vae.safetensors, denoiser.safetensors). ``batch_size`` is the whole
batch, split between torchrun's processes (mld_core.training.distributed); the latents and caption embeddings sit
on the training device.
"""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from mld_core import inputs
from mld_core.checkpoint import load_config, load_weights, recorded_path, save_json, save_weights
from mld_core.condition import verb_hint
from mld_core.condition.content_anchor import ContentAnchorConfig
from mld_core.data.captions import reworded
from mld_core.data.verbs import VERBS
from mld_core.models.denoiser import DenoiserConfig, LatentDenoiser, grow_latent, with_condition, with_verb_hints
from mld_core.models.vae import MotionVAE
from mld_core.schedulers import DDPMScheduler
from mld_core.training import distributed
from mld_core.training.common import (Budget, boosted_weights, check_boosted_labels, check_resumed_modules,
                                     checked_budget, checked_folder_setting, checked_label_boost,
                                     checked_module_names, load_train_state, lr_factor, run_training_data,
                                     save_train_state, set_lr, setup_torch, trainable_parameters,
                                     warmup_factor)
from mld_core.training.vae import GROWTH_NOISE, prepare_run_dir
from mld_core.training.verb_fold import check_foldable, load_verb_fold

LATENT_CACHE = "latents.safetensors"
TEXT_CACHE = "text_embeddings.safetensors"


@dataclass
class DenoiserTrainConfig:
    data: str = ""
    vae: str = ""
    out: str = ""
    cond: str = "text"
    seed: int = 0
    threads: int | None = None
    steps: int | None = None
    minutes: float | None = None
    batch_size: int = 128  # the whole batch, over all processes (torchrun): each takes its share
    lr: float = 1e-4
    ema_decay: float = 0.999
    decay_start: float = 0.6  # cosine learning-rate decay over the last 40% of the budget (--steps/--minutes)
    warmup_steps: int = 0  # the rate ramped up linearly over the run's first steps (a fresh optimiser on --init weights)
    crops_per_clip: int = 8
    balance_power: float = 0.7
    label_boost: dict | None = None  # {label: factor}: that label's clips drawn factor times as often (after balance)
    save_every: int = 500
    guidance_scale: float = 4.0
    bf16: bool = False  # bfloat16 autocast for forward/backward (fp32 weights, optimiser and EMA)
    text_encoder: dict = field(default_factory=lambda: {"kind": "minilm", "path": None})
    init: str | None = None  # a model folder to continue from (fine-tuning): its denoiser and latent normalisation
    # with --init on another VAE (its encoder retrained): normalise that VAE's latents afresh, not as the init model did
    renormalise_latents: bool = False
    reworded_captions: int = 0  # extra versions of each caption in other words (subjects, synonyms) to train on
    reworded_turns: bool = False  # rewordings also say "turns" to a side with other verbs (captions.TURN_VERBS)
    reworded_sides: bool = False  # rewordings also name a side from the body: "to his / her left" (captions.reworded)
    # text only: also read the checked verb each caption names (mld_core.condition.verb_hint), dropped to "none
    # named" for verb_hint_dropout of the rows so the sentence alone still carries the verb
    verb_hints: bool = False
    verb_hint_dropout: float = 0.2
    verb_hint_lr_scale: float = 30.0  # the hint vectors' learning rate over lr's (they start at zero, the rest trained)
    train_modules: list | None = None  # the denoiser's top-level modules to train (e.g. the text-reading ones); None: all
    # text only, with --init a model that has a verb denoiser on --vae's VAE: train towards that model's guided noise
    # (mld_core.training.verb_fold) instead of the drawn noise, so the run samples its verbs without a verb denoiser
    fold_verb_guide: bool = False
    caches_from: str | None = None  # a denoiser run of the same data, VAE, seed and captions: its caches copied
    device: str = "cpu"  # cpu, cuda, mps or auto (where this sitting trains; any sitting may resume on another)
    fp32: bool = False  # on CUDA, no mixed precision (default there: bf16 autocast, or fp16 with a gradient scaler)
    denoiser: DenoiserConfig = field(default_factory=DenoiserConfig)

    def __post_init__(self):
        self.steps, self.minutes = checked_budget(self.steps, self.minutes)
        self.warmup_steps = inputs.int_in_range(self.warmup_steps, "warmup_steps", 0, 1_000_000)
        self.reworded_captions = inputs.int_in_range(self.reworded_captions, "reworded_captions", 0, 20)
        self.reworded_turns = inputs.true_or_false(self.reworded_turns, "reworded_turns")
        self.reworded_sides = inputs.true_or_false(self.reworded_sides, "reworded_sides")
        self.renormalise_latents = inputs.true_or_false(self.renormalise_latents, "renormalise_latents")
        self.verb_hints = inputs.true_or_false(self.verb_hints, "verb_hints")
        if self.verb_hints and self.cond != "text":
            raise ValueError("verb_hints go with --cond text only")
        self.verb_hint_dropout = inputs.number_in_range(self.verb_hint_dropout, "verb_hint_dropout", 0.0, 1.0)
        self.verb_hint_lr_scale = inputs.number_in_range(self.verb_hint_lr_scale, "verb_hint_lr_scale", 0.0, 1000.0)
        self.train_modules = checked_module_names(self.train_modules)
        self.fold_verb_guide = inputs.true_or_false(self.fold_verb_guide, "fold_verb_guide")
        if self.fold_verb_guide and (self.cond != "text" or not self.init or self.renormalise_latents
                                     or self.verb_hints):
            raise ValueError("fold_verb_guide goes with --cond text and --init (a model with a verb denoiser), "
                             "without renormalise_latents or verb_hints")
        self.label_boost = checked_label_boost(self.label_boost)
        self.caches_from = checked_folder_setting(self.caches_from, "caches_from")
        if isinstance(self.denoiser, dict):
            self.denoiser = DenoiserConfig(**self.denoiser)


def recorded_settings(cfg: DenoiserTrainConfig) -> dict:
    """A run's settings as its model's provenance records them: the paths inside the checkout relative to it."""
    settings = {k: v for k, v in asdict(cfg).items() if k != "denoiser"}
    settings.update({k: recorded_path(settings[k]) for k in ("init", "vae", "data", "out")
                     if isinstance(settings.get(k), str)})
    return settings


@dataclass
class Unit:
    """A stretch of a clip with the captions that describe it (HumanML3D captions may cover a time span)."""

    features: np.ndarray
    captions: list
    label: str


def text_units(clips, fps: int) -> list[Unit]:
    units = []
    for clip in clips:
        whole = []
        for cap in clip.captions:
            start, end = float(cap.start_s or 0.0), float(cap.end_s or 0.0)
            if start == 0.0 and end == 0.0:
                whole.append(cap.text)
                continue
            segment = clip.features[int(start * fps): int(end * fps)]
            if len(segment) >= 10:
                units.append(Unit(segment, [cap.text], clip.action or "?"))
        if whole or not clip.captions:
            units.append(Unit(clip.features, whole or [""], clip.action or "?"))
    return units


@torch.no_grad()
def encode_latents(vae: MotionVAE, units: list[Unit], mean, std, crops: int, min_frames: int, max_frames: int,
                   seed: int) -> dict:
    """Encoder means of random crops: mu (N, n, d), lengths (N,), unit (N,)."""
    rng = np.random.default_rng(seed)
    jobs = []  # (unit index, start, length)
    for u, unit in enumerate(units):
        T = len(unit.features)
        full = min(T, max_frames)
        jobs.append((u, 0, full))
        for _ in range(crops if T > min_frames else 0):
            L = int(rng.integers(min_frames, full + 1))
            jobs.append((u, int(rng.integers(0, T - L + 1)), L))
    jobs.sort(key=lambda j: j[2])
    mus = []
    vae.eval()
    batch = []
    bar = tqdm(total=len(jobs), desc="encoding latents", unit="crop", dynamic_ncols=True)

    device = next(vae.parameters()).device

    def flush():
        x = np.stack([(units[u].features[s:s + L] - mean) / std for u, s, L in batch]).astype(np.float32)
        mu, _ = vae.encode(torch.from_numpy(x).to(device), torch.full((len(batch),), batch[0][2], device=device))
        mus.append(mu.float().cpu())
        bar.update(len(batch))
        batch.clear()

    for job in jobs:
        if batch and (job[2] != batch[0][2] or len(batch) * job[2] >= 16384):
            flush()
        batch.append(job)
    if batch:
        flush()
    bar.close()
    return {"mu": torch.cat(mus), "lengths": torch.tensor([j[2] for j in jobs]),
            "unit": torch.tensor([j[0] for j in jobs])}


def with_reworded_captions(units: list, per_caption: int, seed: int, turns: bool = False,
                           sides: bool = False) -> list[list[str]]:
    """Each unit's captions, followed by ``per_caption`` rewordings of each (``mld_core.data.captions.reworded``, with
    other verbs for turning to a side if ``turns``, a side named from the body if ``sides``; duplicates dropped): the
    texts a unit trains on."""
    rng = np.random.default_rng(seed)
    out = []
    for unit in units:
        texts = list(unit.captions)
        for caption in unit.captions:
            texts += [reworded(caption, rng, turns=turns, sides=sides) for _ in range(per_caption)]
        out.append(list(dict.fromkeys(texts)))
    return out


@torch.no_grad()
def embed_captions(encoder, captions: list[str], max_tokens: int, batch: int = 64) -> dict:
    pooled, tokens, mask = [], [], []
    for k in tqdm(range(0, len(captions), batch), desc="encoding captions", unit="batch", dynamic_ncols=True):
        emb = encoder(captions[k:k + batch])
        t = torch.zeros(emb.tokens.shape[0], max_tokens, emb.tokens.shape[-1], dtype=torch.float16)
        m = torch.zeros(emb.tokens.shape[0], max_tokens, dtype=torch.bool)
        L = min(max_tokens, emb.tokens.shape[1])
        t[:, :L] = emb.tokens[:, :L].half().cpu()
        m[:, :L] = emb.mask[:, :L].cpu()
        pooled.append(emb.pooled.float().cpu())
        tokens.append(t)
        mask.append(m)
    return {"pooled": torch.cat(pooled), "tokens": torch.cat(tokens), "mask": torch.cat(mask)}


def prepare_run_with_caches(out: Path, resume: bool, caches_from: str | None) -> None:
    """The run folder (``prepare_run_dir``), with the latent and caption caches of the run folder ``caches_from``
    copied in when a new run starts (a run of the same data, VAE and seed: the caption cache is checked against its
    captions when read, the latent cache is not)."""
    if caches_from and not resume and not Path(caches_from).is_dir():
        raise ValueError(f"caches_from: {caches_from} is not a run folder")
    prepare_run_dir(out, resume)
    for name in (LATENT_CACHE, TEXT_CACHE) if caches_from and not resume else ():
        if (Path(caches_from) / name).is_file():
            shutil.copyfile(Path(caches_from) / name, out / name)


def _cached(path: Path, make) -> dict:
    if path.is_file():
        return load_file(str(path))
    data = make()
    save_file({k: v.contiguous() for k, v in data.items()}, str(path))
    return data


def cached_caption_embeddings(path: Path, captions: list[str], make) -> dict:
    """``embed_captions`` of ``captions``, kept at ``path`` with the captions' SHA-256: a cache made for another
    caption list (other rewordings, a copied cache) is made again, never read against the wrong rows."""
    digest = torch.frombuffer(bytearray(hashlib.sha256("\n".join(captions).encode()).digest()), dtype=torch.uint8)
    if path.is_file():
        data = load_file(str(path))
        same_rows = data["pooled"].shape[0] == len(captions)
        if same_rows and torch.equal(data.get("captions_sha256", digest), digest):  # older caches: rows only
            return data
    data = {**make(), "captions_sha256": digest}
    save_file({k: v.contiguous() for k, v in data.items()}, str(path))
    return data


def _write_coverage_index(out: Path, units: list[Unit], encoder) -> None:
    """The run's prompt-coverage index (mld_core.condition.coverage) from its training captions and content labels."""
    from mld_core.condition import coverage

    pairs = [(c, u.label) for u in units for c in u.captions]
    known = sorted({label for _, label in pairs if label != "?"})
    index = coverage.build_index([c for c, _ in pairs], [label for _, label in pairs], encoder, known)
    index.save(out / coverage.INDEX_NAME)


class _DenoiserLoss(torch.nn.Module):
    """The denoiser's loss as a module's forward (condition tokens included), so DistributedDataParallel can wrap
    it."""

    def __init__(self, denoiser: LatentDenoiser):
        super().__init__()
        self.denoiser = denoiser

    def forward(self, z_t, t, lengths, target, drop, text=None, actions=None, verbs=None):
        """The mean squared error of the predicted noise against ``target`` (the drawn noise, or a fold's)."""
        den, B = self.denoiser, len(z_t)
        if den.config.cond == "none":
            cond = den.null_tokens(B)
        else:
            cond = den.condition_tokens(B, text=text, actions=actions, verbs=verbs, drop=drop)
        return torch.nn.functional.mse_loss(den(z_t, t, cond, lengths).float(), target)


def initial_denoiser(init: Path, init_cfg: DenoiserConfig, dcfg: DenoiserConfig, new_condition: bool,
                     seed: int) -> LatentDenoiser:
    """The --init model's denoiser (``init_cfg``) for ``dcfg``: where the VAE's latent has more tokens than it
    denoises (a grown latent, ``train vae`` with grow_latent_tokens), its latent positions grown the same way; with
    ``new_condition`` (another condition kind, or other action labels), only its shared weights carried over
    (``with_condition``); with other verb hints, every weight carried over (``with_verb_hints``)."""
    old = LatentDenoiser(init_cfg)
    load_weights(init / "denoiser.safetensors", old)
    if dcfg.latent_tokens != init_cfg.latent_tokens:
        old = grow_latent(old, dcfg.latent_tokens, noise=GROWTH_NOISE, seed=seed)
    if new_condition:
        return with_condition(old, dcfg, seed=seed)
    return with_verb_hints(old, dcfg.verb_hints) if dcfg.verb_hints != init_cfg.verb_hints else old


def parameter_groups(denoiser: LatentDenoiser, trained: list, hint_lr_scale: float) -> list[dict]:
    """The optimiser's groups: the hint vectors of a denoiser with verb hints in a group of their own, at
    ``hint_lr_scale`` times the rate (``common.set_lr``); one group otherwise."""
    hints = getattr(denoiser, "verb_embedding", None)
    if hints is None or not any(p is hints.weight for p in trained):
        return [{"params": trained}]
    return [{"params": [p for p in trained if p is not hints.weight]},
            {"params": [hints.weight], "lr_scale": hint_lr_scale}]


def train_denoiser(cfg: DenoiserTrainConfig, resume: bool = False) -> Path:
    from mld_core.data.dataset import load_split

    out, vae_dir = Path(cfg.out), Path(cfg.vae)
    base = load_config(vae_dir)
    rt = distributed.runtime(cfg.device, cfg.bf16, cfg.fp32, (cfg.batch_size, "batch_size"))  # before any writing
    rt.on_main(lambda: prepare_run_with_caches(out, resume, cfg.caches_from))
    setup_torch(cfg.seed, cfg.threads)
    vae = MotionVAE(base.vae)
    load_weights(vae_dir / "vae.safetensors", vae)
    for p in vae.parameters():
        p.requires_grad_(False)
    vae.to(rt.device)
    mean, std = base.mean_std
    fps = base.fps

    # 1. Training units, their captions and class labels.
    units = text_units(load_split(cfg.data, "train"), fps)
    if not units:
        raise ValueError(f"{cfg.data}: the train split is empty")
    check_boosted_labels([u.label for u in units], cfg.label_boost)  # before the slow encoding, not after it
    actions = sorted({u.label for u in units if u.label != "?"}) if cfg.cond == "action" else list(base.actions)
    init = load_config(Path(cfg.init)) if cfg.init else None
    if init is not None and init.denoiser is None:
        raise ValueError(f"--init {cfg.init} has no denoiser to continue from")
    if cfg.fold_verb_guide:  # before the slow encoding
        check_foldable(Path(cfg.init), init, vae_dir)
    init_cfg = copy.deepcopy(init.denoiser) if init is not None else None
    dcfg = copy.deepcopy(init_cfg) if init is not None else cfg.denoiser
    dcfg.cond = cfg.cond
    dcfg.latent_tokens, dcfg.latent_dim, dcfg.max_frames = base.vae.latent_tokens, base.vae.latent_dim, base.max_frames
    if init is not None and dcfg.latent_tokens < init_cfg.latent_tokens:  # grown below where the VAE's has more
        raise ValueError(f"--init {cfg.init} denoises {init_cfg.latent_tokens}-token latents; "
                         f"the VAE's have {dcfg.latent_tokens}")
    if cfg.cond == "action":
        dcfg.num_actions = len(actions)
    dcfg.verb_hints = list(VERBS) if cfg.verb_hints else []
    trainable_parameters(LatentDenoiser(dcfg), cfg.train_modules, "denoiser")  # names checked before the slow steps
    if resume:
        check_resumed_modules(out, cfg.train_modules)

    # 2. Frozen-encoder latents and caption embeddings, cached in the run folder (made by rank 0, read by all).
    def make_latents():
        return encode_latents(vae, units, mean, std, cfg.crops_per_clip, base.min_frames, base.max_frames, cfg.seed)

    rt.on_main(lambda: _cached(out / LATENT_CACHE, make_latents))
    lat = _cached(out / LATENT_CACHE, make_latents)
    del vae
    mu, lengths, unit_of = lat["mu"], lat["lengths"], lat["unit"]
    latent_mean = float(mu.mean())
    latent_scale = float(1.0 / mu.std())
    if init is not None and not cfg.renormalise_latents:  # the denoiser being continued learned latents normalised so
        latent_mean, latent_scale = init.latent_mean, init.latent_scale
    z0_all = (mu - latent_mean) * latent_scale  # (N, n, d)
    texts_of_unit = with_reworded_captions(units, cfg.reworded_captions, cfg.seed, cfg.reworded_turns,
                                           cfg.reworded_sides)
    captions = sorted({c for texts in texts_of_unit for c in texts})
    caption_index = {c: i for i, c in enumerate(captions)}
    unit_captions = [np.array([caption_index[c] for c in texts]) for texts in texts_of_unit]
    text = None
    if cfg.cond == "text":
        from mld_core.models.text_encoder import TextEmbedding, load_text_encoder

        encoder = load_text_encoder(cfg.text_encoder).to(rt.device)  # captions are encoded where training runs
        dcfg.text_dim = encoder.dim

        def make_text():
            text = cached_caption_embeddings(out / TEXT_CACHE, captions,
                                             lambda: embed_captions(encoder, captions, dcfg.max_text_tokens))
            _write_coverage_index(out, units, encoder)
            return text

        rt.on_main(make_text)
        text = cached_caption_embeddings(out / TEXT_CACHE, captions, lambda: None)  # as rank 0 wrote it
        del encoder
        text = {k: v.to(rt.device) for k, v in text.items() if k != "captions_sha256"}
    caption_verbs = verb_hint.verb_ids(captions, dcfg.verb_hints).to(rt.device)  # (captions,), 0: none named
    fold = load_verb_fold(Path(cfg.init), init, vae_dir, captions, rt.device) if cfg.fold_verb_guide else None
    label_ids = torch.tensor([actions.index(units[u].label) if units[u].label in actions else 0
                              for u in unit_of.tolist()])

    # 3. Model, EMA, optimiser, sampling weights.
    if init is not None and not resume:
        new_condition = dcfg.cond != init_cfg.cond or (cfg.cond == "action" and list(init.actions) != actions)
        denoiser = initial_denoiser(Path(cfg.init), init_cfg, dcfg, new_condition, cfg.seed)
    else:
        denoiser = LatentDenoiser(dcfg)
    ema = copy.deepcopy(denoiser).requires_grad_(False)
    trained = trainable_parameters(denoiser, cfg.train_modules, "denoiser")
    denoiser.to(rt.device)
    ema.to(rt.device)
    opt = torch.optim.AdamW(parameter_groups(denoiser, trained, cfg.verb_hint_lr_scale), lr=cfg.lr, weight_decay=0.01)
    step, extra = load_train_state(out, denoiser, opt) if resume else (0, {})
    if resume and (out / "denoiser.safetensors").is_file():
        load_weights(out / "denoiser.safetensors", ema)
    weights = boosted_weights([units[u].label for u in unit_of.tolist()], cfg.balance_power, cfg.label_boost)
    scheduler = DDPMScheduler(base.scheduler)
    n_train = base.scheduler.num_train_timesteps
    unit_list = unit_of.tolist()
    z0_all, lengths, label_ids = z0_all.to(rt.device), lengths.to(rt.device), label_ids.to(rt.device)

    config = copy.deepcopy(base)
    config.model_id = out.name
    config.denoiser = dcfg
    config.text_encoder = dict(cfg.text_encoder) if cfg.cond == "text" else {}
    config.latent_mean, config.latent_scale = latent_mean, latent_scale
    config.actions = actions
    config.guidance_scale = cfg.guidance_scale
    config.content_anchor = ContentAnchorConfig()  # an anchor is built and gated per denoiser (build_content_anchor.py)
    config.verb_guide = None  # a verb denoiser samples the latents of the denoiser it was attached to, not this one's
    config.training_data = run_training_data(cfg.data, [base, init], out, resume)
    config.provenance = {**{k: v for k, v in base.provenance.items() if k != "verb_guide"},
                         "denoiser_training": recorded_settings(cfg)}
    if fold is not None:  # the guide this run learns to do without
        config.provenance["folded_verb_guide"] = {"scale": fold.guide.scale, "actions": fold.guide.actions,
                                                  "guidance_scale": fold.guidance_scale}
    if rt.is_main:
        shutil.copyfile(vae_dir / "vae.safetensors", out / "vae.safetensors")
        save_json(out / "train_config.json", {**asdict(cfg), "stage": "denoiser",
                                              "run": rt.describe(cfg.batch_size, "latents")})

    def save():
        config.provenance["denoiser_steps"] = step
        save_weights(out / "denoiser.safetensors", ema)
        save_json(out / "config.json", config.to_dict())
        save_train_state(out, denoiser, opt, step)

    # 4. DDPM training: eps_theta(z_t, t, c) ~ eps with z_t = sqrt(a_t) z_0 + sqrt(1 - a_t) eps. Every process draws
    #    the whole batch (rows, timesteps, noise, dropped conditions, captions) and trains on its rows of it.
    budget = rt.budget(Budget(cfg.steps, cfg.minutes))
    log = open(out / "log.jsonl", "a") if rt.is_main else None
    bar = tqdm(total=cfg.steps, initial=step, desc="denoiser", unit="step", dynamic_ncols=True, disable=not rt.is_main)
    model = rt.wrap(_DenoiserLoss(denoiser))
    denoiser.train()
    running = None
    B = cfg.batch_size
    n, d = dcfg.latent_tokens, dcfg.latent_dim
    while not budget.done(step):
        rate = lr_factor(budget.progress(step), cfg.decay_start) * warmup_factor(step, cfg.warmup_steps)
        set_lr(opt, cfg.lr * rate)
        rng, gen = distributed.step_rng(cfg.seed, step)
        idx = rng.choice(len(z0_all), size=B, p=weights)
        t = torch.randint(0, n_train, (B,), generator=gen)
        noise = torch.randn(B, n, d, generator=gen)  # (B, n, d)
        drop = torch.rand(B, generator=gen) < dcfg.cond_dropout
        unhinted = torch.rand(B, generator=gen) < cfg.verb_hint_dropout if dcfg.verb_hints else None
        mine = rt.rows(B)
        rows = torch.from_numpy(idx[mine]).to(rt.device)
        t, noise, drop = (rt.to_device(v[mine]) for v in (t, noise, drop))
        z_t = scheduler.add_noise(z0_all[rows], noise, t)
        kwargs = {}
        if cfg.cond == "text":
            cap = torch.tensor([int(rng.choice(unit_captions[unit_list[i]])) for i in idx])[mine].to(rt.device)
            kwargs["text"] = TextEmbedding(pooled=text["pooled"][cap], tokens=text["tokens"][cap].float(),
                                           mask=text["mask"][cap])
            if dcfg.verb_hints:
                kwargs["verbs"] = caption_verbs[cap].masked_fill(rt.to_device(unhinted[mine]), verb_hint.NO_VERB)
        elif cfg.cond == "action":
            kwargs["actions"] = label_ids[rows]
        target = noise if fold is None else fold.targets(z_t, t, lengths[rows], kwargs["text"], drop, cap)
        with rt.autocast():
            loss = model(z_t, t, lengths[rows], target, drop, **kwargs)
        rt.step(loss * rt.share(B), opt, trained)
        with torch.no_grad():
            decay = min(cfg.ema_decay, (1 + step) / (10 + step))
            for pe, p in zip(ema.parameters(), denoiser.parameters()):
                pe.lerp_(p, 1 - decay)
        step += 1
        running = loss.item() if running is None else 0.98 * running + 0.02 * loss.item()
        bar.update(1)
        bar.set_postfix(loss=f"{running:.4f}")
        if (step % cfg.save_every == 0 or budget.done(step)) and rt.is_main:
            log.write(json.dumps({"step": step, "loss": running, "lr": opt.param_groups[0]["lr"], "minutes": round(budget.minutes, 2),
                                  "seconds": round(budget.minutes * 60, 3)}) + "\n")
            log.flush()
            save()
    bar.close()
    if rt.is_main:
        log.close()
        if not (out / "config.json").is_file():
            save()
    rt.barrier()
    return out
