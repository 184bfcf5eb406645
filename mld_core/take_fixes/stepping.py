"""Take fix 1, stepping (config ``stepping``): a Final take's sampled latent z_0 refined until its feet step instead of
sliding. :func:`step_feet` takes Adam steps on z_0 through the VAE decoder to lower the cost below, so the legs that
carry the travel come from the decoder itself (it reconstructs stepping walks), not from a repair of the features;
with ``keep_if_less_skating``, :func:`keep_less_skating` then keeps a free take's sample where that, repaired, skates
less (a constrained take is judged once its constraints are met: ``meet_constraints.py``).

The cost: how far the take's low feet slide over the ground, plus the terms that keep what the sample already does
(its root's velocity, its turning, its stride length, a foot on the floor). All costs are per take, on joints
(B, T, 22, 3) in metres, frames beyond each take's length masked out by ``valid`` (B, T).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
import torch

from mld_core.motion import skeleton as sk
from mld_core.motion.features import features_to_joints
from mld_core.take_fixes.repair import RepairConfig, repair_rows

FEET = [sk.JOINT_NAMES.index(n) for n in ("left_ankle", "left_foot", "right_ankle", "right_foot")]
TOES = [sk.JOINT_NAMES.index(n) for n in ("left_foot", "right_foot")]
ANKLES = [sk.JOINT_NAMES.index(n) for n in ("left_ankle", "right_ankle")]
HIPS = [sk.JOINT_NAMES.index(n) for n in ("left_hip", "right_hip")]
GROUND = [0, 2]  # x, z
FAR = 1e3  # metres: pushes masked frames out of every min / max


@dataclass
class SteppingConfig:
    """How hard a sampled latent is pushed to step (a model folder's config.json "stepping" entry)."""

    steps: int = 0  # Adam steps on z_0 through the decoder; 0: off (takes decode as sampled)
    lr: float = 0.15
    contact_height_m: float = 0.05  # a foot joint this close to the take's lowest toe counts as on the ground
    contact_softness_m: float = 0.01  # ... through a sigmoid of this width (the cost stays differentiable)
    slide_m: float = 0.025  # a ground slide per frame that costs 1 (0.5 m/s at 20 fps)
    velocity_weight: float = 1.0  # the root's ground velocity stays the sample's (1 per cm a frame off, squared)
    turn_weight: float = 1.0  # the hips' turn per frame stays the sample's (1 per degree a frame off, squared)
    stride_weight: float = 1.0  # the ankles' fore-aft range may grow, not shrink (cost 1 per 5 cm short, squared)
    support_weight: float = 1.0  # the lower foot stays within 3 cm of the floor (cost 1 per 3 cm above, squared)
    prior_weight: float = 0.01  # the latent stays near the sample (mean squared change)
    min_slide_share: float = 0.02  # takes with fewer sliding frame pairs than this share are left as sampled
    keep_if_less_skating: bool = False  # a free take keeps its stepped latent only if, repaired, it skates no more
    #                                     than its sampled latent repaired (the repairs may fix the sample better);
    #                                     a constrained take, if it skates no more than the sample met unstepped


def valid_frames(lengths: torch.Tensor, frames: int) -> torch.Tensor:
    """(B, T) 1.0 on each take's frames, 0.0 beyond its length."""
    return (torch.arange(frames, device=lengths.device)[None] < lengths[:, None]).float()


def _per_take_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """x (B, T) averaged over each take's masked frames -> (B,)."""
    return (x * mask).sum(1) / mask.sum(1).clamp(min=1.0)


def feet_heights(joints: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, T, 4) height of the ankles and toes above the take's lowest toe."""
    toe_y = joints[:, :, TOES, 1].amin(-1) + (1 - valid) * FAR  # (B, T)
    floor = toe_y.amin(1)  # (B,)
    return joints[:, :, FEET, 1] - floor[:, None, None]


def foot_slides(joints: torch.Tensor) -> torch.Tensor:
    """(B, T-1, 4) ground distance (m) each ankle and toe moves from one frame to the next."""
    feet = joints[:, :, FEET][..., GROUND]  # (B, T, 4, 2)
    return (feet[:, 1:] - feet[:, :-1]).norm(dim=-1)


def slide_cost(joints: torch.Tensor, valid: torch.Tensor, cfg: SteppingConfig) -> torch.Tensor:
    """(B,) mean over frame pairs and feet of (slide / slide_m)^2, weighted by how surely the foot is on the ground
    in both frames."""
    on_ground = torch.sigmoid((cfg.contact_height_m - feet_heights(joints, valid)) / cfg.contact_softness_m)
    both = on_ground[:, 1:] * on_ground[:, :-1]  # (B, T-1, 4)
    slides = (foot_slides(joints) / cfg.slide_m) ** 2
    return _per_take_mean((both * slides).mean(-1), valid[:, 1:] * valid[:, :-1])


def sliding_share(joints: torch.Tensor, valid: torch.Tensor, cfg: SteppingConfig) -> torch.Tensor:
    """(B,) share of frame pairs in which a foot joint below contact height in both frames slides more than
    slide_m: the takes worth refining."""
    low = feet_heights(joints, valid) < cfg.contact_height_m  # (B, T, 4)
    sliding = (low[:, 1:] & low[:, :-1] & (foot_slides(joints) > cfg.slide_m)).any(-1).float()  # (B, T-1)
    return _per_take_mean(sliding, valid[:, 1:] * valid[:, :-1])


def facing(joints: torch.Tensor) -> torch.Tensor:
    """(B, T, 2) unit ground vector from the right hip to the left hip."""
    across = (joints[:, :, HIPS[0]] - joints[:, :, HIPS[1]])[..., GROUND]
    return across / across.norm(dim=-1, keepdim=True).clamp(min=1e-6)


def stride(joints: torch.Tensor, across: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B,) range (m) of the ankles' separation along the body's forward axis (perpendicular to ``across``)."""
    forward = torch.stack([-across[..., 1], across[..., 0]], -1)  # (B, T, 2)
    separation = ((joints[:, :, ANKLES[0]] - joints[:, :, ANKLES[1]])[..., GROUND] * forward).sum(-1)  # (B, T)
    return (separation - (1 - valid) * FAR).amax(1) - (separation + (1 - valid) * FAR).amin(1)


def turn_per_frame(across: torch.Tensor) -> torch.Tensor:
    """(B, T-1) signed angle (radians) the unit ground vectors ``across`` (B, T, 2) turn from frame to frame."""
    a, b = across[:, :-1], across[:, 1:]
    return torch.atan2(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0], (a * b).sum(-1))


def keep_cost(joints: torch.Tensor, sample: torch.Tensor, valid: torch.Tensor, cfg: SteppingConfig) -> torch.Tensor:
    """(B,) how far the take has moved from the sampled one (joints ``sample``): its root's ground velocity and its
    hips' turn, frame by frame (per frame, not the integrated path: a small change early would otherwise cost at
    every later frame, which makes the cost too stiff to descend on long takes), its stride (only a shorter one
    costs) and the lower foot's distance to the floor."""
    pair = valid[:, 1:] * valid[:, :-1]
    root, root0 = joints[:, :, 0, GROUND], sample[:, :, 0, GROUND]
    velocity = (((root[:, 1:] - root[:, :-1]) - (root0[:, 1:] - root0[:, :-1])) ** 2).sum(-1) / 0.01 ** 2  # (B, T-1)
    sample_facing = facing(sample)
    turn = ((turn_per_frame(facing(joints)) - turn_per_frame(sample_facing)) / math.radians(1.0)) ** 2  # (B, T-1)
    short = torch.relu(stride(sample, sample_facing, valid) - stride(joints, sample_facing, valid)) / 0.05  # (B,)
    lifted = torch.relu(feet_heights(joints, valid).amin(-1) - 0.03) / 0.03  # (B, T)
    return (cfg.velocity_weight * _per_take_mean(velocity, pair) + cfg.turn_weight * _per_take_mean(turn, pair)
            + cfg.stride_weight * short ** 2 + cfg.support_weight * _per_take_mean(lifted ** 2, valid))


