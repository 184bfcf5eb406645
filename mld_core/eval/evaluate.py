"""``python -m mld_core evaluate t2m|a2m|uncond|vae``: the paper's tables with 95% confidence intervals.

Each replication draws fresh text-motion pairs from the split (a random caption per clip, the motion
cropped to it, as T2M does), generates one motion per pair with the pair's length (and text or action),
embeds everything with the evaluator and computes the task's metrics. A "Real" row scores the real
motions of the same draws. Means and 95% intervals (1.96 * std / sqrt(n)) are over replications.

- t2m: R-precision top-1/2/3 (pools of 32), FID, MM-Dist, Diversity (300 pairs), MultiModality
  (``mm_texts`` texts x ``mm_repeats`` generations, ``mm_times`` pairs each). Extension: when the clips
  carry action labels, "Content-Acc" is the evaluator's classifier on each motion against the content
  label of the caption's clip (it tells left from right, which the pooled sentence vector barely does).
- a2m: FID, action accuracy (evaluator classifier), Diversity (200 pairs), MultiModality (20 same-action
  pairs per action), as ACTOR/MLD. A text model is prompted with ``action_prompt`` filled with the
  action's name.
- uncond: FID, KID, Diversity. A text- or action-conditioned model is sampled with its null condition
  (guidance scale 0, i.e. the classifier-free unconditional branch).
- vae: encode/decode the real motions; MPJPE (root-relative), global MPJPE, PA-MPJPE, acceleration
  error (mm, on joints recovered from features), FID and Diversity of the reconstructions.

The FID reference statistics come from one separate draw of the split (seeded), so the Real row's FID
measures the sampling noise floor.
"""

from __future__ import annotations

import inspect
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from mld_core.eval import metrics
from mld_core.eval.samples import Pair, draw_pairs

TASKS = ("t2m", "a2m", "uncond", "vae")

# (key, column title, direction) per task; direction: + higher is better, - lower, = closer to Real
COLUMNS = {
    "t2m": [("R@1", "R@1", "+"), ("R@2", "R@2", "+"), ("R@3", "R@3", "+"), ("FID", "FID", "-"),
            ("MM-Dist", "MM-Dist", "-"), ("Diversity", "Diversity", "="), ("MultiModality", "MModality", "+"),
            ("Content-Acc", "Content acc", "+")],
    "a2m": [("FID", "FID", "-"), ("Accuracy", "Accuracy", "+"), ("Diversity", "Diversity", "="),
            ("MultiModality", "MModality", "=")],
    "uncond": [("FID", "FID", "-"), ("KID", "KID", "-"), ("Diversity", "Diversity", "=")],
    "vae": [("MPJPE", "MPJPE mm", "-"), ("PA-MPJPE", "PA-MPJPE mm", "-"), ("ACCEL", "Accel mm", "-"),
            ("MPJPE_global", "global MPJPE mm", "-"), ("FID", "FID", "-"), ("Diversity", "Diversity", "=")],
}
ARROWS = {"+": "\u2191", "-": "\u2193", "=": "\u2192"}


@dataclass
class EvalSettings:
    replications: int = 20
    split: str = "test"
    seed: int = 0
    max_pairs: int | None = None  # cap on pairs per replication (None: every usable clip)
    r_pool: int = 32
    diversity_times: int = 300
    mm_texts: int = 100  # MultiModality: texts per replication
    mm_repeats: int = 30  # generations per text
    mm_times: int = 10  # pairs per text
    a2m_diversity_times: int = 200
    a2m_mm_times: int = 20
    kid_subsets: int = 50
    kid_subset_size: int = 1000
    batch_size: int = 32  # generation batch
    num_inference_steps: int | None = None  # None: the model's default
    guidance_scale: float | None = None
    draft: bool = False  # sample with the model's Draft denoiser
    side_redraws: int | None = None  # None: the model's config side_redraws; 0: every take its seed's first draw
    verb_redraws: int | None = None  # None: the model's config verb_redraws; 0: no take drawn again for its verb
    vae_sample: bool = True  # decode z ~ q(z|x) as MLD does; False: the posterior mean
    action_prompt: str = "a person does the {action} motion"  # a2m with a text model: the prompt per action

    def to_dict(self) -> dict:
        return asdict(self)


