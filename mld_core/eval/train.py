"""``python -m mld_core train evaluator``: fit the evaluator on a training split.

Contrastive text-motion alignment (symmetric InfoNCE over a batch, TMR-style; pairs with the same
caption text count as positives of each other, not negatives) plus cross-entropy for the action
classifier. The sentence vectors of every caption are computed once by the frozen text encoder and
cached in the run folder. The best epoch on the validation split (R-precision top-3 + action
accuracy) is kept. Resumable: the run folder holds ``train_state.pt`` after every epoch.

On a GPU (``device``) and under torchrun: ``batch_size`` is the whole batch; each process embeds its rows of it
and the loss is computed on every process over the whole batch's embeddings (gathered with their gradients), so
every pair still meets every other pair of its batch as a negative (mld_core.training.distributed).
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from mld_core.eval import metrics
from mld_core.eval.evaluator import CARD_NAME, Evaluator, EvaluatorConfig, _atomic_write, pooled_text
from mld_core.eval.samples import Pair, all_caption_texts, draw_pairs

STATE_NAME = "train_state.pt"
TEXT_CACHE = "text_cache.npz"
HISTORY = "history.json"
DEFAULT_TEXT_ENCODER = {"kind": "minilm"}


@dataclass
class EvaluatorTrainConfig:
    data: str
    out: str
    seed: int = 0
    threads: int = 1
    epochs: int = 60
    minutes: float | None = 12.0  # wall-time budget of this invocation (None: no limit)
    batch_size: int = 64
    lr: float = 3e-4
    weight_decay: float = 0.01
    warmup_steps: int = 100
    action_weight: float = 0.5
    min_frames: int = 20
    val_fraction: float = 0.05  # carved from train when the folder has no val split
    bucket: bool = True  # batches of similar lengths (less padding; negatives of similar duration)
    device: str = "cpu"  # cpu, cuda, mps or auto (where this sitting trains; float32 everywhere)

    def to_dict(self) -> dict:
        return asdict(self)


# --------------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------------


def _load(root: Path):
    from mld_core.data.dataset import load_mean_std, load_split

    train = load_split(root, "train")
    val = load_split(root, "val") if (root / "val.txt").is_file() else []
    test = load_split(root, "test") if (root / "test.txt").is_file() else []
    mean, std = load_mean_std(root)
    return train, val, test, np.asarray(mean, np.float32), np.asarray(std, np.float32)


def _split_val(train: list, fraction: float, seed: int) -> tuple[list, list]:
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(train))
    n_val = max(1, int(round(len(train) * fraction)))
    val_idx = set(order[:n_val].tolist())
    return [c for i, c in enumerate(train) if i not in val_idx], [c for i, c in enumerate(train) if i in val_idx]


def _action_names(root: Path, clips: list) -> list[str]:
    path = root / "actions.json"
    if path.is_file():
        try:
            classes = json.loads(path.read_text()).get("classes") or []
            if classes:
                return [str(c) for c in classes]
        except ValueError:
            pass
    return sorted({c.action for c in clips if getattr(c, "action", None) is not None})


class TextVectors:
    """Caption -> pooled sentence vector, computed once and cached as npz."""

    def __init__(self, texts: list[str], vectors: np.ndarray):
        self.index = {t: i for i, t in enumerate(texts)}
        self.texts, self.vectors = texts, vectors.astype(np.float32)

    def __call__(self, texts: list[str]) -> np.ndarray:
        return self.vectors[[self.index[t] for t in texts]]

    @classmethod
    def build(cls, texts: list[str], encoder, cache: Path | None, batch_size: int = 64, progress: bool = True):
        texts = sorted(set(texts))
        if cache is not None and cache.is_file():
            data = np.load(cache, allow_pickle=False)
            old = {t: v for t, v in zip(data["texts"].tolist(), data["vectors"])}
            if all(t in old for t in texts):
                return cls(texts, np.stack([old[t] for t in texts]) if texts else np.zeros((0, 1), np.float32))
        from tqdm import tqdm

        chunks = []
        for i in tqdm(range(0, len(texts), batch_size), desc="text vectors", unit="batch", disable=not progress):
            chunks.append(pooled_text(encoder, texts[i : i + batch_size]))
        vectors = np.concatenate(chunks).astype(np.float32)
        if cache is not None:
            def write(tmp):
                with open(tmp, "wb") as fh:
                    np.savez(fh, texts=np.array(texts), vectors=vectors)
            _atomic_write(cache, write)
        return cls(texts, vectors)


def _collate(pairs: list[Pair], model: Evaluator, actions: dict[str, int], text_vectors: TextVectors):
    """(normalised features (B, T, D), lengths, sentence vectors, caption group ids, action ids), on the model's
    device."""
    device = model.mean.device
    lens = [p.length for p in pairs]
    x = np.zeros((len(pairs), max(lens), model.config.feature_dim), np.float32)
    for i, p in enumerate(pairs):
        x[i, : p.length] = p.features
    texts = [p.text for p in pairs]
    return (model.normalize(torch.from_numpy(x).to(device)), torch.tensor(lens, device=device),
            torch.from_numpy(text_vectors(texts)).to(device), *_pair_ids(pairs, actions, device))


def _pair_ids(pairs: list[Pair], actions: dict[str, int], device) -> tuple[torch.Tensor, torch.Tensor]:
    """(caption group id, action id or -100) of each pair: pairs with one caption text share a group."""
    texts = [p.text for p in pairs]
    groups = {t: i for i, t in enumerate(dict.fromkeys(texts))}
    return (torch.tensor([groups[t] for t in texts], device=device),
            torch.tensor([actions.get(p.action, -100) if p.action is not None else -100 for p in pairs], device=device))


class _EvaluatorLoss(torch.nn.Module):
    """The batch's loss as a module's forward, so DistributedDataParallel can wrap it: contrastive + action terms
    over the whole batch, whose rows ``rows`` of ``total`` this process embeds (all of them in one process)."""

    def __init__(self, model: Evaluator, action_weight: float, size: int):
        super().__init__()
        self.model, self.action_weight, self.size = model, action_weight, size

    def forward(self, x, lens, tvec, groups, labels, total: int):
        m_emb, logits = self.model.motion_forward(x, lens)
        t_emb = self.model.text_forward(tvec)
        if self.size > 1:
            m_emb, t_emb = _whole_batch(m_emb, total, self.size), _whole_batch(t_emb, total, self.size)
            logits = _whole_batch(logits, total, self.size) if logits is not None else None
        loss = contrastive_loss(t_emb, m_emb, groups, self.model.config.temperature)
        if logits is not None and (labels >= 0).any():
            loss = loss + self.action_weight * F.cross_entropy(logits, labels, ignore_index=-100)
        return loss


def _whole_batch(rows: torch.Tensor, total: int, size: int) -> torch.Tensor:
    """Every process's rows (process r holds rows r, r + N, ...) in the batch's order, with their gradients."""
    from torch.distributed.nn.functional import all_gather

    per = -(-total // size)
    padded = torch.cat([rows, rows.new_zeros(per - len(rows), *rows.shape[1:])])  # (per, ...)
    pieces = torch.stack(all_gather(padded))  # (N, per, ...)
    return pieces.transpose(0, 1).reshape(per * size, *rows.shape[1:])[:total]


def _batches(pairs: list[Pair], batch_size: int, rng: np.random.Generator, bucket: bool) -> list[np.ndarray]:
    """Index batches in random order; with ``bucket``, each batch holds pairs of similar length."""
    order = rng.permutation(len(pairs))
    if bucket:
        order = order[np.argsort([pairs[i].length for i in order], kind="stable")]
    batches = [order[b : b + batch_size] for b in range(0, len(order), batch_size)]
    return [batches[i] for i in rng.permutation(len(batches))]


def contrastive_loss(text_emb: torch.Tensor, motion_emb: torch.Tensor, groups: torch.Tensor,
                     temperature: float) -> torch.Tensor:
    """Symmetric multi-positive InfoNCE; rows with the same group id (same caption) are positives."""
    logits = motion_emb @ text_emb.T / temperature  # (B motions, B texts)
    positive = groups[:, None] == groups[None, :]  # (B, B), diagonal always True

    def one_side(lg: torch.Tensor) -> torch.Tensor:
        return (torch.logsumexp(lg, 1) - torch.logsumexp(lg.masked_fill(~positive, float("-inf")), 1)).mean()

    return 0.5 * (one_side(logits) + one_side(logits.T))


# --------------------------------------------------------------------------------------------------
# Scoring
# --------------------------------------------------------------------------------------------------


def score_pairs(model: Evaluator, pairs: list[Pair], text_vectors, actions: dict[str, int] | None = None) -> dict:
    """R-precision top-1/2/3, MM-Dist, Diversity (when >= 300 pairs) and action accuracy of real pairs."""
    feats = [p.features for p in pairs]
    motion = model.encode_motion(feats)
    text = model.encode_pooled_text(text_vectors([p.text for p in pairs]))
    out = {"pairs": len(pairs)}
    pool = min(32, len(pairs))
    if pool >= 2:
        hits, mm = metrics.r_precision(text, motion, batch_size=pool, rng=np.random.default_rng(0))
        out.update({"R@1": float(hits[0]), "R@2": float(hits[1]), "R@3": float(hits[2]), "MM-Dist": mm,
                    "pool": pool})
    if len(pairs) >= 300:
        out["Diversity"] = metrics.diversity(motion, 300, rng=np.random.default_rng(0))
    if actions and model.config.num_actions:
        labelled = [i for i, p in enumerate(pairs) if p.action in actions]
        if labelled:
            logits = model.classify([feats[i] for i in labelled])
            y = np.array([actions[pairs[i].action] for i in labelled])
            out["action_acc"] = metrics.accuracy(logits, y)
            per_class = [float((logits[y == c].argmax(1) == c).mean()) for c in np.unique(y)]
            out["action_acc_balanced"] = float(np.mean(per_class))
    return out


_SIDE = re.compile(r"\b(left|right)\b", re.IGNORECASE)


def mirror_side_accuracy(model: Evaluator, clips: list, text_vectors) -> tuple[float, int] | None:
    """Left/right check on mirrored clip pairs (id and "M" + id): how often a motion is closer to its own
    sided caption than to the mirrored clip's caption (same caption index, left and right swapped)."""
    by_id = {c.id: c for c in clips}
    motions, own, other = [], [], []
    for c in clips:
        m = by_id.get("M" + c.id)
        if c.id.startswith("M") or m is None:
            continue
        for a, b in ((c, m), (m, c)):
            for ca, cb in zip(a.captions, b.captions):
                if _SIDE.search(ca.text) and ca.text.strip() != cb.text.strip():
                    motions.append(a.features[: model.config.max_frames])
                    own.append(ca.text.strip())
                    other.append(cb.text.strip())
                    break
    if not motions:
        return None
    try:
        t_own, t_other = model.encode_pooled_text(text_vectors(own)), model.encode_pooled_text(text_vectors(other))
    except KeyError:  # a caption without a cached vector (e.g. shorter than min_frames)
        return None
    emb = model.encode_motion(motions)
    closer = np.linalg.norm(emb - t_own, axis=1) < np.linalg.norm(emb - t_other, axis=1)
    return float(closer.mean()), len(motions)


