"""One generation request -> takes ready to key (bpy-free; runs on the worker thread).

:func:`generate` calls the pipeline and turns each generated row into a :class:`Take`: the joints, the local
rotations of the canonical skeleton (``mld_core.motion.rotations.features_to_rotations``), the provenance
that lets anyone regenerate it exactly, and its Action name. :func:`make_work` wraps it for the
:class:`jobs.JobRunner` together with the model cache.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from datetime import datetime, timezone

import numpy as np

from .dependencies import ADDON_VERSION_STRING
from .model_choice import pipe_for_request
from .naming import action_name
from .validation import GenerateRequest

PROVENANCE_PREFIX = "mld_"


@dataclass
class Take:
    prompt: str
    seed: int  # the seed this take was sampled with (request seed + variant)
    variant: int  # 0-based
    request: GenerateRequest
    joints: np.ndarray  # (T, 22, 3) metres, model axes (Y up, facing +Z)
    local_quats: np.ndarray  # (T, 22, 4) w-first, canonical skeleton, model axes
    root_positions: np.ndarray  # (T, 3)
    fps: int
    model_id: str
    guidance: float | None  # the guidance scale actually used
    steps: int
    seconds_generated: float  # wall time of the whole request (shared by its variants)
    name: str = ""
    timings: dict = field(default_factory=dict)
    contacts: np.ndarray | None = None  # (T, 4) the features' foot-contact channels (> 0.5 = contact)
    coverage: object = None  # mld_core.condition.coverage.Coverage of the prompt (None: not checked)
    badges: object = None  # mld_core.eval.quality.Badges (None: not scored)
    residuals: list | None = None  # [(constraint kind, metres, met)] for a directed take
    segments: list | None = None  # [(prompt, first frame)] of a take made from a prompt sequence
    seams: list | None = None  # [(segment, largest joint jerk m/s^3, within real motion's)] of a sequence's seams
    draw: int = 0  # which z_T of its seed (0: the first; a later one when a side or verb redraw drew it again)
    redrawn_for: str = ""  # the redraw that drew it again: "side", "verb", either + " missed", or "" (none)
    weights_use: str = ""  # what the model's weights, and so this take, may be used for (mld_core.data.terms)

    @property
    def frames(self) -> int:
        return int(self.joints.shape[0])

    @property
    def loops(self) -> bool:
        """Whether this take was made as a loop (a Loop among its request's constraints)."""
        constraints = self.request.extra.get("constraints") if isinstance(self.request.extra, dict) else None
        items = getattr(constraints, "items", None) or ()
        if not items:
            return False
        from mld_core.take_fixes.constraints import Loop

        return any(isinstance(item, Loop) for item in items)

    def provenance(self) -> dict:
        """Custom properties for the Action: everything needed to regenerate this take exactly."""
        data = {
            "prompt": self.prompt,
            "seed": int(self.seed),
            "request_seed": int(self.request.seed),
            "variant": int(self.variant),
            "variants": int(self.request.variants),
            "draw": int(self.draw),
            "steps": int(self.steps),
            "draft": bool(self.request.draft),
            "loop": self.loops,  # the last frame repeats the first (exported as a loop: scene/export_takes.py)
            "guidance": float(self.guidance) if self.guidance is not None else -1.0,
            "seconds": float(self.request.seconds),
            "frames": self.frames,
            "fps": int(self.fps),
            "model_id": self.model_id or "",
            "model_dir": self.request.model_dir or "",
            "weights_use": self.weights_use,
            "addon_version": ADDON_VERSION_STRING,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        }
        from mld_core.take_report import custom_properties

        return {**{PROVENANCE_PREFIX + k: v for k, v in data.items()},
                **custom_properties(self.coverage, self.badges, PROVENANCE_PREFIX)}

    def summary(self) -> dict:
        """A JSON-able record (batch manifests)."""
        prov = {k.removeprefix(PROVENANCE_PREFIX): v for k, v in self.provenance().items()}
        prov["name"] = self.name
        prov["generate_s"] = round(self.seconds_generated, 4)
        from mld_core.take_report import take_record

        prov.update(take_record(self.coverage, self.badges))
        if self.residuals:
            prov["constraints"] = [{"kind": k, "residual_cm": round(r * 100, 2), "met": bool(m)}
                                   for k, r, m in self.residuals]
        if self.seams:
            from mld_core.take_report import seam_records

            prov["seams"] = seam_records(self.seams)
        return prov


@dataclass
class GenerationResult:
    takes: list
    request: GenerateRequest
    load_s: float = 0.0
    generate_s: float = 0.0
    pose_s: float = 0.0
    planned: tuple | None = None  # (KeyPlan, [keying.TakeKeys]): keys computed here for request.extra["key_plan"]

    @property
    def total_s(self) -> float:
        return self.load_s + self.generate_s + self.pose_s


def rotations_from_features(features: np.ndarray):
    """(local quaternions (T, 22, 4), root positions (T, 3)) of the canonical skeleton."""
    from mld_core.motion.rotations import features_to_rotations

    quats, root = features_to_rotations(np.asarray(features, np.float32))
    return np.asarray(quats, np.float64), np.asarray(root, np.float64)


def generate(pipe, request: GenerateRequest, callback=None, check_cancel=None) -> GenerationResult:
    """Run ``pipe`` for one request; one :class:`Take` per variant, best first (pipeline ``rank=True``), each with
    the prompt's coverage and its badges."""
    start = time.perf_counter()
    guidance = request.guidance
    coverage = pipe.coverage([request.prompt])[0] if hasattr(pipe, "coverage") else None
    constraints, sequence = request.extra.get("constraints"), request.extra.get("sequence")
    steps = None if request.draft else request.steps  # a Draft runs its own few steps
    options = {"draft": True} if request.draft else {}  # (pipelines without a Draft mode take no draft argument)
    for name in ("side_redraws", "verb_redraws"):  # the batch's --side-redraws, --verb-redraws (else the model's)
        if request.extra.get(name) is not None:
            options[name] = request.extra[name]
    if sequence:  # one motion from prompt segments (a batch job)
        out = pipe.sequence(sequence, seed=request.seed, num_inference_steps=steps, guidance_scale=guidance,
                            **options)
    else:
        out = pipe([request.prompt], seconds=request.seconds, num_inference_steps=steps,
                   guidance_scale=guidance, seed=request.seed, num_variants=request.variants, callback=callback,
                   rank=request.extra.get("rank", True), constraints=constraints or None, **options)
    generated = time.perf_counter() - start
    if check_cancel is not None:
        check_cancel()
    used_steps = request.steps
    if request.draft:
        used_steps = getattr(getattr(getattr(pipe, "config", None), "draft", None), "num_inference_steps", 0)
    used_guidance = guidance
    if used_guidance is None:
        default = getattr(pipe, "default_guidance", None)
        used_guidance = default(request.draft) if default is not None else \
            getattr(getattr(pipe, "config", None), "guidance_scale", None)
    fps = int(getattr(out, "fps", 20) or 20)
    model_id = getattr(out, "model_id", "") or getattr(pipe, "model_id", "") or ""
    weights_use = weights_use_of(pipe)
    t0 = time.perf_counter()
    takes = []
    for row in range(len(out.seeds)):
        n = int(out.lengths[row])
        joints = np.asarray(out.joints[row, :n], np.float64)
        quats, root = rotations_from_features(out.features[row, :n])
        if quats.shape[0] != n:
            raise RuntimeError(f"rotations have {quats.shape[0]} frames for {n} generated frames")
        take = Take(
            prompt=request.prompt,
            seed=int(out.seeds[row]),
            variant=int(out.seeds[row]) - int(request.seed),
            request=request,
            joints=joints,
            local_quats=quats,
            root_positions=root,
            fps=fps,
            model_id=model_id,
            guidance=used_guidance,
            steps=used_steps,
            seconds_generated=generated,
            timings=dict(getattr(out, "timings", {}) or {}),
            contacts=np.asarray(out.features[row, :n, -4:], np.float64),
            coverage=coverage,
            badges=out.badges[row] if getattr(out, "badges", None) is not None else None,
            residuals=out.residuals[row] if getattr(out, "residuals", None) else None,
            segments=list(zip([p for p, _ in sequence], out.timings["segments"])) if sequence else None,
            seams=out.seams[row] if getattr(out, "seams", None) else None,
            draw=int(out.draws[row]) if getattr(out, "draws", None) else 0,
            redrawn_for=out.redrawn_for[row] if getattr(out, "redrawn_for", None) else "",
            weights_use=weights_use,
        )
        take.name = action_name(request.prompt, request.seed, take.variant, request.variants)
        takes.append(take)
    return GenerationResult(takes, request, generate_s=generated, pose_s=time.perf_counter() - t0)


def weights_use_of(pipe) -> str:
    """What the weights of the model that made a take may be used for ("" for a stand-in without a config)."""
    from mld_core.data import terms

    config = getattr(pipe, "config", None)
    return terms.use_label(terms.of_model(config)) if hasattr(config, "model_id") else ""


def make_work(cache):
    """The job runner's work function: load (cached) -> generate with progress + cancel -> takes."""

    def work(job):
        request: GenerateRequest = job.request
        job.stage = "loading model"
        loads_before = cache.loads
        pipe = pipe_for_request(cache, request)
        load_s = cache.load_seconds if cache.loads != loads_before else 0.0
        job.check_cancel()
        min_s, max_s = getattr(pipe, "min_seconds", None), getattr(pipe, "max_seconds", None)
        if min_s is not None and max_s is not None and not (min_s - 1e-6 <= request.seconds <= max_s + 1e-6):
            raise ValueError(f"This model makes {min_s:g} to {max_s:g} seconds of motion; got {request.seconds:g}")
        job.stage = "denoising"
        result = generate(pipe, request, callback=job.step, check_cancel=job.check_cancel)
        result.load_s = load_s
        job.stage = "posing"
        plan = request.extra.get("key_plan")
        if plan is not None:  # the keys too, off the main thread (Live Preview: only writing them is left there)
            from mld_core.rig.keying import plan_takes

            result.planned = (plan, plan_takes(result.takes, plan))
        return result

    return work