PRESETS = {
    # about 10 minutes for the default model's t2m on 2 cores (see docs/evaluation.md)
    "reduced": dict(replications=3, mm_texts=32, mm_repeats=16, mm_times=10),
    # the T2M / MLD protocol
    "full": dict(replications=20, mm_texts=100, mm_repeats=30, mm_times=10),
}


# Replication r's generations are seeded from seed * SEED_STRIDE + r * REPLICATION_SEED_STRIDE on, and use fewer
# than SEEDS_PER_REPLICATION seeds (its pairs, then 50,000 on, mm_texts x mm_repeats for MultiModality).
SEED_STRIDE, REPLICATION_SEED_STRIDE, SEEDS_PER_REPLICATION = 1_000_003, 100_003, 2 * 10**7


def min_pairs(task: str, settings: EvalSettings) -> int:
    """The fewest pairs a replication can score: R-precision needs a pool, FID and Diversity two motions."""
    return 2 if task == "vae" else max(2, min(settings.r_pool, 8))


def check_settings(settings: EvalSettings, task: str, name: Callable[[str], str] = str) -> None:
    """Every number of ``settings`` in its range for ``task``, or InputError naming the field as ``name(field)``
    (the command line passes its flags' names); nothing is clamped or silently skipped."""
    from mld_core import inputs

    for field, lo, hi in (("replications", 1, 10_000), ("batch_size", 1, 4096), ("mm_texts", 0, 10_000),
                          ("mm_repeats", 0, 1000)):
        inputs.int_in_range(getattr(settings, field), name(field), lo, hi)
    if settings.max_pairs is not None:
        inputs.int_in_range(settings.max_pairs, name("max_pairs"), min_pairs(task, settings), 10**9)
    if task == "t2m" and settings.mm_texts > 0 and settings.mm_repeats < settings.mm_times:
        raise inputs.InputError(f"{name('mm_repeats')} must be at least {settings.mm_times} (MultiModality compares "
                                f"{settings.mm_times} pairs per text), got {settings.mm_repeats}; or set "
                                f"{name('mm_texts')} 0 to leave MultiModality out")
    if settings.num_inference_steps is not None:
        inputs.check_steps(settings.num_inference_steps, name("num_inference_steps"))
    inputs.check_guidance(settings.guidance_scale, name("guidance_scale"))
    top = (inputs.SEED_MAX - settings.replications * REPLICATION_SEED_STRIDE - SEEDS_PER_REPLICATION) // SEED_STRIDE
    inputs.int_in_range(settings.seed, name("seed"), 0, max(top, 0))  # every generation's seed stays a valid seed


# --------------------------------------------------------------------------------------------------
# Generation through the pipeline
# --------------------------------------------------------------------------------------------------