def _selection_score(s: dict) -> float:
    return s.get("R@3", 0.0) + s.get("action_acc", 0.0)


# --------------------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------------------


def train_evaluator(cfg: EvaluatorTrainConfig, model_config: EvaluatorConfig | None = None, *, resume: bool = False,
                    text_encoder=None, data: tuple | None = None, progress: bool = True, log=print) -> Path:
    """Train (or resume) an evaluator run in ``cfg.out``; returns the folder with the best evaluator.

    ``text_encoder``: a TextEncoder to use instead of loading ``model_config.text_encoder``.
    ``data``: preloaded ``(train_clips, val_clips, test_clips, mean, std, action_names)`` instead of reading
    ``cfg.data`` (clips as from mld_core.data.dataset.load_split).
    """
    from tqdm import tqdm

    from mld_core.training import distributed

    root, out = Path(cfg.data), Path(cfg.out)
    state_path = out / STATE_NAME
    rt = distributed.runtime(cfg.device, fp32=True, batch=(cfg.batch_size, "batch_size"))

    def prepare():
        if resume and not state_path.is_file():
            raise FileNotFoundError(f"nothing to resume: {state_path} does not exist")
        if not resume and (state_path.is_file() or (out / "model.safetensors").is_file()):
            raise FileExistsError(f"{out} already holds an evaluator run; pass --resume or choose another --out")
        out.mkdir(parents=True, exist_ok=True)

    rt.on_main(prepare)
    threads_before = torch.get_num_threads()
    torch.set_num_threads(max(1, cfg.threads))
    try:
        return _train(cfg, model_config, root, out, resume, text_encoder, data, progress and rt.is_main,
                      log if rt.is_main else (lambda *_: None), tqdm, rt)
    finally:
        torch.set_num_threads(threads_before)


