"""Latent sampling: z_T ~ N(0, I) per row, then denoising one timestep at a time to z_0.

- Final (:class:`FinalSampler`): DDIM steps of the denoiser with classifier-free guidance,
  eps = eps(z_t, t, null) + s * (eps(z_t, t, c) - eps(z_t, t, null)); on the rows whose prompt names one of a verb
  denoiser's labels a (:class:`VerbGuidance`), plus s_a * (eps_a(z_t, t, a) - eps_a(z_t, t, null)), the two
  conditions composed as in Liu et al., "Compositional Visual Generation with Composable Diffusion Models" (2022).
- Draft (:class:`DraftSampler`): consistency steps of the distilled denoiser, which takes s as an input (one pass per
  step), re-noised between steps; its last ``teacher_steps`` are guided DDIM steps of the denoiser it was distilled
  from (its teacher), which finish the sample.

A sampler only steps: the pipeline runs the loop over its ``timesteps`` (progress and cancelling live there).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mld_core.models.denoiser import LatentDenoiser


@dataclass
class Conditions:
    """The condition tokens c and the null tokens (B, C, d) of the denoiser that samples, and a Draft's teacher's own
    (None: no teacher steps)."""

    cond: torch.Tensor
    null: torch.Tensor
    teacher_cond: torch.Tensor | None = None
    teacher_null: torch.Tensor | None = None


def initial_latents(seeds: list, draw: int, tokens: int, dim: int,
                    device: torch.device) -> tuple[torch.Tensor, list[torch.Generator]]:
    """z_T (B, n, d) drawn per row from its own generator, seeded with the row's seed, so that a batch equals single
    runs; draw k skips each generator's first k draws. The generators are returned too (a Draft re-noises from them)."""
    generators = [torch.Generator().manual_seed(sd) for sd in seeds]
    for g in generators:
        for _ in range(draw):
            torch.randn(tokens, dim, generator=g)
    z = torch.stack([torch.randn(tokens, dim, generator=g) for g in generators]).to(device)  # (B, n, d)
    return z, generators


def guided_eps(denoiser: LatentDenoiser, z: torch.Tensor, t, cond: torch.Tensor, null: torch.Tensor,
               lengths: torch.Tensor, scale: float | None) -> torch.Tensor:
    """The denoiser's noise prediction at z_t (B, n, d) in float32: with ``scale``, classifier-free guidance
    eps_null + s * (eps_c - eps_null) from one pass over the 2B rows [null; cond]; without, the condition alone."""
    dtype = denoiser.latent_in.weight.dtype
    if scale is None:
        t_batch = torch.full((len(z),), int(t), device=z.device)
        return denoiser(z.to(dtype), t_batch, cond.to(dtype), lengths).float()
    eps_null, eps_cond = null_and_cond_eps(denoiser, z, t, cond, null, lengths)
    return eps_null + scale * (eps_cond - eps_null)


def null_and_cond_eps(denoiser: LatentDenoiser, z: torch.Tensor, t, cond: torch.Tensor, null: torch.Tensor,
                      lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(eps(z_t, t, null), eps(z_t, t, c)), each (B, n, d) in float32, from one pass over the 2B rows [null; cond]."""
    dtype = denoiser.latent_in.weight.dtype
    t_batch = torch.full((2 * len(z),), int(t), device=z.device)
    eps = denoiser(torch.cat([z, z]).to(dtype), t_batch, torch.cat([null, cond]).to(dtype),
                   torch.cat([lengths, lengths])).float()
    eps_null, eps_cond = eps.chunk(2)  # each (B, n, d)
    return eps_null, eps_cond


@dataclass
class VerbGuidance:
    """The term a second, action-conditioned denoiser on the same latents adds to the rows ``rows`` (B',) of a batch:
    ``scale`` * (eps_a(z_t, t, a) - eps_a(z_t, t, null)), its condition and null tokens (B', C, d) those rows'."""

    denoiser: LatentDenoiser
    rows: torch.Tensor  # (B',) long, indices into the batch
    cond: torch.Tensor
    null: torch.Tensor
    scale: float

    def add_to(self, eps: torch.Tensor, z: torch.Tensor, t, lengths: torch.Tensor) -> torch.Tensor:
        """eps (B, n, d) with the term added on its rows."""
        r = self.rows
        eps_null, eps_cond = null_and_cond_eps(self.denoiser, z[r], t, self.cond, self.null, lengths[r])
        eps = eps.clone()
        eps[r] += self.scale * (eps_cond - eps_null)  # (B', n, d)
        return eps


@dataclass
class FinalSampler:
    """DDIM steps of ``denoiser`` on ``scheduler``'s timesteps (set by the caller), guided with ``scale`` (None: the
    condition alone), and on some rows by a verb denoiser too (``verb``)."""

    denoiser: LatentDenoiser
    scheduler: object  # mld_core.schedulers.DDIMScheduler
    conditions: Conditions
    lengths: torch.Tensor  # (B,) frames
    scale: float | None
    verb: VerbGuidance | None = None

    @property
    def timesteps(self):
        return self.scheduler.timesteps

    def step(self, k: int, t, z: torch.Tensor) -> torch.Tensor:
        """z_t (B, n, d) -> the next timestep's."""
        c = self.conditions
        eps = guided_eps(self.denoiser, z, t, c.cond, c.null, self.lengths, self.scale)
        if self.verb is not None:
            eps = self.verb.add_to(eps, z, t, self.lengths)
        z, _ = self.scheduler.step(eps, t, z)
        return z


@dataclass
class DraftSampler:
    """Consistency steps of the Draft ``denoiser`` (``guidance`` its input s), re-noised from the rows' own
    ``generators``; the last ``teacher_steps`` are DDIM steps of ``teacher`` guided with ``teacher_scale``, and on
    some rows by a verb denoiser too (``verb``)."""

    denoiser: LatentDenoiser
    scheduler: object  # mld_core.schedulers.LCMScheduler
    conditions: Conditions
    lengths: torch.Tensor  # (B,) frames
    guidance: float
    generators: list
    teacher: LatentDenoiser | None = None
    teacher_scale: float | None = None
    teacher_steps: int = 0
    verb: VerbGuidance | None = None  # added to the teacher steps' noise on its rows

    @property
    def timesteps(self):
        return self.scheduler.timesteps

    def step(self, k: int, t, z: torch.Tensor) -> torch.Tensor:
        """z_t (B, n, d) -> the next timestep's: a consistency step, or (the last ``teacher_steps``) a teacher's."""
        total, c = len(self.timesteps), self.conditions
        if k >= total - self.teacher_steps:  # a guided DDIM step of its teacher (config draft.teacher_guidance)
            eps = guided_eps(self.teacher, z, t, c.teacher_cond, c.teacher_null, self.lengths, self.teacher_scale)
            if self.verb is not None:
                eps = self.verb.add_to(eps, z, t, self.lengths)
            return self.scheduler.ddim_step(eps, t, self.scheduler.next_timestep(t), z)
        dtype = self.denoiser.latent_in.weight.dtype
        B = len(z)
        scales = torch.full((B,), self.guidance, device=z.device)
        t_batch = torch.full((B,), int(t), device=z.device)
        eps = self.denoiser(z.to(dtype), t_batch, c.cond.to(dtype), self.lengths, guidance=scales).float()
        noise = None
        if k + 1 < total and self.scheduler.needs_noise:  # (B, n, d), each row from its own generator
            noise = torch.stack([torch.randn(*z.shape[1:], generator=g) for g in self.generators]).to(z.device)
        z, _ = self.scheduler.step(eps, t, z, noise)
        return z
