"""Take fix 2, constraints: the takes' latents z_0, and then their decoded features, refined until they meet the
constraints a caller gives (``constraints.py``: poses to hit, a root path, a loop). Meeting them is how a directed
take is decoded (:class:`MeetConstraints` stands in for the plain decode).

First Adam steps on the latent through the decoder (the motion stays one the model makes; a stepped take's feet's
ground slide costs too, so that it keeps stepping), then on the decoded features themselves with a smoothness term
(what a latent of this size cannot reach exactly). With ``stepping.keep_if_less_skating``, a stepped take is met
twice, from its stepped latent and from its sample (without the slide), in one batch, and keeps the unstepped one only
if it meets as many constraints and skates less.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
import torch

from mld_core.inputs import InputError
from mld_core.motion.features import features_to_joints
from mld_core.take_fixes.constraints import (Constraints, bone_stretch, planted_feet, planted_foot_speed,
                                             root_speed)
from mld_core.take_fixes.stepping import SteppingConfig, slide_cost, valid_frames


def meet_constraints(decoder, z: torch.Tensor, lengths: torch.Tensor, constraints: Constraints,
                     stepping: SteppingConfig | None = None, slide_rows: torch.Tensor | None = None) -> np.ndarray:
    """Denormalised features (B, T, F) of the sampled latents z (B, n, d) refined through ``decoder`` (a
    mld_core.decode.LatentDecoder) to meet ``constraints``: first the latent (with ``stepping``, the feet's ground
    slide costs too, in the rows ``slide_rows`` (B,) bool marks, default all), then the decoded features. All rows
    must have one length."""
    if len(set(lengths.tolist())) != 1:
        raise InputError("constraints need every motion of a call to have the same length")
    constraints.check_frames(int(lengths[0]))
    n = int(lengths[0])
    with torch.inference_mode(False), torch.enable_grad():
        mean, std = decoder.mean_std()
        lengths = lengths.clone()
        z0 = z.detach().clone()

        def decode(latent):  # (B, n, d) -> normalised features (B, T, F)
            return decoder.normalised_with_grad(latent, lengths)

        slide_weight = constraints.latent_slide_weight()
        if stepping is not None:  # (B,) the slide's weight per row
            on = torch.ones(len(z0), dtype=torch.bool) if slide_rows is None else torch.as_tensor(slide_rows)
            row_slide = slide_weight * on.to(device=z0.device, dtype=torch.float32)
        z_opt = z0.clone().requires_grad_(True)
        opt = torch.optim.Adam([z_opt], lr=constraints.lr)
        for _ in range(constraints.steps):  # 1. the latent
            opt.zero_grad()
            joints = features_to_joints(decode(z_opt) * std + mean)  # (B, T, 22, 3), differentiable
            loss = constraints.cost(joints) + constraints.prior_weight * ((z_opt - z0) ** 2).mean()
            if stepping is not None:
                valid = valid_frames(lengths, joints.shape[1])
                loss = loss + (row_slide * slide_cost(joints, valid, stepping)).mean()
            # x B: every term is a mean over the takes, so each take's gradient is its own cost's, whatever the
            # batch (a batch equals single runs); the latent's gradient only, not the decoder's weights'
            (loss * len(z0)).backward(inputs=[z_opt])
            opt.step()
        x0 = decode(z_opt).detach()
        contacts = planted_feet(x0 * std + mean, constraints.planted_toe_height_m)  # (B, T, 4) feet held still
        x = x0.clone().requires_grad_(True)
        opt = torch.optim.Adam([x], lr=constraints.feature_lr)
        change_only = constraints.change_only_rows(root_speed(x0 * std + mean))  # (B,) True: the change only
        origin = x0 * torch.as_tensor(change_only, dtype=x0.dtype, device=x0.device)[:, None, None]  # x0 or 0
        for _ in range(constraints.feature_steps):  # 2. the features, kept smooth and near the decoded ones
            opt.zero_grad()
            moved = x - origin  # the change, or the features themselves
            accel = moved[:, 2:] - 2 * moved[:, 1:-1] + moved[:, :-2]
            joints = features_to_joints(x * std + mean)
            loss = (constraints.cost(joints) + constraints.smooth_weight * (accel ** 2).mean()
                    + constraints.prior_weight * ((x - x0) ** 2).mean()
                    + constraints.planted_weight * planted_foot_speed(joints, contacts)
                    + constraints.bone_weight * bone_stretch(joints))
            (loss * len(x0)).backward()  # each take's gradient its own cost's (above)
            opt.step()
        features = (x.detach() * std + mean).cpu().numpy()
    out = np.zeros((len(features), int(lengths.max()), features.shape[-1]), np.float32)
    out[:, :n] = features
    return out


def meet_stepped_or_not(decoder, sampled: torch.Tensor, stepped: torch.Tensor, lengths: torch.Tensor,
                        constraints: Constraints, stepping: SteppingConfig) -> np.ndarray:
    """Features (B, T, F) of constrained takes: the constraints met from each stepped latent (B, n, d) with the feet's
    slide in the cost, unless met from its sampled latent without it they meet as many constraints and skate less;
    then those. Both are met in one batch of 2B rows (rows are independent: a batch equals single runs); every take
    is met twice, even one whose latent stepping left as sampled."""
    B = len(sampled)
    with_slide = torch.arange(2 * B) < B
    both = meet_constraints(decoder, torch.cat([stepped, sampled]), torch.cat([lengths, lengths]), constraints,
                            stepping, slide_rows=with_slide)  # (2B, T, F)
    return keep_less_skating_met(decoder, both[:B], both[B:], lengths, constraints)


def keep_less_skating_met(decoder, features: np.ndarray, unstepped: np.ndarray, lengths: torch.Tensor,
                          constraints: Constraints) -> np.ndarray:
    """Per constrained take, ``features`` (B, T, F: met from its stepped latent) unless ``unstepped`` (met from its
    sampled latent without the slide cost) meets as many constraints and skates less; then that."""
    n = int(lengths[0])
    out = features.copy()
    for i in range(len(features)):
        (met_s, skate_s), (met_u, skate_u) = (met_and_skating(decoder, f[:n], constraints)
                                              for f in (features[i], unstepped[i]))
        if met_u >= met_s and skate_u < skate_s:
            out[i] = unstepped[i]
    return out


def met_and_skating(decoder, features: np.ndarray, constraints: Constraints) -> tuple[int, float]:
    """A take's (number of constraints met, foot skating ratio); features (T, F)."""
    from mld_core.eval.quality import foot_skating_ratio

    joints = decoder.joints(features[None], [len(features)])[0]  # (T, 22, 3)
    met = sum(bool(ok) for _, _, ok in constraints.residuals(joints))
    return met, foot_skating_ratio(joints, decoder.fps)


@dataclass
class MeetConstraints:
    """The fix: the takes decoded by meeting ``constraints``; a stepped take's slide in the latent's cost
    (``stepping``), and with ``stepping.keep_if_less_skating`` its sample met too (:func:`meet_stepped_or_not`)."""

    constraints: Constraints
    stepping: SteppingConfig
    timings: ClassVar[tuple] = ("constraints_s", "decode_s")

    def apply(self, takes, decoder):
        if takes.stepped and self.stepping.keep_if_less_skating:
            features = meet_stepped_or_not(decoder, takes.sampled, takes.latents, takes.lengths, self.constraints,
                                           self.stepping)
        else:
            features = meet_constraints(decoder, takes.latents, takes.lengths, self.constraints,
                                        self.stepping if takes.stepped else None)
        return replace(takes, features=features)
