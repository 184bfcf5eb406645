"""How smooth a loop's seam is against real motion: the mean joint acceleration of the root-relative pose across
the seam (frames T-2, T-1, 0, 1) vs the 95th percentile of the same quantity over real test clips.

    python research/loop_seam.py --data DIR [--model DIR] [--seeds 4]

Prints the real clips' 95th percentile, then per looped prompt its largest seam and that as a multiple of it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mld_core.take_fixes.constraints import Constraints, Loop  # noqa: E402
from mld_core.data.dataset import load_split  # noqa: E402
from mld_core.motion.features import features_to_joints  # noqa: E402
from mld_core.pipeline import MLDPipeline  # noqa: E402

PROMPTS = ("a person walks forward", "a person runs", "a person waves with the right hand")
REAL = ("walk", "run", "wave-right-hand", "walk-turn-left")


def relative(joints: np.ndarray) -> np.ndarray:
    out = joints.copy()
    out[:, :, [0, 2]] -= joints[:, :1, [0, 2]]
    return out


def acceleration(pose: np.ndarray) -> np.ndarray:
    """(T-2,) mean over joints of |x[t+1] - 2 x[t] + x[t-1]| (metres per frame^2)."""
    return np.linalg.norm(pose[2:] - 2 * pose[1:-1] + pose[:-2], axis=-1).mean(-1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--model", default=None)
    ap.add_argument("--seeds", type=int, default=4)
    args = ap.parse_args(argv)
    pipe = MLDPipeline.from_pretrained(args.model)
    real = [c for c in load_split(args.data, "test", min_frames=40) if c.action in REAL]
    p95 = float(np.percentile(np.concatenate([acceleration(relative(features_to_joints(c.features)))
                                              for c in real]), 95))
    print(f"real test clips ({', '.join(REAL)}): 95th percentile {p95:.4f} m/frame^2")
    for prompt in PROMPTS:
        out = pipe([prompt] * args.seeds, 4.0, seed=list(range(args.seeds)), constraints=Constraints([Loop()]))
        seams = []
        for i, n in enumerate(out.lengths):
            pose = relative(out.joints[i, :n].astype(np.float64))
            seams.append(acceleration(np.concatenate([pose[-2:], pose[:2]])).max())
        print(f"{prompt}: seam {max(seams):.4f} m/frame^2 = {max(seams) / p95:.2f}x the real 95th percentile")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