def step_feet(decoder, z: torch.Tensor, lengths: torch.Tensor, cfg: SteppingConfig) -> torch.Tensor:
    """Sampled latents z_0 (B, n, d) refined so that the takes step instead of sliding: Adam steps through
    ``decoder`` (a mld_core.decode.LatentDecoder) on the feet's ground slide, keeping each take's root velocity,
    turning and stride. Takes that hardly slide are returned as sampled; each row is refined on its own (a batch
    equals single runs)."""
    with torch.inference_mode(False), torch.enable_grad():
        mean, std = decoder.mean_std()
        z0 = z.detach().clone()

        def joints_of(latent, n):  # (b, n, d) -> differentiable joints (b, T, 22, 3)
            return features_to_joints(decoder.normalised_with_grad(latent, n) * std + mean)

        sample = joints_of(z0, lengths).detach()
        valid = valid_frames(lengths, sample.shape[1])
        rows = torch.nonzero(sliding_share(sample, valid, cfg) >= cfg.min_slide_share).flatten()
        if not len(rows):
            return z
        n = lengths[rows].clone()
        sample, valid = sample[rows][:, : int(n.max())], valid[rows][:, : int(n.max())]
        start = z0[rows]
        latent = start.clone().requires_grad_(True)
        best, best_loss = start.clone(), torch.full((len(rows),), float("inf"), device=z.device)
        opt = torch.optim.Adam([latent], lr=cfg.lr)
        for k in range(cfg.steps + 1):  # the last pass only scores the last step
            with torch.set_grad_enabled(k < cfg.steps):
                joints = joints_of(latent, n)
                loss = (slide_cost(joints, valid, cfg) + keep_cost(joints, sample, valid, cfg)
                        + cfg.prior_weight * ((latent - start) ** 2).mean(dim=(1, 2)))  # (b,)
            better = loss.detach() < best_loss  # each row keeps its best latent: never worse than sampled
            best[better], best_loss[better] = latent.detach()[better], loss.detach()[better]
            if k < cfg.steps:
                opt.zero_grad()
                # rows independent: each row's gradient is its own loss's; only the latent's (the decoder's
                # weights need none: that would cost about 30% more per step)
                loss.sum().backward(inputs=[latent])
                opt.step()
        out = z0.clone()
        out[rows] = best
    return out