def _train(cfg, model_config, root, out, resume, text_encoder, data, progress, log, tqdm, rt) -> Path:
    started = time.monotonic()
    if data is None:
        train, val, test, mean, std = _load(root)
        names = _action_names(root, train)
    else:
        train, val, test, mean, std, names = data
        mean, std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
    if not train:
        raise ValueError(f"{root} has no training clips")
    if not val:
        train, val = _split_val(train, cfg.val_fraction, cfg.seed)

    state = torch.load(out / STATE_NAME, map_location="cpu", weights_only=True) if resume else None
    if state is not None:
        model_config = EvaluatorConfig.from_dict(json.loads(state["model_config"]))
        cfg_saved = json.loads(state["train_config"])
        # the run's settings, except where and how long this invocation runs
        cfg = EvaluatorTrainConfig(**{**cfg_saved, "data": cfg.data, "out": cfg.out, "minutes": cfg.minutes,
                                      "epochs": cfg.epochs, "threads": cfg.threads, "device": cfg.device})
    else:
        model_config = model_config or EvaluatorConfig()
        model_config = EvaluatorConfig.from_dict({
            **model_config.to_dict(),
            "feature_dim": int(mean.shape[0]),
            "action_names": names,
            "text_encoder": model_config.text_encoder or dict(DEFAULT_TEXT_ENCODER),
        })
    actions = {n: i for i, n in enumerate(model_config.action_names)}

    if text_encoder is None:
        from mld_core.models.text_encoder import load_text_encoder

        text_encoder = load_text_encoder(dict(model_config.text_encoder)).to(rt.device)
    texts = all_caption_texts(train + val + test, min_frames=cfg.min_frames, fps=model_config.fps)
    rt.on_main(lambda: TextVectors.build(texts, text_encoder, out / TEXT_CACHE, progress=progress))  # cached by rank 0
    vectors = TextVectors.build(texts, text_encoder, out / TEXT_CACHE, progress=progress)
    if vectors.vectors.shape[1] != model_config.text_dim:
        model_config = EvaluatorConfig.from_dict({**model_config.to_dict(), "text_dim": int(vectors.vectors.shape[1])})

    torch.manual_seed(cfg.seed)
    model = Evaluator(model_config, mean, std).to(rt.device)
    model._text_encoder = text_encoder
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    epoch, step, best, history = 0, 0, -1.0, []
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["torch_rng"])
        epoch, step, best = int(state["epoch"]), int(state["step"]), float(state["best"])
        history = json.loads(state["history"])
        started -= 60.0 * (history[-1]["minutes"] if history else 0.0)  # minutes count across resumes
        log(f"resuming at epoch {epoch} (best val score {best:.3f})")

    val_pairs = draw_pairs(val, np.random.default_rng(12345), min_frames=cfg.min_frames,
                           max_frames=model_config.max_frames, fps=model_config.fps)
    n_train = sum(1 for _ in draw_pairs(train, np.random.default_rng(0), min_frames=cfg.min_frames,
                                        max_frames=model_config.max_frames, fps=model_config.fps))
    if n_train < 2:
        raise ValueError(f"{root} has fewer than 2 usable training pairs (captions >= {cfg.min_frames} frames)")
    per_epoch = int(np.ceil(n_train / cfg.batch_size))
    log(f"evaluator: {n_train} train pairs/epoch, {len(val_pairs)} val pairs, {len(names)} actions, "
        f"{sum(p.numel() for p in model.parameters()) / 1e6:.2f} M parameters, {torch.get_num_threads()} thread(s), "
        f"{rt.device.type}" + (f", {rt.size} processes" if rt.size > 1 else ""))
    wrapped = rt.wrap(_EvaluatorLoss(model, cfg.action_weight, rt.size))

    bar = tqdm(total=cfg.epochs * per_epoch, initial=min(step, cfg.epochs * per_epoch), desc="evaluator",
               unit="step", disable=not progress)
    stopped_early = False
    invocation_start = time.monotonic()
    while epoch < cfg.epochs:
        if rt.decide(cfg.minutes is not None and (time.monotonic() - invocation_start) / 60 >= cfg.minutes):
            stopped_early = True  # rank 0's clock decides for every process
            break
        rng = np.random.default_rng([cfg.seed, epoch])
        pairs = draw_pairs(train, rng, min_frames=cfg.min_frames, max_frames=model_config.max_frames,
                           fps=model_config.fps)
        model.train()
        losses = []
        for batch_idx in _batches(pairs, cfg.batch_size, rng, cfg.bucket):
            batch = [pairs[i] for i in batch_idx]
            if len(batch) < max(2, rt.size):  # every process needs a row
                continue
            groups, labels = _pair_ids(batch, actions, rt.device)  # the whole batch's
            x, lens, tvec, _, _ = _collate([batch[i] for i in rt.rows(len(batch))], model, actions, vectors)
            lr = cfg.lr * min(1.0, (step + 1) / max(1, cfg.warmup_steps))
            for g in opt.param_groups:
                g["lr"] = lr
            loss = wrapped(x, lens, tvec, groups, labels, len(batch))
            rt.step(loss, opt, list(model.parameters()))
            step += 1
            losses.append(float(loss.detach()))
            bar.update(1)
            bar.set_postfix(epoch=epoch + 1, loss=f"{np.mean(losses[-20:]):.3f}")
        epoch += 1
        if not rt.is_main:  # rank 0 alone scores and writes
            continue
        scores = score_pairs(model, val_pairs, vectors, actions)
        scores.update(epoch=epoch, loss=float(np.mean(losses)) if losses else float("nan"),
                      minutes=round((time.monotonic() - started) / 60, 2))
        history.append(scores)
        improved = _selection_score(scores) > best
        if improved:
            best = _selection_score(scores)
            model.save_pretrained(out)
        bar.write(f"epoch {epoch}: loss {scores['loss']:.3f} val R@1 {scores.get('R@1', float('nan')):.3f} "
                  f"R@3 {scores.get('R@3', float('nan')):.3f} acc {scores.get('action_acc', float('nan')):.3f}"
                  + (" *" if improved else ""))
        _save_state(out, model, opt, epoch, step, best, history, cfg, model_config)
    bar.close()
    if not rt.is_main:
        rt.barrier()
        return out
    if stopped_early:
        log(f"stopped after {cfg.minutes} minutes at epoch {epoch}; continue with --resume")

    best_model = Evaluator.from_pretrained(out)
    report = {"val": score_pairs(best_model, val_pairs, vectors, actions)}
    if test:
        test_pairs = draw_pairs(test, np.random.default_rng(0), min_frames=cfg.min_frames,
                                max_frames=model_config.max_frames, fps=model_config.fps)
        report["test"] = score_pairs(best_model, test_pairs, vectors, actions)
        side = mirror_side_accuracy(best_model, test, vectors)
        if side is not None:
            report["test"]["side_acc"], report["test"]["side_pairs"] = side
    best_epoch = max(history, key=_selection_score)["epoch"] if history else 0
    card = make_card(model_config, cfg, report, epoch=best_epoch, epochs_run=epoch, root=root,
                     n_train=n_train, minutes=history[-1]["minutes"] if history else 0.0)
    best_model.save_pretrained(out, card=card)
    _atomic_write(out / HISTORY, lambda p: Path(p).write_text(json.dumps({"history": history, "report": report},
                                                                          indent=2) + "\n"))
    for split, s in report.items():
        log(f"{split}: " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in s.items()))
    rt.barrier()
    return out