class PipelineGenerator:
    """Adapts MLDPipeline to the evaluation: batched calls, per-row lengths and seeds."""

    def __init__(self, pipe, settings: EvalSettings, progress: bool = False):
        self.pipe, self.settings, self.progress = pipe, settings, progress
        self._per_row_seeds = None

    @property
    def fps(self) -> int:
        return int(getattr(self.pipe, "fps", 20))

    @property
    def frame_range(self) -> tuple[int, int]:
        cfg = getattr(self.pipe, "config", None)
        lo = int(getattr(cfg, "min_frames", round(self.pipe.min_seconds * self.fps)))
        hi = int(getattr(cfg, "max_frames", round(self.pipe.max_seconds * self.fps)))
        return lo, hi

    @property
    def cond(self) -> str:
        den = getattr(self.pipe, "denoiser", None)
        return getattr(getattr(den, "config", None), "cond", "text")

    @property
    def actions(self) -> list[str]:
        return list(getattr(getattr(self.pipe, "config", None), "actions", []) or [])

    def _kwargs(self) -> dict:
        kw = {}
        if self.settings.num_inference_steps is not None:
            kw["num_inference_steps"] = self.settings.num_inference_steps
        if self.settings.guidance_scale is not None:
            kw["guidance_scale"] = self.settings.guidance_scale
        if self.settings.draft:
            kw["draft"] = True
        if self.settings.side_redraws is not None:
            kw["side_redraws"] = self.settings.side_redraws
        if self.settings.verb_redraws is not None:
            kw["verb_redraws"] = self.settings.verb_redraws
        return kw

    def _call(self, prompts: list, frames: list[int], seeds: list[int], num_variants: int = 1, **kw):
        """One pipeline call; every row gets its own seed. Falls back to single-row calls when the
        pipeline takes only one integer seed per call (rows of one call would share their noise)."""
        secs = [n / self.fps for n in frames]
        if self._per_row_seeds is None:
            self._per_row_seeds = _accepts_seed_list(self.pipe)
        if self._per_row_seeds or len(prompts) == 1:
            seed = list(seeds) if len(prompts) > 1 else int(seeds[0])
            out = self.pipe(prompts, seconds=secs, seed=seed, num_variants=num_variants, **kw)
            return [out.features[i, : int(n)] for i, n in enumerate(out.lengths)]
        feats = []
        for i in range(len(prompts)):
            feats += self._call([prompts[i]], [frames[i]], [seeds[i]], num_variants, **kw)
        return feats

    def _batched(self, n: int, make_call: Callable[[slice], list], desc: str) -> list[np.ndarray]:
        from tqdm import tqdm

        out = []
        bs = self.settings.batch_size
        for start in tqdm(range(0, n, bs), desc=desc, unit="batch", leave=False, disable=not self.progress):
            out += make_call(slice(start, min(n, start + bs)))
        return out

    def text(self, prompts: list[str], frames: list[int], seed: int) -> list[np.ndarray]:
        kw = self._kwargs()
        return self._batched(len(prompts), lambda s: self._call(
            prompts[s], frames[s], [seed + i for i in range(s.start, s.stop)], **kw), "t2m")

    def text_variants(self, prompts: list[str], frames: list[int], repeats: int, seed: int) -> list[list[np.ndarray]]:
        """``repeats`` generations per prompt; variant v of prompt i uses seed + i * repeats + v."""
        kw = self._kwargs()
        out = []
        for i, (p, n) in enumerate(zip(prompts, frames)):
            out.append(self._batched(repeats, lambda s: self._variants(p, n, s, seed + i * repeats, kw), "mm"))
        return out

    def _variants(self, prompt: str, frames: int, s: slice, base: int, kw: dict) -> list[np.ndarray]:
        # variant v of a call is seeded seed + v: one call per contiguous block of variants
        out = self.pipe([prompt], seconds=frames / self.fps, seed=base + s.start, num_variants=s.stop - s.start, **kw)
        return [out.features[i, : int(n)] for i, n in enumerate(out.lengths)]

    def action_prompt(self, action: str) -> str:
        return self.settings.action_prompt.format(action=str(action).replace("_", " ").replace("-", " "))

    def action(self, actions: list[str], frames: list[int], seed: int) -> list[np.ndarray]:
        if self.cond == "text":  # a text model: prompt with the action's name
            return self.text([self.action_prompt(a) for a in actions], frames, seed)
        kw = self._kwargs()

        def call(s: slice) -> list[np.ndarray]:
            acts, fr = actions[s], frames[s]
            seeds = [seed + i for i in range(s.start, s.stop)]
            if self._per_row_seeds is None:
                self._per_row_seeds = _accepts_seed_list(self.pipe)
            if not self._per_row_seeds:
                res = []
                for a, n, sd in zip(acts, fr, seeds):
                    o = self.pipe([], seconds=n / self.fps, actions=[a], seed=sd, **kw)
                    res.append(o.features[0, : int(o.lengths[0])])
                return res
            o = self.pipe([], seconds=[n / self.fps for n in fr], actions=list(acts), seed=seeds, **kw)
            return [o.features[i, : int(n)] for i, n in enumerate(o.lengths)]

        return self._batched(len(actions), call, "a2m")

    def unconditional(self, frames: list[int], seed: int) -> list[np.ndarray]:
        kw = self._kwargs()
        if self.cond == "none":
            prompts = [""] * len(frames)
        else:  # the classifier-free null branch: eps = eps_null + 0 * (eps_c - eps_null)
            kw["guidance_scale"] = 0.0
            if self.cond == "action":
                acts = [self.actions[0]] * len(frames)
                return self._batched(len(frames), lambda s: self._uncond_action(acts[s], frames[s], seed, s, kw), "uncond")
            prompts = ["a person moves"] * len(frames)
        return self._batched(len(frames), lambda s: self._call(
            prompts[s], frames[s], [seed + i for i in range(s.start, s.stop)], **kw), "uncond")

    def _uncond_action(self, acts, frames, seed, s, kw):
        res = []
        for a, n, i in zip(acts, frames, range(s.start, s.stop)):
            o = self.pipe([], seconds=n / self.fps, actions=[a], seed=seed + i, **kw)
            res.append(o.features[0, : int(o.lengths[0])])
        return res

    def reconstruct(self, motions: list[np.ndarray], seed: int) -> list[np.ndarray]:
        import torch

        vae, mean, std = self.pipe.vae, np.asarray(self.pipe.mean, np.float32), np.asarray(self.pipe.std, np.float32)
        gen = torch.Generator().manual_seed(int(seed))

        def call(s: slice) -> list[np.ndarray]:
            chunk = motions[s]
            lens = [len(m) for m in chunk]
            x = np.zeros((len(chunk), max(lens), mean.shape[0]), np.float32)
            for i, m in enumerate(chunk):
                x[i, : len(m)] = (m - mean) / std
            device = next(vae.parameters()).device
            lengths = torch.tensor(lens, device=device)
            with torch.inference_mode():
                mu, logvar = vae.encode(torch.from_numpy(x).to(device), lengths)
                z = mu
                if self.settings.vae_sample:  # the draw on the CPU: the same numbers on every device
                    z = mu + torch.randn(mu.shape, generator=gen).to(device) * (0.5 * logvar).exp()
                rec = vae.decode(z, lengths).float().cpu().numpy()  # (B, T, D) normalised
            return [(rec[i, :n] * std + mean).astype(np.float32) for i, n in enumerate(lens)]

        return self._batched(len(motions), call, "vae")