def keep_less_skating(decoder, sampled: torch.Tensor, stepped: torch.Tensor, lengths: torch.Tensor,
                      repair: RepairConfig) -> torch.Tensor:
    """Per free take, its stepped latent (B, n, d) unless the take, decoded and repaired (``repair``, whether or not
    the call repairs), skates more than its sampled latent decoded and repaired; then the sampled one. Stepping
    lowers the slide of the unrepaired feet; some samples' feet the repairs plant better unstepped."""
    from mld_core.eval.quality import foot_skating_ratio

    rows = torch.nonzero((stepped != sampled).flatten(1).any(1)).flatten()
    if not len(rows):
        return stepped
    n = lengths[rows].tolist()

    def skating(z: torch.Tensor) -> np.ndarray:  # (b,) the repaired takes' foot skating ratios
        with torch.inference_mode():
            features = decoder.features(z, lengths[rows])
        joints = decoder.joints(repair_rows(features, n, repair), n)
        return np.array([foot_skating_ratio(j[:k], decoder.fps) for j, k in zip(joints, n)])

    worse = torch.as_tensor(skating(stepped[rows]) > skating(sampled[rows]))
    out = stepped.clone()
    out[rows[worse]] = sampled[rows[worse]]
    return out


@dataclass
class Stepping:
    """The fix: the takes' latents stepped (:func:`step_feet`); a free take's kept only where, repaired, it skates no
    more than its sample (config ``keep_if_less_skating``)."""

    config: SteppingConfig
    repair: RepairConfig  # how a free take is judged: as these repairs leave it
    constrained: bool = False  # the takes have constraints: they are judged when met (meet_constraints.py)
    timings: ClassVar[tuple] = ("stepping_s",)

    def apply(self, takes, decoder):
        stepped = step_feet(decoder, takes.latents, takes.lengths, self.config)
        if self.config.keep_if_less_skating and not self.constrained:
            stepped = keep_less_skating(decoder, takes.sampled, stepped, takes.lengths, self.repair)
        return replace(takes, latents=stepped, stepped=True)
