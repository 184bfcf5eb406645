"""Diffusion noise schedulers as plain objects (they know nothing of models).

``DDPMScheduler`` is used for training (``add_noise`` at random timesteps) and ``DDIMScheduler`` for sampling.
Both follow the conventions of diffusers' ``scheduling_ddpm.py`` / ``scheduling_ddim.py`` with MLD's settings:
1000 training steps, ``scaled_linear`` betas 0.00085 -> 0.012, ``steps_offset`` 1, ``set_alpha_to_one`` False,
"leading" timestep spacing, epsilon prediction.

Symbols: alpha_bar_t = prod_{s<=t} (1 - beta_s);  x_t = sqrt(alpha_bar_t) x_0 + sqrt(1 - alpha_bar_t) eps.
"""

from __future__ import annotations

import numbers

from dataclasses import asdict, dataclass

import torch


@dataclass
class SchedulerConfig:
    num_train_timesteps: int = 1000
    beta_start: float = 0.00085
    beta_end: float = 0.012
    beta_schedule: str = "scaled_linear"  # or "linear"
    set_alpha_to_one: bool = False
    steps_offset: int = 1

    def to_dict(self) -> dict:
        return asdict(self)


def make_betas(config: SchedulerConfig) -> torch.Tensor:
    n = config.num_train_timesteps
    if config.beta_schedule == "scaled_linear":
        return torch.linspace(config.beta_start**0.5, config.beta_end**0.5, n, dtype=torch.float32) ** 2
    if config.beta_schedule == "linear":
        return torch.linspace(config.beta_start, config.beta_end, n, dtype=torch.float32)
    raise ValueError(f"unknown beta_schedule {config.beta_schedule!r} (scaled_linear or linear)")