def _accepts_seed_list(pipe) -> bool:
    """Whether pipe(..., seed=[...]) gives each row its own seed (read from the ``seed`` annotation)."""
    try:
        sig = inspect.signature(pipe.__call__)
        ann = str(sig.parameters["seed"].annotation) if "seed" in sig.parameters else ""
    except (TypeError, ValueError):
        ann = ""
    if "Sequence" in ann or "list" in ann:
        return True
    return False


# --------------------------------------------------------------------------------------------------
# Tasks
# --------------------------------------------------------------------------------------------------


class _Rows:
    """Per-row, per-metric lists of replication values."""

    def __init__(self):
        self.values: dict[str, dict[str, list[float]]] = {}

    def add(self, row: str, scores: dict) -> None:
        for k, v in scores.items():
            self.values.setdefault(row, {}).setdefault(k, []).append(float(v))

    def summary(self) -> dict:
        out = {}
        for row, m in self.values.items():
            out[row] = {}
            for k, vals in m.items():
                mean, ci = metrics.mean_ci(vals)
                out[row][k] = {"mean": mean, "ci": ci, "values": vals}
        return out


def _draw(clips, rng, settings: EvalSettings, frame_range, fps, *, need_action: bool = False) -> list[Pair]:
    lo, hi = frame_range
    pairs = draw_pairs(clips, rng, min_frames=lo, max_frames=hi, fps=fps)
    if need_action:
        pairs = [p for p in pairs if p.action is not None]
    if settings.max_pairs is not None and len(pairs) > settings.max_pairs:
        keep = np.sort(rng.choice(len(pairs), settings.max_pairs, replace=False))
        pairs = [pairs[i] for i in keep]
    return pairs


def _t2m_scores(motion_emb, text_emb, ref_emb, settings, rng) -> dict:
    pool = min(settings.r_pool, len(motion_emb))
    hits, mm_dist = metrics.r_precision(text_emb, motion_emb, batch_size=pool, rng=rng)
    return {"R@1": hits[0], "R@2": hits[1], "R@3": hits[2], "MM-Dist": mm_dist,
            "FID": metrics.fid(motion_emb, ref_emb),
            "Diversity": metrics.diversity(motion_emb, min(settings.diversity_times, len(motion_emb)), rng=rng)}


