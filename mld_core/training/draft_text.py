"""The Draft's text encoder: distil the model's MiniLM (6 layers) into a shorter stack of its own layers.

    python -m mld_core train draft-text --data DIR --teacher MODEL_DIR --out RUN [--minutes 60] [--install]

Every Draft take encodes its prompt, and the 6-layer MiniLM is about a third of a Draft's time (docs/draft.md). The
student keeps the teacher's embeddings and tokenizer and starts from copies of some of its layers (``init_layers``).
It learns what the denoisers read of a text: per text, the mean squared error of the last hidden states over its real
tokens, plus ``pooled_weight`` x (1 - cosine) of the pooled embeddings, plus ``condition_weight`` x the error of each
of the model's denoisers' condition tokens (over their variance). The texts (text_variant): training captions as
they are, spliced, with words dropped, with sides swapped or reworded; prompts composed from phrases; random words of
the vocabulary, so prompts no caption spells out still land near the teacher's embedding.

The run folder holds ``draft_text.safetensors`` (the student's layers) and its log; ``--install`` copies the layers
(fp16) into the model folder and sets config ``draft.text_layers``: the Draft then encodes with them
(MLDPipeline.from_pretrained), Final keeps the full encoder.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from mld_core import inputs
from mld_core.checkpoint import DRAFT_TEXT_WEIGHTS, load_config, save_json
from mld_core.data import terms
from mld_core.data.captions import SUBJECTS, reworded
from mld_core.fileio import atomic_write
from mld_core.inputs import InputError
from mld_core.training import distributed
from mld_core.training.common import (Budget, checked_budget, load_train_state, lr_factor, run_training_data,
                                     save_train_state, set_lr, setup_torch)


@dataclass
class DraftTextTrainConfig:
    """Settings of ``train draft-text`` (saved as the run's train_config.json)."""

    data: str = ""
    teacher: str = ""  # a model folder whose text encoder is the MiniLM
    out: str = ""
    seed: int = 0
    threads: int | None = None
    steps: int | None = None
    minutes: float | None = None
    batch_size: int = 64  # texts per batch, over all processes (torchrun): each takes its share
    lr: float = 1e-4
    decay_start: float = 0.5
    init_layers: list = field(default_factory=lambda: [0, 3, 5])  # the teacher's layers the student starts from
    pooled_weight: float = 1.0
    condition_weight: float = 1.0  # the model's denoisers' condition tokens of the texts (MSE / their variance)
    splice_share: float = 0.25  # share of a batch's texts that splice two captions at a word
    drop_share: float = 0.15  # ... that drop words of a caption
    swap_share: float = 0.2  # ... that swap a caption's sides and directions (left <-> right, ...): pairs of texts
    #                          that differ in one word, which the denoisers must tell apart
    reword_share: float = 0.3  # ... that say a caption in other words (reworded: subjects, synonyms)
    composed_share: float = 0.25  # share of all texts composed from phrases (composed_prompt: other wordings)
    random_share: float = 0.05  # share of all texts that are random words of the vocabulary (every word's states)
    val_texts: int = 256  # validation split captions scored at each save
    save_every: int = 100
    device: str = "cpu"  # cpu, cuda, mps or auto (where this sitting trains; any sitting may resume on another)
    fp32: bool = False  # accepted for every stage's --fp32; this stage trains in float32 everywhere

    def __post_init__(self):
        """Every setting checked before any work, and kept as the checked number."""
        self.steps, self.minutes = checked_budget(self.steps, self.minutes)
        for name, lo, hi in (("batch_size", 1, 65536), ("val_texts", 1, 10**6), ("save_every", 1, 10**9)):
            setattr(self, name, inputs.int_in_range(getattr(self, name), name, lo, hi))
        for name, lo, hi in (("lr", 1e-12, 1.0), ("decay_start", 0.0, 1.0), ("pooled_weight", 0.0, 1e3),
                             ("condition_weight", 0.0, 1e3),
                             ("splice_share", 0.0, 1.0), ("drop_share", 0.0, 1.0), ("swap_share", 0.0, 1.0),
                             ("reword_share", 0.0, 1.0), ("composed_share", 0.0, 1.0), ("random_share", 0.0, 1.0)):
            setattr(self, name, inputs.number_in_range(getattr(self, name), name, lo, hi))
        if self.splice_share + self.drop_share + self.swap_share + self.reword_share > 1.0:
            raise InputError("splice_share + drop_share + swap_share + reword_share must be at most 1")
        if self.composed_share + self.random_share > 1.0:
            raise InputError("composed_share + random_share must be at most 1")
        if not isinstance(self.init_layers, (list, tuple)) or not self.init_layers:
            raise InputError(f"init_layers must be a non-empty list of layer indices, got {self.init_layers!r}")
        self.init_layers = [inputs.int_in_range(i, "init_layers", 0, 10**6) for i in self.init_layers]


OPPOSITES = {"left": "right", "right": "left", "forward": "backward", "forwards": "backwards",
             "backward": "forward", "backwards": "forwards", "up": "down", "down": "up", "clockwise":
             "counterclockwise", "counterclockwise": "clockwise", "front": "back", "back": "front"}


ACTIONS = ("walks", "runs", "jogs", "sprints", "strolls", "steps", "marches", "limps", "shuffles", "sneaks", "jumps",
           "hops", "skips", "kicks", "stomps", "waves", "raises", "lifts", "lowers", "swings", "shakes", "turns",
           "spins", "twists", "bows", "nods", "crouches", "squats", "kneels", "sits down", "stands up", "leans",
           "stretches", "punches", "throws", "catches", "claps", "dances", "climbs", "crawls", "stumbles", "reaches",
           "points", "grabs", "pushes", "pulls", "carries", "salutes", "shrugs", "bends over", "looks around",
           "backs away", "paces", "slides", "dodges", "blocks", "slashes", "stabs", "rolls", "falls down", "gets up")
PARTS = ("the left hand", "the right hand", "both hands", "one hand", "the left arm", "the right arm", "both arms",
         "the left leg", "the right leg", "the left foot", "the right foot", "the head", "the hips", "the torso",
         "a sword", "a ball", "a heavy box", "a cup", "a rope", "their hat", "an imaginary object")
WAYS = ("forward", "backward", "backwards", "to the left", "to the right", "in a circle", "in place", "ahead", "up",
        "down", "sideways", "diagonally to the left", "diagonally to the right", "around", "across the room",
        "straight ahead", "above the head", "over the shoulder", "towards the camera", "away from the camera")
MANNERS = ("slowly", "quickly", "happily", "angrily", "sadly", "carefully", "nervously", "proudly", "lazily",
           "with energy", "like an old man", "like a zombie", "like a robot", "at full speed", "several times",
           "twice", "three times", "politely", "gracefully", "clumsily", "in a hurry", "while looking down")
JOINS = (" and ", ", then ", " while ", " before ", " and then ", " after that ", ". then ")


def composed_prompt(rng: np.random.Generator) -> str:
    """A prompt composed from phrases (who, what, with which part, where, how), one or two clauses: wordings the
    captions do not use, as users type them."""
    def clause() -> str:
        words = [ACTIONS[int(rng.integers(len(ACTIONS)))]]
        for phrases, chance in ((PARTS, 0.4), (WAYS, 0.6), (MANNERS, 0.4)):
            if rng.random() < chance:
                words.append(phrases[int(rng.integers(len(phrases)))])
        return " ".join(words)

    text = f"{SUBJECTS[int(rng.integers(len(SUBJECTS)))]} {clause()}"
    if rng.random() < 0.5:
        text += JOINS[int(rng.integers(len(JOINS)))] + clause()
    return text


def text_variant(captions: list[str], rng: np.random.Generator, cfg: DraftTextTrainConfig,
                 vocabulary: list[str] = ()) -> str:
    """One training text: composed from phrases, random words of ``vocabulary``, or a caption: as it is, two
    captions spliced at a word, with words dropped, with its sides and directions swapped, or reworded."""
    source = rng.random()
    if source < cfg.composed_share:
        return composed_prompt(rng)
    if source < cfg.composed_share + cfg.random_share and vocabulary:
        return " ".join(vocabulary[int(i)] for i in rng.integers(len(vocabulary), size=int(rng.integers(2, 13))))
    words = captions[int(rng.integers(len(captions)))].split()
    r = rng.random()
    if r < cfg.splice_share and len(words) > 1:
        other = captions[int(rng.integers(len(captions)))].split()
        words = words[: int(rng.integers(1, len(words)))] + other[int(rng.integers(len(other))):]
    elif r < cfg.splice_share + cfg.drop_share:
        words = [w for w in words if rng.random() > 0.15] or words
    elif r < cfg.splice_share + cfg.drop_share + cfg.swap_share:
        words = [_opposite(w) for w in words]
    elif r < cfg.splice_share + cfg.drop_share + cfg.swap_share + cfg.reword_share:
        return reworded(" ".join(words), rng)
    return " ".join(words)


def whole_words(tokenizer) -> list[str]:
    """The vocabulary's whole words (no word pieces, special tokens or punctuation)."""
    return sorted(w for w in tokenizer.vocab if w.isalpha() and w.isascii() and len(w) > 1)


def _opposite(word: str) -> str:
    """left -> right, 'left,' -> 'right,', anything else unchanged."""
    core = word.rstrip(".,;!?")
    return OPPOSITES.get(core.lower(), core) + word[len(core):]


def distil_loss(student, teacher, texts: list[str], cfg: DraftTextTrainConfig, denoisers: list = (),
                totals=None) -> tuple[torch.Tensor, dict]:
    """Hidden-state MSE over real tokens + pooled_weight x (1 - cos) of the pooled embeddings + condition_weight x
    the MSE (over its variance) of each denoiser's condition tokens, and the parts.

    ``totals`` (one of torchrun's processes, ``texts`` its rows of a batch): a function summing a tensor over the
    processes; the loss is then this process's part of the whole batch's, whose sum over the processes is the whole
    batch's loss (the token count and the variances are the whole batch's)."""
    from mld_core.models.text_encoder import TextEmbedding

    with torch.no_grad():
        goal = teacher(texts)
    own_text = student.embed(*student.tokenize(texts))  # differentiable
    states, pooled, mask = own_text.tokens, own_text.pooled, own_text.mask
    m = mask[..., None].float()  # (B, L, 1)
    rows = len(texts) if totals is None else float(totals(torch.tensor(float(len(texts)), device=m.device)))
    count = m.sum() if totals is None else totals(m.sum().detach())
    mse = (((states - goal.tokens.float()) ** 2) * m).sum() / (count * states.shape[-1])
    cos = (pooled * goal.pooled.float()).sum(-1).sum() / rows
    loss = mse + cfg.pooled_weight * (len(texts) / rows - cos)
    parts = {"mse": mse.item(), "cos": cos.item()}
    for k, den in enumerate(denoisers if cfg.condition_weight else ()):
        L = den.config.max_text_tokens
        with torch.no_grad():
            aim = den.condition_tokens(len(texts), text=TextEmbedding(
                goal.pooled.float(), goal.tokens[:, :L].float(), goal.mask[:, :L]))  # (B, C, d)
        own = den.condition_tokens(len(texts), text=TextEmbedding(pooled, states[:, :L], mask[:, :L]))
        error = ((own - aim) ** 2).mean() if totals is None else ((own - aim) ** 2).sum() / (rows * aim[0].numel())
        cond = error / _variance(aim, totals).clamp(min=1e-12)
        loss = loss + cfg.condition_weight * cond
        parts[f"cond{k}"] = cond.item()
    return loss, parts


def _variance(x: torch.Tensor, totals=None) -> torch.Tensor:
    """The variance of every element of ``x`` (unbiased); with ``totals``, over every process's ``x``."""
    if totals is None:
        return x.var()
    n, s1, s2 = totals(torch.stack([torch.tensor(float(x.numel()), device=x.device), x.sum(), (x ** 2).sum()]).double())
    return ((s2 - s1 * s1 / n) / (n - 1)).to(x.dtype)


class _DistilLoss(nn.Module):
    """This process's part of the distillation loss as a module's forward, so DistributedDataParallel can wrap the
    student (the teacher and the denoisers stay outside: frozen, and not broadcast)."""

    def __init__(self, student, teacher, cfg: DraftTextTrainConfig, denoisers: list, totals):
        super().__init__()
        self.student, self.frozen, self.cfg, self.totals = student, (teacher, list(denoisers)), cfg, totals

    def forward(self, texts: list[str]):
        teacher, denoisers = self.frozen
        return distil_loss(self.student, teacher, texts, self.cfg, denoisers, self.totals)


def trainable(encoder) -> nn.Module:
    """The encoder with its layers' weights turned into parameters (a loaded MiniLM keeps them as frozen buffers)."""
    for layer in encoder.layers:
        layer.packed = {}
        for name, buf in list(layer._buffers.items()):
            del layer._buffers[name]
            layer.register_parameter(name, nn.Parameter(buf.detach().clone().float()))
    return encoder


def save_layers(encoder, path: Path, dtype: torch.dtype = torch.float32) -> None:
    """The encoder's layers as a safetensors file of HF-named tensors (MiniLMEncoder.from_pretrained(layer_file=))."""
    from safetensors.torch import save_file

    weights = {k: v.to(dtype).contiguous() for k, v in encoder.layer_weights().items()}
    atomic_write(Path(path), lambda tmp: save_file(weights, str(tmp)))


def train_draft_text(cfg: DraftTextTrainConfig, resume: bool = False) -> Path:
    """Distil the teacher model folder's MiniLM into ``len(init_layers)`` layers; the run folder is cfg.out."""
    from mld_core.data.dataset import load_split
    from mld_core.training.denoiser import text_units
    from mld_core.training.vae import prepare_run_dir

    out, teacher_dir = Path(cfg.out), Path(cfg.teacher)
    base = load_config(teacher_dir)
    # float32 everywhere: the layers' states are matched to a fine tolerance
    rt = distributed.runtime(cfg.device, batch=(cfg.batch_size, "batch_size"))
    teacher = _teacher_encoder(base, teacher_dir, cfg.init_layers, rt.device)
    captions = sorted({c for u in text_units(load_split(cfg.data, "train"), base.fps) for c in u.captions if c})
    val = sorted({c for u in text_units(load_split(cfg.data, "val"), base.fps) for c in u.captions if c})
    if not captions:
        raise ValueError(f"{cfg.data}: the train split has no captions")
    if resume:
        _check_same_student(out, cfg)
    rt.on_main(lambda: prepare_run_dir(out, resume))
    setup_torch(cfg.seed, cfg.threads)
    denoisers = [d.to(rt.device) for d in _frozen_denoisers(teacher_dir, base)] if cfg.condition_weight else []
    vocabulary = whole_words(teacher.tokenizer)

    # 1. The student: copies of the teacher's layers init_layers on its embeddings.
    student = trainable(teacher.keep_layers(cfg.init_layers)).to(rt.device)
    opt = torch.optim.AdamW([p for p in student.parameters()], lr=cfg.lr, weight_decay=0.0)
    step, _ = load_train_state(out, student, opt) if resume else (0, {})
    val = [val[i] for i in np.random.default_rng(cfg.seed).permutation(len(val))[: cfg.val_texts]] or captions[:1]
    if rt.is_main:
        save_json(out / "train_config.json", {**asdict(cfg), "stage": "draft-text",
                                              "run": rt.describe(cfg.batch_size, "texts"),
                                              "training_data": run_training_data(cfg.data, [base], out, resume)})
    totals = _sum_over_processes if rt.size > 1 else None
    model = rt.wrap(_DistilLoss(student, teacher, cfg, denoisers, totals))

    def validate() -> dict:
        with torch.no_grad():
            _, parts = distil_loss(student, teacher, val, cfg, denoisers)
        return {f"val_{k}": v for k, v in parts.items()}

    # 2. Distillation; each save writes the layers and the train state, then logs the step. Every process draws
    #    the whole batch of texts and trains on its rows of it.
    log = open(out / "log.jsonl", "a") if rt.is_main else None
    if step == 0 and rt.is_main:
        log.write(json.dumps({"step": 0, **validate()}) + "\n")
    budget, running = rt.budget(Budget(cfg.steps, cfg.minutes)), None
    while not budget.done(step):
        set_lr(opt, cfg.lr * lr_factor(budget.progress(step), cfg.decay_start))
        rng, _ = distributed.step_rng(cfg.seed, step)
        texts = [text_variant(captions, rng, cfg, vocabulary) for _ in range(cfg.batch_size)]
        loss, _ = model([texts[i] for i in rt.rows(len(texts))])
        rt.step(loss * rt.size, opt, list(student.parameters()))
        step += 1
        running = loss.item() * rt.size if running is None else 0.95 * running + 0.05 * loss.item() * rt.size
        if (step % cfg.save_every == 0 or budget.done(step)) and rt.is_main:
            save_layers(student, out / DRAFT_TEXT_WEIGHTS)
            save_train_state(out, student, opt, step)
            log.write(json.dumps({"step": step, "loss": running, **validate(),
                                  "minutes": round(budget.minutes, 2)}) + "\n")
            log.flush()
    if rt.is_main:
        log.close()
    rt.barrier()
    return out


def _sum_over_processes(value: torch.Tensor) -> torch.Tensor:
    """``value`` summed over torchrun's processes (no gradient flows through)."""
    value = value.detach().clone()
    torch.distributed.all_reduce(value)
    return value


def _teacher_encoder(base, teacher_dir: Path, init_layers: list, device: torch.device | str = "cpu"):
    """The model's MiniLM on ``device`` (prepacked on the CPU), checked to have the layers ``init_layers`` names
    (one-line errors)."""
    from mld_core.models.text_encoder import MiniLMEncoder, TextEncoderError, load_text_encoder

    try:
        teacher = load_text_encoder(base.text_encoder)
    except (TextEncoderError, TypeError) as exc:
        raise ValueError(f"--teacher {teacher_dir}: its text encoder cannot be loaded: {exc}") from None
    if not isinstance(teacher, MiniLMEncoder):
        raise ValueError(f"--teacher {teacher_dir}: its text encoder ({base.text_encoder.get('kind')}) is no MiniLM")
    if max(init_layers) >= len(teacher.layers):
        raise ValueError(f"init_layers {init_layers}: the text encoder has {len(teacher.layers)} layers")
    teacher.to(device)
    teacher.pack_for_cpu_inference()  # no-op off the CPU
    return teacher


def _check_same_student(out: Path, cfg: DraftTextTrainConfig) -> None:
    """--resume continues the student the run started: the same init_layers."""
    path = out / "train_config.json"
    if path.is_file():
        started = json.loads(path.read_text()).get("init_layers")
        if started is not None and list(started) != list(cfg.init_layers):
            raise ValueError(f"{out} trains a student of layers {started}; --resume cannot change init_layers "
                             f"to {cfg.init_layers}")


def _frozen_denoisers(model_dir: Path, base) -> list:
    """The model folder's text-conditioned denoisers (its own and its Draft's), frozen: what reads the text."""
    from mld_core.checkpoint import load_weights
    from mld_core.models.denoiser import LatentDenoiser

    found = []
    for config, name in ((base.denoiser, "denoiser.safetensors"),
                         (base.draft.denoiser if base.draft is not None else None, "draft.safetensors")):
        if config is not None and config.cond == "text" and (model_dir / name).is_file():
            den = LatentDenoiser(config)
            load_weights(model_dir / name, den)
            found.append(den.eval().requires_grad_(False))
    return found


def install_draft_text(run: Path, model_dir: Path) -> None:
    """Copy a distilled Draft text encoder (its layers, fp16) into a model folder with a Draft, and set config
    ``draft.text_layers``. The layers are read and checked against the folder's text encoder before anything is
    written; errors are one line (ValueError)."""
    from mld_core.models.text_encoder import TextEncoderError, load_text_encoder

    cfg = load_config(model_dir)
    if cfg.draft is None:
        raise ValueError(f"{model_dir} has no Draft (train one with `train draft` first)")
    source = Path(run) / DRAFT_TEXT_WEIGHTS
    try:
        student = load_text_encoder({**cfg.text_encoder, "layer_file": str(source)})
        run_cfg = json.loads((Path(run) / "train_config.json").read_text())
    except (TextEncoderError, TypeError, OSError, ValueError) as exc:
        raise ValueError(f"cannot install {source} into {model_dir}: {str(exc).splitlines()[0]}") from None
    save_layers(student, Path(model_dir) / DRAFT_TEXT_WEIGHTS, torch.float16)
    cfg.draft.text_layers = len(student.layers)
    cfg.provenance["draft_text_training"] = {k: v for k, v in run_cfg.items() if k not in ("stage", "training_data")}
    terms.add_to(cfg, run_cfg.get("training_data") or [terms.unrecorded(f"Draft text encoder {Path(run).name}")])
    save_json(Path(model_dir) / "config.json", cfg.to_dict())