class _Schedule:
    def __init__(self, config: SchedulerConfig | None = None):
        self.config = config or SchedulerConfig()
        betas = make_betas(self.config)
        self.betas = betas  # float32 throughout, as diffusers computes them
        self.alphas_cumprod = torch.cumprod(1.0 - betas, dim=0)  # alpha_bar_t, (N,)
        self.timesteps = torch.arange(self.config.num_train_timesteps - 1, -1, -1)

    def to(self, device: torch.device | str):
        """The schedule's tables on ``device`` (a GPU's samples are stepped there); returns self."""
        for name, value in list(vars(self).items()):
            if isinstance(value, torch.Tensor):
                setattr(self, name, value.to(device))
        return self

    def add_noise(self, original: torch.Tensor, noise: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        """x_t = sqrt(alpha_bar_t) x_0 + sqrt(1 - alpha_bar_t) eps, one timestep per batch item."""
        alpha_bar = self.alphas_cumprod.to(original.device)[timesteps].to(original.dtype)
        shape = (-1,) + (1,) * (original.dim() - 1)
        alpha_bar = alpha_bar.reshape(shape)  # (B, 1, ...)
        return alpha_bar.sqrt() * original + (1.0 - alpha_bar).sqrt() * noise


class DDPMScheduler(_Schedule):
    """Training-time forward process (``add_noise``) and ancestral sampling (``step``) over all 1000 steps."""

    def set_timesteps(self, num_inference_steps: int | None = None) -> None:
        n = self.config.num_train_timesteps if num_inference_steps is None else num_inference_steps
        ratio = self.config.num_train_timesteps // n
        self.timesteps = torch.arange(0, n) * ratio
        self.timesteps = self.timesteps.flip(0)
        self._ratio = ratio

    def step(self, model_output: torch.Tensor, timestep: int, sample: torch.Tensor,
             generator: torch.Generator | None = None) -> torch.Tensor:
        t = int(timestep)
        prev_t = t - getattr(self, "_ratio", 1)
        a_t = self.alphas_cumprod[t]
        a_prev = self.alphas_cumprod[prev_t] if prev_t >= 0 else torch.tensor(1.0)
        beta_t = 1 - a_t / a_prev
        x0 = (sample - (1 - a_t).sqrt() * model_output) / a_t.sqrt()
        mean = (a_prev.sqrt() * beta_t / (1 - a_t)) * x0 + ((1 - beta_t).sqrt() * (1 - a_prev) / (1 - a_t)) * sample
        if t == 0:
            return mean
        variance = ((1 - a_prev) / (1 - a_t) * beta_t).clamp(min=1e-20)
        noise = torch.randn(sample.shape, generator=generator, dtype=sample.dtype, device=sample.device)
        return mean + variance.sqrt() * noise


class DDIMScheduler(_Schedule):
    """Deterministic (eta = 0) or stochastic DDIM sampling on a sub-sequence of the training timesteps."""

    def __init__(self, config: SchedulerConfig | None = None):
        super().__init__(config)
        self.final_alpha_cumprod = torch.tensor(1.0) if self.config.set_alpha_to_one else self.alphas_cumprod[0]
        self.num_inference_steps: int | None = None

    def set_timesteps(self, num_inference_steps: int) -> None:
        n_train = self.config.num_train_timesteps
        if not 1 <= num_inference_steps <= n_train:
            raise ValueError(f"num_inference_steps must be in 1..{n_train}, got {num_inference_steps}")
        self.num_inference_steps = num_inference_steps
        ratio = n_train // num_inference_steps
        timesteps = (torch.arange(0, num_inference_steps) * ratio).flip(0) + self.config.steps_offset
        self.timesteps = timesteps.clamp(max=n_train - 1)  # with steps_offset 1, 1000 steps would reach t = 1000

    def step(self, model_output: torch.Tensor, timestep: int, sample: torch.Tensor, eta: float = 0.0,
             generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """One reverse step x_t -> x_{t-1}; returns (prev_sample, pred_original_sample)."""
        if self.num_inference_steps is None:
            raise RuntimeError("call set_timesteps before step")
        t = int(timestep)
        prev_t = t - self.config.num_train_timesteps // self.num_inference_steps
        a_t = self.alphas_cumprod[t]
        a_prev = self.alphas_cumprod[prev_t] if prev_t >= 0 else self.final_alpha_cumprod
        pred_x0 = (sample - (1 - a_t).sqrt() * model_output) / a_t.sqrt()
        variance = (1 - a_prev) / (1 - a_t) * (1 - a_t / a_prev)
        sigma = eta * variance.sqrt()
        direction = (1 - a_prev - sigma**2).sqrt() * model_output
        prev = a_prev.sqrt() * pred_x0 + direction
        if eta > 0:
            noise = torch.randn(sample.shape, generator=generator, dtype=sample.dtype, device=sample.device)
            prev = prev + sigma * noise
        return prev, pred_x0


class LCMScheduler(_Schedule):
    """Multistep sampling of a latent consistency model (Luo et al. 2023; MotionLCM): the model's noise prediction
    at x_t gives the clean estimate f(x_t, t) = c_skip(t) x_t + c_out(t) x0(eps); between steps the estimate is
    noised again to the next timestep. Timesteps come from the ``original_steps``-point DDIM grid the model was
    distilled on (``skip`` = its spacing, the distillation's step from t to t - skip).

    ``fresh_noise`` (gamma, 0..1) is the share of new noise in the re-noising: 1 is LCM's own sampler (new noise at
    every step); 0 re-noises with the noise the step itself implies, eps = (x_t - sqrt(a_t) f(x_t)) / sqrt(1 - a_t),
    so the next step continues the same sample as a DDIM step would; in between, sqrt(1 - gamma) of the implied
    noise plus sqrt(gamma) of new noise (unit variance either way)."""

    def __init__(self, config: SchedulerConfig | None = None, original_steps: int = 50, timestep_scaling: float = 10.0,
                 sigma_data: float = 0.5, fresh_noise: float = 1.0):
        super().__init__(config)
        if not 0.0 <= fresh_noise <= 1.0:
            raise ValueError(f"fresh_noise must be in 0..1, got {fresh_noise}")
        self.fresh_noise = float(fresh_noise)
        n_train = self.config.num_train_timesteps
        if not 1 <= original_steps <= n_train:
            raise ValueError(f"original_steps must be in 1..{n_train}, got {original_steps}")
        self.skip = n_train // original_steps
        self.grid = torch.arange(0, original_steps) * self.skip + self.config.steps_offset  # ascending, (S,)
        self.grid = self.grid.clamp(max=n_train - 1)
        self.timestep_scaling, self.sigma_data = timestep_scaling, sigma_data
        self.timesteps = self.grid.flip(0)[:1]

    def set_timesteps(self, num_inference_steps: int, timesteps: list[int] | None = None) -> None:
        """``num_inference_steps`` timesteps spread evenly over the grid, the largest first; or ``timesteps``, as
        many points of the grid, descending."""
        size = len(self.grid)
        if not 1 <= num_inference_steps <= size:
            raise ValueError(f"num_inference_steps must be in 1..{size} for this Draft model, got {num_inference_steps}")
        if timesteps is not None:
            self.timesteps = self.checked_timesteps(timesteps, num_inference_steps)
            return
        picks = (size - 1) - (torch.arange(num_inference_steps) * size) // num_inference_steps  # distinct, (n,)
        self.timesteps = self.grid[picks]

    def checked_timesteps(self, timesteps, count: int) -> torch.Tensor:
        """``timesteps`` as a tensor when they are ``count`` distinct points of the grid in descending order."""
        points = self.grid.tolist()
        values = list(timesteps) if isinstance(timesteps, (list, tuple)) else None
        whole = values is not None and all(isinstance(t, numbers.Integral) and not isinstance(t, bool) for t in values)
        if not whole or len(values) != count or any(int(t) not in points for t in values) \
                or any(a <= b for a, b in zip(values, values[1:])):
            shown = ", ".join(map(str, points)) if len(points) <= 3 else f"{points[0]}, {points[1]}, ..., {points[-1]}"
            raise ValueError(f"the Draft's timesteps must be {count} descending points of its grid {shown}; "
                             f"got {timesteps!r}")
        return torch.tensor([int(t) for t in values])

    def boundary(self, timesteps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(c_skip, c_out) per timestep: f(x, t) -> x as t -> 0, the x0 estimate elsewhere."""
        scaled = timesteps.float() * self.timestep_scaling
        c_skip = self.sigma_data**2 / (scaled**2 + self.sigma_data**2)
        c_out = scaled / (scaled**2 + self.sigma_data**2).sqrt()
        return c_skip, c_out

    def denoised(self, model_output: torch.Tensor, timesteps: torch.Tensor, sample: torch.Tensor) -> torch.Tensor:
        """f(x_t, t) for a batch: model_output and sample (B, ...), timesteps (B,) or a scalar."""
        timesteps = torch.as_tensor(timesteps, device=self.alphas_cumprod.device).reshape(-1)
        shape = (-1,) + (1,) * (sample.dim() - 1)
        a_t = self.alphas_cumprod[timesteps].reshape(shape).to(sample.dtype)  # (B, 1, ...)
        pred_x0 = (sample - (1 - a_t).sqrt() * model_output) / a_t.sqrt()
        c_skip, c_out = (c.reshape(shape).to(sample.dtype) for c in self.boundary(timesteps))
        return c_skip * sample + c_out * pred_x0

    def step(self, model_output: torch.Tensor, timestep: int, sample: torch.Tensor,
             noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """One step from ``timestep``; returns (next sample, clean estimate). Before the last step the estimate is
        re-noised to the next timestep with ``noise`` (like sample; needed unless ``fresh_noise`` is 0) mixed with
        the step's implied noise; at the last step the next sample is the estimate."""
        t = int(timestep)
        denoised = self.denoised(model_output, torch.tensor(t), sample)
        later = (self.timesteps < t).nonzero()
        if len(later) == 0:
            return denoised, denoised
        if noise is None and self.needs_noise:
            raise ValueError("LCM steps before the last need noise unless fresh_noise is 0")
        a_t = self.alphas_cumprod[t].to(sample.dtype)
        implied = (sample - a_t.sqrt() * denoised) / (1 - a_t).sqrt()
        g = self.fresh_noise
        mixed = implied if not self.needs_noise else (1 - g) ** 0.5 * implied + g ** 0.5 * noise
        a_next = self.alphas_cumprod[int(self.timesteps[later[0, 0]])]
        return a_next.sqrt() * denoised + (1 - a_next).sqrt() * mixed, denoised

    @property
    def needs_noise(self) -> bool:
        """Whether steps before the last need new noise (``fresh_noise`` > 0)."""
        return self.fresh_noise > 0

    def teacher_step(self, model_output: torch.Tensor, timesteps: torch.Tensor, sample: torch.Tensor) -> torch.Tensor:
        """The distillation's ODE step: a DDIM (eta 0) step from each x_t to t - skip, timesteps (B,) >= skip."""
        return self.ddim_step(model_output, timesteps, timesteps - self.skip, sample)

    def ddim_step(self, model_output: torch.Tensor, timesteps: torch.Tensor | int, prev_timesteps: torch.Tensor | int,
                  sample: torch.Tensor) -> torch.Tensor:
        """A DDIM (eta 0) step from x_t to x_prev, one pair of timesteps per row or one for all; a negative
        ``prev_timesteps`` steps to the clean sample (alpha_bar 1)."""
        shape = (-1,) + (1,) * (sample.dim() - 1)
        device = self.alphas_cumprod.device
        t = torch.as_tensor(timesteps, device=device).reshape(-1)
        prev = torch.as_tensor(prev_timesteps, device=device).reshape(-1)
        a_t = self.alphas_cumprod[t].reshape(shape)
        a_prev = torch.where(prev >= 0, self.alphas_cumprod[prev.clamp(min=0)],
                             torch.ones((), device=device)).reshape(shape)
        pred_x0 = (sample - (1 - a_t).sqrt() * model_output) / a_t.sqrt()
        return a_prev.sqrt() * pred_x0 + (1 - a_prev).sqrt() * model_output

    def next_timestep(self, timestep: int) -> int:
        """The timestep after ``timestep`` in the current schedule; -1 after the last (the clean sample)."""
        later = self.timesteps[self.timesteps < int(timestep)]
        return int(later[0]) if len(later) else -1