def evaluate(task: str, evaluator, clips: Sequence, generator: PipelineGenerator, settings: EvalSettings, *,
             model_name: str = "MLD", progress: bool = True, log=print) -> dict:
    """Run ``settings.replications`` replications of ``task``; returns the JSON-ready result."""
    from tqdm import tqdm

    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose one of {', '.join(TASKS)}")
    check_settings(settings, task)
    from mld_core.bench import OtherLoad

    started, cpu_started = time.monotonic(), time.process_time()
    other_load = OtherLoad()
    fps = generator.fps
    lo, hi = generator.frame_range
    frame_range = (max(lo, 4), min(hi, evaluator.config.max_frames))
    need_action = task == "a2m"
    action_index = {n: i for i, n in enumerate(evaluator.config.action_names)}
    if need_action:
        if not evaluator.config.num_actions:
            raise ValueError("this evaluator has no action classifier; train it on a folder with actions.json")
        known = set(generator.actions) if generator.cond == "action" else set(action_index)
        clips = [c for c in clips if getattr(c, "action", None) in action_index and c.action in known]
        if not clips:
            raise ValueError("no clip of the split has an action that both the model and the evaluator know")

    ref_pairs = _draw(clips, np.random.default_rng([settings.seed, 999_999]),
                      replace(settings, max_pairs=None), frame_range, fps, need_action=need_action)
    fewest = min_pairs(task, settings)
    if len(ref_pairs) < fewest:
        raise ValueError(f"the split has only {len(ref_pairs)} usable clips (need >= {fewest}) between "
                         f"{frame_range[0]} and {frame_range[1]} frames")
    ref_emb = evaluator.encode_motion([p.features for p in ref_pairs])
    rows = _Rows()
    text_cache: dict[str, np.ndarray] = {}

    def text_embeddings(texts: list[str]) -> np.ndarray:
        missing = [t for t in dict.fromkeys(texts) if t not in text_cache]
        if missing:
            for t, e in zip(missing, evaluator.encode_text(missing)):
                text_cache[t] = e
        return np.stack([text_cache[t] for t in texts])

    bar = tqdm(range(settings.replications), desc=f"evaluate {task}", unit="rep", disable=not progress)
    for rep in bar:
        rng = np.random.default_rng([settings.seed, rep])
        pairs = _draw(clips, rng, settings, frame_range, fps, need_action=need_action)
        real_feats = [p.features for p in pairs]
        frames = [p.length for p in pairs]
        real_emb = evaluator.encode_motion(real_feats)
        gen_seed = settings.seed * SEED_STRIDE + rep * REPLICATION_SEED_STRIDE
        if task == "t2m":
            texts = [p.text for p in pairs]
            text_emb = text_embeddings(texts)
            labelled = [i for i, p in enumerate(pairs) if p.action in action_index] if evaluator.config.num_actions else []
            labels = np.array([action_index[pairs[i].action] for i in labelled])

            def content_acc(feats) -> dict:
                # extension: the evaluator's classifier on each motion vs the content label of its source clip
                if not labelled:
                    return {}
                return {"Content-Acc": metrics.accuracy(evaluator.classify([feats[i] for i in labelled]), labels)}

            rows.add("Real", {**_t2m_scores(real_emb, text_emb, ref_emb, settings,
                                            np.random.default_rng([rep, 1])), **content_acc(real_feats)})
            gen = generator.text(texts, frames, gen_seed)
            gen_emb = evaluator.encode_motion(gen)
            scores = _t2m_scores(gen_emb, text_emb, ref_emb, settings, np.random.default_rng([rep, 1]))
            scores.update(content_acc(gen))
            if settings.mm_texts > 0 and settings.mm_repeats >= settings.mm_times:
                pick = rng.choice(len(pairs), min(settings.mm_texts, len(pairs)), replace=False)
                variants = generator.text_variants([texts[i] for i in pick], [frames[i] for i in pick],
                                                   settings.mm_repeats, gen_seed + 50_000)
                emb = np.stack([evaluator.encode_motion(v) for v in variants])  # (n_texts, repeats, E)
                scores["MultiModality"] = metrics.multimodality(emb, settings.mm_times, rng=np.random.default_rng([rep, 2]))
            rows.add(model_name, scores)
        elif task == "a2m":
            labels = np.array([action_index[p.action] for p in pairs])
            times = min(settings.a2m_diversity_times, len(pairs))

            def a2m_scores(emb, feats):
                return {"FID": metrics.fid(emb, ref_emb),
                        "Accuracy": metrics.accuracy(evaluator.classify(feats), labels),
                        "Diversity": metrics.diversity(emb, times, rng=np.random.default_rng([rep, 1])),
                        "MultiModality": metrics.action_multimodality(emb, labels, settings.a2m_mm_times,
                                                                      rng=np.random.default_rng([rep, 2]))}

            rows.add("Real", a2m_scores(real_emb, real_feats))
            gen = generator.action([p.action for p in pairs], frames, gen_seed)
            rows.add(model_name, a2m_scores(evaluator.encode_motion(gen), gen))
        elif task == "uncond":
            times = min(settings.diversity_times, len(pairs))

            def uncond_scores(emb):
                kid_mean, _ = metrics.kid(emb, ref_emb, n_subsets=settings.kid_subsets,
                                          subset_size=settings.kid_subset_size, rng=np.random.default_rng([rep, 3]))
                return {"FID": metrics.fid(emb, ref_emb), "KID": kid_mean,
                        "Diversity": metrics.diversity(emb, times, rng=np.random.default_rng([rep, 1]))}

            rows.add("Real", uncond_scores(real_emb))
            gen = generator.unconditional(frames, gen_seed)
            rows.add(model_name, uncond_scores(evaluator.encode_motion(gen)))
        else:  # vae
            from mld_core.motion.features import features_to_joints

            times = min(settings.diversity_times, len(pairs))
            rows.add("Real", {"FID": metrics.fid(real_emb, ref_emb),
                              "Diversity": metrics.diversity(real_emb, times, rng=np.random.default_rng([rep, 1]))})
            rec = generator.reconstruct(real_feats, gen_seed)
            rec_emb = evaluator.encode_motion(rec)
            scores = metrics.reconstruction_errors([np.asarray(features_to_joints(r)) for r in rec],
                                                   [np.asarray(features_to_joints(f)) for f in real_feats])
            scores.update({"FID": metrics.fid(rec_emb, ref_emb),
                           "Diversity": metrics.diversity(rec_emb, times, rng=np.random.default_rng([rep, 1]))})
            rows.add(model_name, scores)
        bar.set_postfix(pairs=len(pairs))
    bar.close()
    return {"task": task, "rows": rows.summary(), "order": ["Real", model_name], "settings": settings.to_dict(),
            "pairs_per_replication": len(pairs), "reference_pairs": len(ref_pairs),
            "frame_range": list(frame_range), "seconds": round(time.monotonic() - started, 1),
            "cpu_seconds": round(time.process_time() - cpu_started, 1), "other_cpus": other_load.cpus()}