def _save_state(out, model, opt, epoch, step, best, history, cfg, model_config) -> None:
    from mld_core.training.common import on_cpu

    state = {"model": on_cpu(model.state_dict()), "optimizer": on_cpu(opt.state_dict()), "epoch": epoch, "step": step,
             "best": best, "history": json.dumps(history), "torch_rng": torch.get_rng_state(),
             "train_config": json.dumps(cfg.to_dict()), "model_config": json.dumps(model_config.to_dict())}
    _atomic_write(out / STATE_NAME, lambda p: torch.save(state, p))


def make_card(model_config: EvaluatorConfig, cfg: EvaluatorTrainConfig, report: dict, *, epoch: int,
              epochs_run: int, root: Path, n_train: int, minutes: float) -> str:
    def row(split: str) -> str:
        s = report.get(split)
        if not s:
            return f"| {split} | - | - | - | - | - | - |"
        f = lambda k: f"{s[k]:.3f}" if k in s else "-"  # noqa: E731
        return f"| {split} ({s['pairs']} pairs) | {f('R@1')} | {f('R@2')} | {f('R@3')} | {f('MM-Dist')} | " \
               f"{f('action_acc')} | {f('action_acc_balanced')} |"

    c = model_config
    test = report.get("test") or {}
    side_line = (f"Left/right check (mirrored test clips, {test['side_pairs']} motions): the motion is closer to its own "
                 f"sided caption than to the mirrored one in {100 * test['side_acc']:.1f}% of cases.\n"
                 if "side_acc" in test else "")
    return f"""# Evaluator card

A small text-motion evaluator for this project's MLD evaluation (FID, R-precision, MM-Dist, Diversity,
MultiModality on its embeddings; action accuracy with its classifier). It is a measuring instrument
for comparing models trained on the same data, not a generator, and its numbers are not comparable
with those of Guo et al.'s HumanML3D evaluator.

- Training data: `{root.name}` (HumanML3D-format folder), train split, {n_train} text-motion pairs per epoch
  (one random caption per clip, cropped to its segment, at most {c.max_frames} frames at {c.fps} fps).
  Default data: the Bandai-Namco-Research-Motiondataset 1 and 2, licence **CC BY-NC 4.0**
  (non-commercial); these weights are derived from it and carry the same licence.
- Motion encoder: {c.feature_dim}-d normalised features -> linear {c.hidden} -> two stride-2 1-D convolutions ->
  {c.layers}-layer transformer ({c.heads} heads, ff {c.ff_dim}) -> masked mean -> {c.embed_dim}-d unit embedding;
  action classifier ({c.num_actions} classes) on the pooled vector.
- Text encoder: frozen `{c.text_encoder}` pooled vector ({c.text_dim}-d) -> trainable MLP head -> {c.embed_dim}-d
  unit embedding.
- Loss: symmetric InfoNCE (temperature {c.temperature}; identical captions are positives) + {cfg.action_weight} x
  action cross-entropy. AdamW lr {cfg.lr}, batch {cfg.batch_size}, seed {cfg.seed}, {cfg.threads} CPU thread(s);
  best epoch {epoch} of {epochs_run} by validation R@3 + action accuracy; {minutes:.1f} minutes of wall time
  in all (data loading, sentence vectors, training, validation; on a machine shared with other jobs).
- Stored as fp16 safetensors (statistics fp32).

## Scores on real motions (one random caption per clip, R-precision pools of 32)

| split | R@1 | R@2 | R@3 | MM-Dist | action acc | balanced acc |
|---|---|---|---|---|---|---|
{row("val")}
{row("test")}

{side_line}
Limits: the frozen sentence encoder's pooled vector barely separates left from right (MiniLM: cos 0.98
for "waves the left hand" / "waves the right hand"); the trained head has to learn the difference from
the mirrored clips, so check the left/right line above before trusting R-precision on sidedness.
"""
