"""``python -m mld_core bench``: average inference time per prompt (AITS) and FLOPs, MLD vs raw-motion diffusion.

AITS as in the MLD paper: the time to turn one prompt into motion features, i.e. text encoding + the
reverse diffusion + decoding (for MLD the VAE decoder; the raw baseline has nothing to decode), averaged
over prompts, at batch 1 and batch 32.

The raw-motion baseline (``--baseline raw``) is MDM-style: the same denoiser (same transformer width,
depth, skips, condition tokens and classifier-free guidance) run directly on the (T, 263) frames instead
of MLD's few latent tokens, sampled with 1000 DDPM steps (as MDM) and with 50 DDIM steps. Its weights are
UNTRAINED (random): the numbers are for speed and FLOPs only, not motion quality. The 1000-step runs can be
timed on fewer prompts (batch 1) or on a prefix of the steps and extrapolated per step (batch 32); the
output says which. FLOPs are counted with ``torch.utils.flop_counter`` for one sample (guidance included).
"""

from __future__ import annotations

import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

PROMPTS = (
    "a person walks forward",
    "a person runs in a circle",
    "someone waves with the right hand",
    "a person raises both hands above the head",
    "a man walks backwards slowly",
    "a person turns left while walking",
    "a person jumps up and down",
    "someone bows politely",
    "a person kicks with the right leg",
    "a woman dances happily",
    "a person sprints forward",
    "a person walks like a tired old man",
    "someone punches twice with the left fist",
    "a person raises the left hand and lowers it",
    "a person turns right and walks away",
    "a person walks proudly with big steps",
    "someone swings an imaginary sword down",
    "a person waves goodbye with both hands",
    "a person walks forward and then stops",
    "someone points to the right",
    "a person crouches and stands up",
    "a person walks in a zigzag",
    "someone calls out with hands around the mouth",
    "a person steps to the side",
    "a person strolls casually",
    "someone runs and then slows to a walk",
    "a person sneaks forward quietly",
    "a person stretches both arms out",
    "someone walks angrily",
    "a person does a spinning kick",
    "a person raises the right hand to answer",
    "a person walks forward, turns around and comes back",
)


def _prompts(n: int) -> list[str]:
    return [PROMPTS[i % len(PROMPTS)] for i in range(n)]


# --------------------------------------------------------------------------------------------------
# MLD: timing the pipeline
# --------------------------------------------------------------------------------------------------


def time_pipeline(pipe, prompts: Sequence[str], *, seconds: float = 4.0, batch_size: int = 1,
                  num_inference_steps: int | None = None, guidance_scale: float | None = None,
                  warmup: int = 1, progress: bool = False, draft: bool = False) -> dict:
    """AITS of ``pipe`` over ``prompts`` in batches of ``batch_size``.

    Returns {"aits_s": text + diffusion + decoding per prompt (from the pipeline's timings, or wall time
    when it reports none), "wall_aits_s": the whole call per prompt (including joint recovery; one draw per
    prompt, no side redraws), "parts":
    per-prompt seconds of each stage, "prompts": n, "batch_size"}. ``warmup`` untimed calls come first.
    """
    from tqdm import tqdm

    prompts = list(prompts)
    if not prompts:
        raise ValueError("no prompts to time")
    kw = {"side_redraws": 0, "verb_redraws": 0}  # one sample per prompt (AITS): no take is drawn again
    if num_inference_steps is not None:
        kw["num_inference_steps"] = num_inference_steps
    if guidance_scale is not None:
        kw["guidance_scale"] = guidance_scale
    if draft:
        kw["draft"] = True
    batches = [prompts[i : i + batch_size] for i in range(0, len(prompts), batch_size)]
    for _ in range(warmup):
        pipe(batches[0], seconds=seconds, seed=0, **kw)
    if hasattr(pipe, "clear_text_cache"):  # every prompt timed cold: its text is encoded
        pipe.clear_text_cache()
    parts = {"condition_s": 0.0, "diffusion_s": 0.0, "decode_s": 0.0}
    timed, wall = 0.0, 0.0
    for k, batch in enumerate(tqdm(batches, desc=f"MLD batch {batch_size}", leave=False, disable=not progress)):
        t0 = time.perf_counter()
        out = pipe(batch, seconds=seconds, seed=k, **kw)
        dt = time.perf_counter() - t0
        wall += dt
        timings = getattr(out, "timings", None) or {}
        if all(p in timings for p in parts):
            for p in parts:
                parts[p] += timings[p]
            timed += sum(timings[p] for p in parts)
        else:
            timed += dt
    n = len(prompts)
    return {"aits_s": timed / n, "wall_aits_s": wall / n, "parts": {p: v / n for p, v in parts.items()},
            "prompts": n, "batch_size": batch_size}


