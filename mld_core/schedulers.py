"""Diffusion noise schedulers as plain objects (they know nothing of models).

``DDPMScheduler`` is used for training (``add_noise`` at random timesteps) and ``DDIMScheduler`` for sampling.
Both follow the conventions of diffusers' ``scheduling_ddpm.py`` / ``scheduling_ddim.py`` with MLD's settings:
1000 training steps, ``scaled_linear`` betas 0.00085 -> 0.012, ``steps_offset`` 1, ``set_alpha_to_one`` False,
"leading" timestep spacing, epsilon prediction.

Symbols: alpha_bar_t = prod_{s<=t} (1 - beta_s);  x_t = sqrt(alpha_bar_t) x_0 + sqrt(1 - alpha_bar_t) eps.
"""

from __future__ import annotations

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
