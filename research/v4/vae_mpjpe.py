"""VAE reconstruction error per source: root-relative and global MPJPE (mm) of encode -> decode on the test splits
of the Bandai Namco and CMU folders, the same clips for every model.

    python research/v4/vae_mpjpe.py --bandai data/bandai --cmu data/cmu --clips 200 MODEL_OR_RUN [MODEL_OR_RUN ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from mld_core.checkpoint import load_config, load_weights  # noqa: E402
from mld_core.data.dataset import load_split  # noqa: E402
from mld_core.models.vae import MotionVAE  # noqa: E402
from mld_core.training.vae import validate_mpjpe  # noqa: E402


def test_clips(folder: Path, n: int) -> list:
    clips = load_split(folder, "test", captioned=False)
    rng = np.random.default_rng(0)
    return [clips[i] for i in sorted(rng.choice(len(clips), size=min(n, len(clips)), replace=False))]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("models", nargs="+", type=Path)
    p.add_argument("--bandai", required=True, type=Path)
    p.add_argument("--cmu", required=True, type=Path)
    p.add_argument("--clips", type=int, default=200)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    sources = {"bandai": test_clips(args.bandai, args.clips), "cmu": test_clips(args.cmu, args.clips)}
    print(f"{'model':40s} " + " ".join(f"{s + ' ' + k:>16s}" for s in sources for k in ("root", "global")))
    for folder in args.models:
        config = load_config(folder)
        vae = MotionVAE(config.vae)
        load_weights(folder / "vae.safetensors", vae)
        mean, std = config.mean_std
        row = []
        for clips in sources.values():
            row += validate_mpjpe(vae, clips, np.asarray(mean, np.float32), np.asarray(std, np.float32),
                                  config.vae.max_frames)
        print(f"{str(folder)[-40:]:40s} " + " ".join(f"{v:16.1f}" for v in row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