# --------------------------------------------------------------------------------------------------
# The raw-motion baseline
# --------------------------------------------------------------------------------------------------


class RawMotionBaseline:
    """MLD's denoiser architecture over the motion frames themselves: T tokens of ``feature_dim``.

    Built from the pipeline's denoiser config with latent_tokens = T frames and latent_dim = 263, so the
    width, depth, skips, condition path and guidance are the same as MLD's; only the sequence differs.
    Random (untrained) weights, seeded.
    """

    def __init__(self, pipe, frames: int, seed: int = 0):
        from mld_core.models.denoiser import LatentDenoiser

        self.pipe, self.frames = pipe, int(frames)
        den_cfg = pipe.denoiser.config
        self.feature_dim = int(pipe.config.vae.feature_dim)
        cfg = replace(den_cfg, latent_tokens=self.frames, latent_dim=self.feature_dim,
                      max_frames=max(den_cfg.max_frames, self.frames))
        torch.manual_seed(seed)
        # The same inference path as the pipeline's denoiser: its precision, prepacked weights on a CPU.
        self.dtype = next(pipe.denoiser.parameters()).dtype
        self.device = getattr(pipe, "device", torch.device("cpu"))
        self.model = LatentDenoiser(cfg).eval().to(self.device, self.dtype)
        self.model.transformer.pack_for_cpu_inference()  # no-op off the CPU
        self.config = cfg

    @property
    def cond(self) -> str:
        return self.config.cond

    def condition(self, prompts: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """(cond, null) tokens (B, C, d): text encoding with the pipeline's frozen text encoder."""
        B = len(prompts)
        if self.cond == "text":
            text = self.pipe.text_encoder(list(prompts))
            text = type(text)(**{k: v.to(self.device) for k, v in vars(text).items()})
            return self.model.condition_tokens(B, text=text), self.model.null_tokens(B)
        if self.cond == "action":
            actions = torch.zeros(B, dtype=torch.long, device=self.device)
            return self.model.condition_tokens(B, actions=actions), self.model.null_tokens(B)
        return self.model.null_tokens(B), self.model.null_tokens(B)

    def guidance(self, guidance_scale: float | None) -> float:
        return float(self.pipe.config.guidance_scale if guidance_scale is None else guidance_scale)

    @torch.inference_mode()
    def sample(self, prompts: list[str], *, scheduler: str = "ddim", steps: int = 50,
               guidance_scale: float | None = None, max_steps: int | None = None, seed: int = 0) -> dict:
        """Generate (B, T, 263) features; with ``max_steps`` stop early (for per-step timing).

        Returns {"features", "condition_s", "diffusion_s", "steps_run", "steps"}.
        """
        from mld_core.schedulers import DDIMScheduler, DDPMScheduler

        B, T = len(prompts), self.frames
        s = self.guidance(guidance_scale)
        t0 = time.perf_counter()
        cond, null = self.condition(prompts)
        t_cond = time.perf_counter() - t0
        sched = DDIMScheduler(self.pipe.config.scheduler) if scheduler == "ddim" else DDPMScheduler(self.pipe.config.scheduler)
        sched.set_timesteps(steps)
        gen = torch.Generator().manual_seed(seed)
        x = torch.randn(B, T, self.feature_dim, generator=gen).to(self.device)  # (B, T, 263) normalised frames
        use_guidance = s != 1.0 and self.cond != "none"
        both = (torch.cat([null, cond]) if use_guidance else cond).to(self.dtype)
        lengths = torch.full((B * (2 if use_guidance else 1),), T, device=self.device)
        t0 = time.perf_counter()
        run = 0
        for t in sched.timesteps:
            if max_steps is not None and run >= max_steps:
                break
            x_in = torch.cat([x, x]) if use_guidance else x
            t_batch = torch.full((x_in.shape[0],), int(t), device=self.device)
            eps = self.model(x_in.to(self.dtype), t_batch, both, lengths).float()
            if use_guidance:
                e_null, e_cond = eps.chunk(2)
                eps = e_null + s * (e_cond - e_null)
            out = sched.step(eps, t, x, generator=gen) if scheduler == "ddpm" and self.device.type == "cpu" else \
                sched.step(eps, t, x)  # (a CPU generator cannot draw a GPU's noise)
            x = out[0] if isinstance(out, tuple) else out
            run += 1
        t_diff = time.perf_counter() - t0
        feats = x.float().cpu().numpy() * self.pipe.std + self.pipe.mean
        return {"features": feats.astype(np.float32), "condition_s": t_cond, "diffusion_s": t_diff,
                "steps_run": run, "steps": len(sched.timesteps)}


def time_raw(baseline: RawMotionBaseline, prompts: Sequence[str], *, batch_size: int, scheduler: str, steps: int,
             guidance_scale: float | None = None, max_steps: int | None = None, progress: bool = False) -> dict:
    """AITS of the raw baseline; with ``max_steps`` < steps the diffusion time is extrapolated per step."""
    from tqdm import tqdm

    prompts = list(prompts)
    batches = [prompts[i : i + batch_size] for i in range(0, len(prompts), batch_size)]
    baseline.sample(batches[0], scheduler=scheduler, steps=steps, guidance_scale=guidance_scale, max_steps=2)  # warm-up
    cond_s = diff_s = 0.0
    run = total = 0
    for k, batch in enumerate(tqdm(batches, desc=f"raw {scheduler}-{steps} batch {batch_size}", leave=False,
                                   disable=not progress)):
        r = baseline.sample(batch, scheduler=scheduler, steps=steps, guidance_scale=guidance_scale,
                            max_steps=max_steps, seed=k)
        cond_s += r["condition_s"]
        diff_s += r["diffusion_s"] * r["steps"] / max(1, r["steps_run"])  # per-step extrapolation
        run, total = r["steps_run"], r["steps"]
    n = len(prompts)
    return {"aits_s": (cond_s + diff_s) / n, "parts": {"condition_s": cond_s / n, "diffusion_s": diff_s / n},
            "prompts": n, "batch_size": batch_size, "steps_timed": run, "steps": total,
            "extrapolated": run < total}


# --------------------------------------------------------------------------------------------------
# FLOPs
# --------------------------------------------------------------------------------------------------


def _count_flops(fn) -> int:
    """FLOPs of fn() with every module in train mode (the fused eval fast path hides its matmuls)."""
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    with torch.enable_grad(), counter:  # autograd on: FlopCounterMode's module tracking expects it
        fn()
    return int(counter.get_total_flops())


class _TrainMode:
    """Temporarily put modules in train mode (for FLOP counting only); restores each module's mode."""

    def __init__(self, *modules):
        self.modules = [m for m in modules if isinstance(m, torch.nn.Module)]

    def __enter__(self):
        self.saved = [(sub, sub.training) for m in self.modules for sub in m.modules()]
        self.packed = [(sub, sub._packed, getattr(sub, "_packed_projections", [])) for sub, _ in self.saved
                       if isinstance(getattr(sub, "_packed", None), dict)]
        # the text encoder's layers keep prepacked weights too (oneDNN ops the counter does not see): plain ops here
        self.text_packed = [(sub, sub.packed) for sub, _ in self.saved if isinstance(getattr(sub, "packed", None), dict)]
        for sub, _ in self.text_packed:
            sub.packed = {}
        for m in self.modules:
            m.train()

    def __exit__(self, *exc):
        for sub, mode in self.saved:
            sub.training = mode
        for sub, packed, projections in self.packed:  # train() drops prepacked weights; they did not change
            sub._packed, sub._packed_projections = packed, projections
        for sub, packed in self.text_packed:
            sub.packed = packed


def mld_flops(pipe, prompt: str, frames: int, steps: int, guidance_scale: float | None = None,
              draft: bool = False) -> dict:
    """FLOPs for one sample: condition (text encoder + condition tokens), steps x denoiser, VAE decode. ``draft``:
    the Draft denoiser, one pass per step (the guidance scale is its input)."""
    den = pipe.draft_denoiser if draft else pipe.denoiser
    s = float(pipe.config.guidance_scale if guidance_scale is None else guidance_scale)
    use_guidance = s != 1.0 and den.config.cond != "none" and not draft
    scale = {"guidance": torch.full((1,), s)} if draft else {}
    n, d = pipe.config.vae.latent_tokens, pipe.config.vae.latent_dim
    lengths = torch.tensor([frames])
    encoder = pipe.draft_text_encoder if draft and pipe.draft_text_encoder is not None else pipe.text_encoder
    with _TrainMode(den, pipe.vae, encoder):
        holder = {}

        def condition():
            if den.config.cond == "text":
                text = encoder([prompt])
                holder["cond"] = den.condition_tokens(1, text=text)
            elif den.config.cond == "action":
                holder["cond"] = den.condition_tokens(1, actions=torch.zeros(1, dtype=torch.long))
            else:
                holder["cond"] = den.null_tokens(1)
            holder["null"] = den.null_tokens(1)

        f_cond = _count_flops(condition)
        cond = torch.cat([holder["null"], holder["cond"]]) if use_guidance else holder["cond"]
        rows = 2 if use_guidance else 1
        dtype = next(den.parameters()).dtype  # fp32, or bf16 with --precision bf16
        z = torch.randn(rows, n, d, dtype=dtype)
        f_step = _count_flops(lambda: den(z, torch.full((rows,), 500), cond.to(dtype), lengths.repeat(rows), **scale))
        f_dec = _count_flops(lambda: pipe.vae.decode(torch.randn(1, n, d), lengths))
    out = {"condition": f_cond, "per_step": f_step, "steps": steps, "decode": f_dec,
           "total": f_cond + steps * f_step + f_dec}
    teacher_steps = min(pipe.config.draft.teacher_steps, steps - 1) if draft else 0
    if teacher_steps:  # the Draft's last steps are guided steps of the model's own denoiser
        teacher = mld_flops(pipe, prompt, frames, teacher_steps, s)
        with _TrainMode(pipe.text_encoder):
            f_text = _count_flops(lambda: pipe.text_encoder([prompt])) if den.config.cond == "text" else 0
        out["condition"] += teacher["condition"] - f_text  # its condition tokens; the text is encoded once
        out.update(teacher_steps=teacher_steps, teacher_per_step=teacher["per_step"])
        out["total"] = out["condition"] + (steps - teacher_steps) * f_step + teacher_steps * teacher["per_step"] + f_dec
    return out


def raw_flops(baseline: RawMotionBaseline, prompt: str, steps: int, guidance_scale: float | None = None) -> dict:
    s = baseline.guidance(guidance_scale)
    use_guidance = s != 1.0 and baseline.cond != "none"
    with _TrainMode(baseline.model, baseline.pipe.text_encoder):
        holder = {}
        f_cond = _count_flops(lambda: holder.update(zip(("cond", "null"), baseline.condition([prompt]))))
        cond = torch.cat([holder["null"], holder["cond"]]) if use_guidance else holder["cond"]
        rows = 2 if use_guidance else 1
        x = torch.randn(rows, baseline.frames, baseline.feature_dim, dtype=baseline.dtype)
        f_step = _count_flops(lambda: baseline.model(x, torch.full((rows,), 500), cond.to(baseline.dtype),
                                                     torch.full((rows,), baseline.frames)))
    return {"condition": f_cond, "per_step": f_step, "steps": steps, "decode": 0, "total": f_cond + steps * f_step}


# --------------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------------


def run_bench(model=None, *, baseline: str | None = None, prompts: int = 32, seconds: float = 4.0,
              steps: int | None = None, guidance_scale: float | None = None, ddpm_prompts: int = 2,
              ddpm_timed_steps: int = 20, raw_ddim_prompts: int = 8, threads: int | None = None,
              progress: bool = True, log=print, precision: str = "fp32", device: str = "cpu") -> dict:
    """Time MLD (and the raw baseline) on the same prompts; returns the JSON-ready result."""
    from mld_core.pipeline import MLDPipeline

    if threads:
        torch.set_num_threads(threads)
    pipe = model if hasattr(model, "denoiser") else MLDPipeline.from_pretrained(model, precision=precision,
                                                                                device=device)
    if pipe.denoiser is None:
        raise ValueError("this model folder has only a VAE; the benchmark needs a denoiser")
    frames = pipe.frames_for(seconds)
    steps = int(steps or pipe.config.num_inference_steps)
    guidance = float(pipe.config.guidance_scale if guidance_scale is None else guidance_scale)
    texts = _prompts(prompts)
    cond = pipe.denoiser.config.cond
    result = {"model_id": pipe.model_id, "seconds": seconds, "frames": frames, "prompts": prompts,
              "cpus": os.cpu_count(),
              "threads": torch.get_num_threads(), "torch": torch.__version__, "machine": platform.machine(),
              "device": _device_name(getattr(pipe, "device", torch.device("cpu"))),
              "processor": platform.processor() or platform.machine(), "guidance_scale": guidance,
              "precision": getattr(pipe, "precision", "fp32"), "draft_precision": getattr(pipe, "draft_precision", ""),
              "draft_text_layers": getattr(pipe, "draft_text_layers", None),
              "methods": []}

    mld_kw = {"num_inference_steps": steps, "guidance_scale": guidance_scale}
    log(f"timing MLD ({pipe.model_id}) on {prompts} prompts, {seconds:g} s ({frames} frames), "
        f"{torch.get_num_threads()} thread(s)")
    if cond == "action":
        action = pipe.config.actions[0]

        class _ActionPipe:  # same call shape: the prompt list only sets the batch size
            def __init__(self, p):
                self.p = p

            def __call__(self, batch, **kw):
                return self.p([], actions=[action] * len(batch), **kw)

        timed_pipe = _ActionPipe(pipe)
    else:
        timed_pipe = pipe
    other_load = OtherLoad()
    mld = {"name": "MLD", "scheduler": f"DDIM-{steps}", "steps": steps, "trained": True}
    mld["batch1"] = time_pipeline(timed_pipe, texts, seconds=seconds, batch_size=1, progress=progress, **mld_kw)
    mld["batch32"] = time_pipeline(timed_pipe, texts, seconds=seconds, batch_size=32, progress=progress, **mld_kw)
    mld["flops"] = mld_flops(pipe, texts[0], frames, steps, guidance_scale)
    result["methods"].append(mld)
    if getattr(pipe, "draft_denoiser", None) is not None and cond == "text":
        d_steps = pipe.config.draft.num_inference_steps
        t_steps = min(pipe.config.draft.teacher_steps, d_steps - 1)
        sampler = f"LCM-{d_steps - t_steps}" + (f" + DDIM-{t_steps}" if t_steps else "")
        draft = {"name": "MLD Draft", "scheduler": sampler, "steps": d_steps, "trained": True}
        kw = {"guidance_scale": guidance_scale, "draft": True}
        draft["batch1"] = time_pipeline(pipe, texts, seconds=seconds, batch_size=1, progress=progress, **kw)
        draft["batch32"] = time_pipeline(pipe, texts, seconds=seconds, batch_size=32, progress=progress, **kw)
        draft["flops"] = mld_flops(pipe, texts[0], frames, d_steps, guidance_scale, draft=True)
        result["methods"].append(draft)

    if baseline == "raw":
        raw = RawMotionBaseline(pipe, frames)
        log("timing the raw-motion baseline (untrained weights: speed and FLOPs only)")
        ddim = {"name": "raw-motion DDIM", "scheduler": "DDIM-50", "steps": 50, "trained": False}
        ddim["batch1"] = time_raw(raw, texts[: max(1, min(raw_ddim_prompts, prompts))], batch_size=1,
                                  scheduler="ddim", steps=50, guidance_scale=guidance_scale, progress=progress)
        ddim["batch32"] = time_raw(raw, texts[: max(1, min(32, prompts))], batch_size=32, scheduler="ddim",
                                   steps=50, guidance_scale=guidance_scale, progress=progress)
        ddim["flops"] = raw_flops(raw, texts[0], 50, guidance_scale)
        ddpm = {"name": "raw-motion DDPM (MDM-style)", "scheduler": "DDPM-1000", "steps": 1000, "trained": False}
        ddpm["batch1"] = time_raw(raw, texts[: max(1, min(ddpm_prompts, prompts))], batch_size=1, scheduler="ddpm",
                                  steps=1000, guidance_scale=guidance_scale, progress=progress)
        ddpm["batch32"] = time_raw(raw, texts[: max(1, min(32, prompts))], batch_size=32, scheduler="ddpm",
                                   steps=1000, guidance_scale=guidance_scale, max_steps=ddpm_timed_steps,
                                   progress=progress)
        ddpm["flops"] = raw_flops(raw, texts[0], 1000, guidance_scale)
        result["methods"] += [ddim, ddpm]
    result["other_cpus"] = other_load.cpus()
    base1, base32 = mld["batch1"]["aits_s"], mld["batch32"]["aits_s"]
    for m in result["methods"]:
        m["ratio_batch1"] = m["batch1"]["aits_s"] / base1
        m["ratio_batch32"] = m["batch32"]["aits_s"] / base32
        m["flops_ratio"] = m["flops"]["total"] / mld["flops"]["total"]
    return result


class OtherLoad:
    """How many CPUs other processes kept busy while a measurement ran (Linux /proc/stat; else None).

    busy CPU time of the whole machine minus this process's own CPU time, divided by the wall time.
    """

    def __init__(self):
        self.start = self._snapshot()

    @staticmethod
    def _snapshot():
        try:
            with open("/proc/stat") as fh:
                fields = [int(x) for x in fh.readline().split()[1:]]
            tick = os.sysconf("SC_CLK_TCK")
        except (OSError, ValueError, AttributeError):
            return None
        idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
        busy = (sum(fields[:8]) - idle) / tick  # user..steal, without guest (already in user)
        own = time.process_time()
        return busy, own, time.monotonic()

    def cpus(self) -> float | None:
        end = self._snapshot()
        if self.start is None or end is None or end[2] - self.start[2] <= 0:
            return None
        others = (end[0] - self.start[0]) - (end[1] - self.start[1])
        return round(max(0.0, others / (end[2] - self.start[2])), 2)


def busy_note(other_cpus: float | None, cpus: int | None) -> str | None:
    """A warning when other processes used more than a quarter of the machine during a measurement."""
    if other_cpus is None or not cpus or other_cpus <= 0.25 * cpus:
        return None
    return (f"WARNING: other processes kept {other_cpus:.1f} of the {cpus} CPUs busy during this run: "
            "times include waiting for them; re-run on an idle machine for representative timings.")


def _gflops(flops: float) -> str:
    g = flops / 1e9
    return f"{g:.2f}" if g >= 0.1 else f"{g:.3g}"


def _ratio(x: float) -> str:
    return f"{x:.2f}" if x < 1 else f"{x:.1f}"


def format_bench(result: dict) -> str:
    head = ["method", "sampler", "AITS b1 (s)", "AITS b32 (s)", "x MLD b1", "x MLD b32", "GFLOPs/sample",
            "x MLD FLOPs"]
    rows = []
    notes = []
    for m in result["methods"]:
        name = m["name"] + ("" if m["trained"] else " [untrained]")
        b1, b32 = m["batch1"], m["batch32"]
        c1 = f"{b1['aits_s']:.3f}" + ("*" if b1.get("prompts", 0) < result["prompts"] else "")
        c32 = f"{b32['aits_s']:.3f}" + ("\u2020" if b32.get("extrapolated") else "")
        if b1.get("prompts", 0) < result["prompts"]:
            notes.append(f"* {m['name']} batch 1: timed on {b1['prompts']} of the {result['prompts']} prompts"
                         + (" (all steps run)" if not b1.get("extrapolated") else ""))
        if b32.get("extrapolated"):
            notes.append(f"\u2020 {m['name']} batch 32: {b32['steps_timed']} of {b32['steps']} steps timed, "
                         f"diffusion time extrapolated per step")
        rows.append([name, m["scheduler"], c1, c32, _ratio(m["ratio_batch1"]), _ratio(m["ratio_batch32"]),
                     _gflops(m['flops']['total']), _ratio(m["flops_ratio"])])
    widths = [max(len(str(r[i])) for r in [head] + rows) for i in range(len(head))]
    fmt = lambda r: "| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    lines = [f"AITS = text encoding + diffusion + decoding per prompt; {result['frames']} frames "
             f"({result['seconds']:g} s), guidance {result['guidance_scale']:g}, {result['prompts']} prompts, "
             f"{result['threads']} CPU thread(s), {result.get('precision', 'fp32')} denoiser, torch {result['torch']}"
             + (f", on {result['device']}" if result.get("device", "cpu") != "cpu" else ""),
             fmt(head), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [fmt(r) for r in rows]
    if any(not m["trained"] for m in result["methods"]):
        lines.append("The raw-motion baseline has UNTRAINED (random) weights: its rows measure speed and FLOPs only. "
                     "It is MLD's denoiser (same width, depth, skips, conditioning, guidance) run on the "
                     f"{result['frames']} x 263 frames instead of the latent tokens.")
    note = busy_note(result.get("other_cpus"), result.get("cpus"))
    return "\n".join(lines + notes + ([note] if note else []))


def _device_name(device: torch.device) -> str:
    """The device timed, in words: the CPU, or the GPU's name."""
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    return device.type


def register(groups) -> None:
    from mld_core.cli import DEVICE_HELP, PRECISION_CHOICES, PRECISION_HELP

    p = groups["root"].add_parser(
        "bench", help="average inference time per prompt (AITS) and FLOPs; --baseline raw adds raw-motion diffusion",
        description=__doc__.split("\n\n")[1] if __doc__ else None)
    p.add_argument("--model", default=None, help="model folder or bundled model's name (default: the bundled default)")
    p.add_argument("--baseline", choices=["raw"], default=None,
                   help="also time a raw-motion diffusion baseline (MDM-style DDPM-1000 and DDIM-50)")
    p.add_argument("--prompts", type=int, default=32, help="number of prompts timed (default 32)")
    p.add_argument("--seconds", type=float, default=4.0, help="motion length (default 4 s)")
    p.add_argument("--steps", type=int, default=None, help="MLD DDIM steps (default: the model's)")
    p.add_argument("--guidance", type=float, default=None, help="guidance scale (default: the model's)")
    p.add_argument("--ddpm-prompts", type=int, default=2,
                   help="prompts for the full 1000-step raw DDPM at batch 1 (default 2)")
    p.add_argument("--ddpm-timed-steps", type=int, default=20,
                   help="raw DDPM at batch 32: steps timed before extrapolating to 1000 (default 20)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--precision", choices=PRECISION_CHOICES, default="fp32", help=PRECISION_HELP)
    p.add_argument("--device", default="cpu", help=f"where the model runs: {DEVICE_HELP}")
    p.add_argument("--json", default=None, help="also write the numbers here")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run_cli)