# --------------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------------


def format_table(result: dict) -> str:
    task = result["task"]
    cols = [c for c in COLUMNS[task] if any(c[0] in result["rows"].get(r, {}) for r in result["order"])]
    header = ["Method"] + [f"{title} {ARROWS[d]}" for _, title, d in cols]
    lines = []
    for row in result["order"]:
        vals = result["rows"].get(row, {})
        cells = [row]
        for key, _, _ in cols:
            if key in vals:
                v = vals[key]
                digits = {"MPJPE": 1, "PA-MPJPE": 1, "MPJPE_global": 1, "KID": 4}.get(key, 3)
                cells.append(f"{v['mean']:.{digits}f}\u00b1{v['ci']:.{digits}f}")
            else:
                cells.append("-")
        lines.append(cells)
    widths = [max(len(r[i]) for r in [header] + lines) for i in range(len(header))]
    fmt = lambda r: "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    s = result["settings"]
    title = (f"{task} on {result.get('data', '?')} [{s['split']}], {s['replications']} replication(s), "
             f"{result['pairs_per_replication']} pairs each; mean \u00b1 95% CI")
    return "\n".join([title, fmt(header), sep] + [fmt(r) for r in lines])


def write_json(result: dict, path: str | Path) -> None:
    from mld_core.eval.evaluator import _atomic_write

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(result, indent=2) + "\n"
    _atomic_write(path, lambda tmp: Path(tmp).write_text(text))
