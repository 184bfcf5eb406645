"""How the takes of the CMU verbs' prompts look beside their check: implausible takes, jerk, skating, floor.

    python research/v4/verb_take_quality.py --data data/cmu MODEL [MODEL ...] [--seeds 8] [--threads 1]

For each model, the command and user wordings of scripts/vocabulary.py (20 prompts) at seeds 0..N-1, 5 s each: the
share of takes the data checks call implausible (mld_core.data.take_checks: body height, floor, joint speeds), the
mean joint jerk over the real clips' (mld_core.eval.quality.mean_jerk against the CMU folder's real test windows),
the foot-skating ratio and the deepest ground penetration. A guidance term that bends takes out of shape shows here
before it shows in a verb's pass rate. A measurement, not a test.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from mld_core.data.take_checks import implausible  # noqa: E402
from mld_core.eval.quality import foot_skating_ratio, ground_penetration_cm, mean_jerk  # noqa: E402
from vocabulary import COMMANDS, USER  # noqa: E402


def real_jerk(data: Path, limit: int = 200) -> float:
    """Mean joint jerk of the first ``limit`` real test windows of ``data``."""
    from mld_core.data.dataset import split_ids

    ids = [i for i in split_ids(data, "test") if not i.startswith("M")][:limit]
    return float(np.mean([mean_jerk(np.load(data / "new_joints" / f"{i}.npy")) for i in ids]))


def takes_quality(model: str, seeds: int) -> dict:
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained(model)
    rows = []
    for prompt in [*COMMANDS.values(), *USER.values()]:
        out = pipe([prompt], seconds=5.0, seed=0, num_variants=seeds)
        for v in range(len(out.joints)):
            j = out.joints[v, : out.lengths[v]]
            rows.append((implausible(j, pipe.fps) is not None, mean_jerk(j, pipe.fps), foot_skating_ratio(j, pipe.fps),
                         ground_penetration_cm(j)))
    a = np.asarray(rows, np.float64)
    return {"takes": len(rows), "implausible": a[:, 0].mean(), "jerk": a[:, 1].mean(), "skating": a[:, 2].mean(),
            "penetration_cm": a[:, 3].mean()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a folder written by data prepare cmu-joints")
    ap.add_argument("models", nargs="+")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    reference = real_jerk(args.data)
    print(f"real test windows' mean jerk {reference:.1f} m/s^3")
    print(f"{'model':40} {'takes':>5} {'implausible':>11} {'jerk/real':>9} {'skating':>7} {'below floor cm':>14}")
    for model in args.models:
        q = takes_quality(model, args.seeds)
        print(f"{model:40} {q['takes']:5d} {q['implausible']:11.3f} {q['jerk'] / reference:9.2f} {q['skating']:7.3f} "
              f"{q['penetration_cm']:14.2f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
