"""How much of its latent a VAE uses: the posterior's spread on real clips, per latent dimension.

    python research/v4/latent_use.py MODEL [MODEL ...] --data DIR [--labels throw,kick] [--clips 64]

A dimension whose posterior sigma stays near 1 (the prior's) carries nothing the decoder can read; one with a small
sigma carries the clip. For each model: the mean and median sigma, the number of dimensions with a mean sigma under
0.3 / 0.5 / 0.7 / 0.9, and the spread of mu across clips, on clips of the train split (those with the given action
labels of actions.json, else any).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from mld_core.data.dataset import split_ids  # noqa: E402
from mld_core.pipeline import MLDPipeline  # noqa: E402

THRESHOLDS = (0.3, 0.5, 0.7, 0.9)


def clip_ids(data: Path, labels: set[str], count: int) -> list[str]:
    """Up to ``count`` train clips, those labelled with one of ``labels`` when given."""
    ids = split_ids(data, "train")
    if labels:
        path = data / "actions.json"
        clips = json.loads(path.read_text()).get("clips", {}) if path.is_file() else {}
        ids = [i for i in ids if clips.get(i) in labels]
    return ids[:count]


def posterior(pipe: MLDPipeline, data: Path, ids: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
    """mu and sigma (B, n, d) of the clips (their first max_frames frames) under the model's VAE."""
    max_frames = int(pipe.config.max_frames)
    feats = [np.load(data / "new_joint_vecs" / f"{i}.npy")[:max_frames] for i in ids]
    mean = torch.tensor(np.asarray(pipe.config.mean), dtype=torch.float32)
    std = torch.tensor(np.asarray(pipe.config.std), dtype=torch.float32)
    x = torch.zeros(len(feats), max(len(f) for f in feats), mean.numel())  # (B, T, F)
    for k, f in enumerate(feats):
        x[k, :len(f)] = (torch.from_numpy(f).float() - mean) / std
    lengths = torch.tensor([len(f) for f in feats])
    with torch.no_grad():
        mu, logvar = pipe.vae.float().encode(x, lengths)
    return mu, (0.5 * logvar).exp()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("models", nargs="+")
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--labels", default="", help="comma-separated action labels (default: any clip)")
    ap.add_argument("--clips", type=int, default=64)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    ids = clip_ids(args.data, {s for s in args.labels.split(",") if s}, args.clips)
    if not ids:
        print(f"error: no train clips in {args.data} with labels {args.labels!r}", file=sys.stderr)
        return 2
    print(f"{len(ids)} clips; dims with mean sigma under " + " / ".join(str(t) for t in THRESHOLDS))
    for model in args.models:
        pipe = MLDPipeline.from_pretrained(model)
        mu, sigma = posterior(pipe, args.data, ids)
        per_dim = sigma.mean(0).flatten()  # (n * d,)
        counts = " / ".join(str(int((per_dim < t).sum())) for t in THRESHOLDS)
        print(f"{pipe.model_id}: latent {tuple(mu.shape[1:])}, sigma mean {sigma.mean():.2f} median "
              f"{sigma.median():.2f}, active dims {counts} of {per_dim.numel()}, mu spread {mu.std(0, correction=0).mean():.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
