"""Where does foot skating come from? Real walks vs VAE reconstructions vs diffusion samples, and root vs pose.

    python research/skating_source.py --data DIR [--model DIR] [--clips 24] [--json out.json]

For each locomotion content of the test split (at most ``--clips`` clips each, their first max_frames frames) it
prints the foot skating ratio (mld_core.eval.quality) and the per-take bone length SD (mm) of:

- ``real``: the clip's own features -> joints;
- ``recon``: VAE encode (mean) -> decode at the clip's length;
- ``recon pose + real root``: the reconstruction's root-relative channels under the real root channels (0-3);
- ``real pose + recon root``: the other way round; the two say whether the root trajectory or the pose skates;
- ``sample``: the diffusion model on the clip's first caption at the clip's length (seed = clip index), unrepaired;
- ``one skeleton`` / ``planted fully`` / ``repaired, feet not locked`` / ``repaired, not stepped``:
  mld_core.take_fixes.repair's bone lengths alone, root re-estimation from the planted feet with no travel kept, the
  model's configured repairs without lock_feet, and with it;
- ``stepped`` / ``stepped, repaired (default)``: the same samples' latents refined so that their feet step
  (take_fixes.stepping.step_feet, config ``stepping``), decoded as they are, then with the model's repairs: the
  pipeline's output.

Besides skating, bone length SD, jerk and travel it prints the share of frames with a straight knee (either knee
bent less than 3 degrees), which the leg IK of lock_feet raises where it holds a foot out of the leg's reach.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mld_core.data.dataset import load_split  # noqa: E402
from mld_core.eval.quality import foot_skating_ratio, mean_jerk  # noqa: E402
from mld_core.motion import skeleton as sk  # noqa: E402
from mld_core.motion.features import features_to_joints  # noqa: E402
from mld_core.take_fixes.repair import (RepairConfig, features_with_bone_lengths, plant_feet,  # noqa: E402
                                        repair_features)
from mld_core.pipeline import MLDPipeline  # noqa: E402
from mld_core.rig.fidelity import knee_bend_deg  # noqa: E402

CONTENTS = ("walk", "run", "dash", "walk-back", "walk-left", "walk-right", "walk-turn-left", "walk-turn-right")
ROOT = slice(0, 4)


def bone_sd_mm(joints: np.ndarray) -> float:
    """Mean over bones of the SD of each bone's length within the take, mm."""
    parents = np.asarray(sk.PARENTS)
    child = np.arange(1, 22)
    length = np.linalg.norm(joints[:, child] - joints[:, parents[child]], axis=-1)  # (T, 21)
    return float(length.std(axis=0).mean() * 1000.0)


def straight_knee_share(joints: np.ndarray, degrees: float = 3.0) -> float:
    """Share of frames (T, 22, 3) in which either knee is bent less than ``degrees`` (the leg straight)."""
    bent = [knee_bend_deg(joints[:, hip], joints[:, knee], joints[:, ankle]) for hip, knee, ankle in ((1, 4, 7), (2, 5, 8))]
    return float((np.minimum(*bent) < degrees).mean())


def reconstruct(pipe: MLDPipeline, features: list[np.ndarray]) -> list[np.ndarray]:
    """Each clip encoded (its VAE mean) and decoded at its own length."""
    out = []
    for f in features:
        z, lengths = pipe.features_to_latents([f])  # (1, n, d) diffusion-space latent
        out.append(pipe.latents_to_features(z, lengths)[0, : len(f)])
    return out


def swap_root(pose_from: np.ndarray, root_from: np.ndarray) -> np.ndarray:
    out = pose_from.copy()
    out[:, ROOT] = root_from[:, ROOT]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--model", default=None)
    ap.add_argument("--clips", type=int, default=24)
    ap.add_argument("--split", default="test")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    pipe = MLDPipeline.from_pretrained(args.model)
    clips = load_split(args.data, args.split, min_frames=pipe.config.min_frames)
    rows = {}
    for content in CONTENTS:
        chosen = [c for c in clips if c.action == content][: args.clips]
        if not chosen:
            continue
        real = [c.features[: pipe.config.max_frames] for c in chosen]
        recon = reconstruct(pipe, real)
        lengths = [len(f) for f in real]
        out = pipe([c.captions[0].text for c in chosen], [n / pipe.fps for n in lengths],
                   seed=list(range(len(chosen))), repair=False)
        samples = [out.features[i, :n] for i, n in enumerate(lengths)]
        repairs = pipe.config.repair
        pipe.config.repair = RepairConfig(bone_lengths=False, plant_feet=False, lock_feet=False)
        out = pipe([c.captions[0].text for c in chosen], [n / pipe.fps for n in lengths],
                   seed=list(range(len(chosen))))  # stepped (when the model's config says so), not repaired
        pipe.config.repair = repairs
        stepped = [out.features[i, :n] for i, n in enumerate(lengths)]
        full = RepairConfig(bone_lengths=False, min_travel_kept=0.0)
        variants = {"real": real, "recon": recon,
                    "recon pose + real root": [swap_root(r, t) for r, t in zip(recon, real)],
                    "real pose + recon root": [swap_root(t, r) for r, t in zip(recon, real)],
                    "recon, planted fully": [plant_feet(f, full) for f in recon],
                    "sample": samples,
                    "sample, one skeleton": [features_with_bone_lengths(f) for f in samples],
                    "sample, planted fully": [plant_feet(f, full) for f in samples],
                    "sample, repaired, feet not locked": [repair_features(f, replace(pipe.config.repair, lock_feet=False))
                                                          for f in samples],
                    "sample, repaired, not stepped": [repair_features(f, pipe.config.repair) for f in samples],
                    "stepped": stepped,
                    "stepped, repaired (default)": [repair_features(f, pipe.config.repair) for f in stepped]}
        rows[content] = {}
        for name, feats in variants.items():
            joints = [features_to_joints(f.astype(np.float64)) for f in feats]
            rows[content][name] = {"skating": float(np.mean([foot_skating_ratio(j) for j in joints])),
                                   "bone_sd_mm": float(np.mean([bone_sd_mm(j) for j in joints])),
                                   "jerk": float(np.mean([mean_jerk(j) for j in joints])),
                                   "straight_knee": float(np.mean([straight_knee_share(j) for j in joints])),
                                   "travel_m": float(np.mean([np.linalg.norm(j[-1, 0, [0, 2]] - j[0, 0, [0, 2]])
                                                              for j in joints]))}
        print(f"{content} ({len(chosen)} clips)", flush=True)
        for name, r in rows[content].items():
            print(f"  {name:34s} skating {r['skating']:.3f}  bone SD {r['bone_sd_mm']:5.1f} mm  jerk {r['jerk']:5.1f}"
                  f"  travel {r['travel_m']:4.2f} m  straight knee {r['straight_knee']:.3f}",
                  flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