def _check_flags(args) -> None:
    """Every number in its range and --json writable, before the model loads (the timings are not lost to a bad
    output path)."""
    from mld_core import inputs

    for flag, hi in (("prompts", 10_000), ("ddpm_prompts", 10_000), ("ddpm_timed_steps", 1000)):
        inputs.int_in_range(getattr(args, flag), f"--{flag.replace('_', '-')}", 1, hi)
    inputs.check_seconds(args.seconds, inputs.model_limits(args.model), "--seconds")
    if args.steps is not None:
        inputs.check_steps(args.steps, "--steps")
    args.guidance = inputs.check_guidance(args.guidance, "--guidance")  # 0: the model's default (None)
    if args.json:
        inputs.check_outputs({"--json": Path(args.json)}, overwrite=True)


def _run_cli(args) -> int:
    from mld_core.checkpoint import CheckpointError
    from mld_core.cli import UsageError

    _check_flags(args)
    try:
        result = run_bench(args.model, baseline=args.baseline, prompts=args.prompts, seconds=args.seconds,
                           steps=args.steps, guidance_scale=args.guidance, ddpm_prompts=args.ddpm_prompts,
                           ddpm_timed_steps=args.ddpm_timed_steps, threads=args.threads,
                           progress=not args.no_progress, precision=args.precision, device=args.device)
    except (CheckpointError, FileNotFoundError, ValueError) as exc:
        raise UsageError(str(exc)) from None
    print(format_bench(result))
    if args.json:
        from mld_core.eval.evaluator import _atomic_write

        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps(result, indent=2) + "\n"
        _atomic_write(path, lambda tmp: Path(tmp).write_text(text))
        print(f"wrote {path}")
    return 0
