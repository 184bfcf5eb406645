"""Do pose keys cost the take its prompt? R@3 and FID (bundled evaluator) of takes with pose keys against free takes
of the same captions and seeds (a measurement: prints a table).

    .venv/bin/python research/control_quality.py --data DIR [--clips 128] [--threads 2]

For the first --clips test clips of at least 3 s (mirrors left out): the clip's first caption at its length, with 4
pose keys taken from the clip (pelvis, wrists, ankles) and without; R@3 over batches of 32 (the protocol's
matching), FID of each set against the real clips' features. A reduced version of ``evaluate t2m`` (one draw).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mld_core.take_fixes.constraints import Constraints, PoseKeys  # noqa: E402
from mld_core.eval import metrics  # noqa: E402
from mld_core.motion.skeleton import JOINT_NAMES  # noqa: E402

KEYED = ("pelvis", "left_wrist", "right_wrist", "left_ankle", "right_ankle")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--clips", type=int, default=128)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    import torch

    from mld_core.eval.evaluator import Evaluator
    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(args.threads)
    pipe, evaluator = MLDPipeline.from_pretrained(), Evaluator.from_pretrained()
    ids = [i.strip() for i in (args.data / "test.txt").read_text().splitlines() if i.strip() and not i.startswith("M")]
    real, keyed, free, captions = [], [], [], []
    for cid in ids:
        joints = np.load(args.data / "new_joints" / f"{cid}.npy")[:196]
        if len(joints) < 60:
            continue
        caption = (args.data / "texts" / f"{cid}.txt").read_text().splitlines()[0].split("#")[0]
        frames = np.linspace(5, len(joints) - 5, 4).astype(int)
        targets = {int(f): {n: joints[f, JOINT_NAMES.index(n)].tolist() for n in KEYED} for f in frames}
        seed = len(captions)
        out = pipe([caption], seconds=len(joints) / 20, seed=seed, constraints=Constraints([PoseKeys(targets)]))
        plain = pipe([caption], seconds=len(joints) / 20, seed=seed)
        n = int(out.lengths[0])
        keyed.append(out.features[0, :n])
        free.append(plain.features[0, :n])
        real.append(np.load(args.data / "new_joint_vecs" / f"{cid}.npy")[:n])
        captions.append(caption)
        if len(captions) == args.clips:
            break
    text = evaluator.encode_text(captions)
    emb = {name: evaluator.encode_motion(feats) for name, feats in (("real", real), ("keyed", keyed), ("free", free))}
    rng = np.random.default_rng(0)
    print(f"{len(captions)} test clips, 4 pose keys each")
    print("| takes | R@3 | FID (vs real) |")
    print("|---|---|---|")
    for name in ("real", "free", "keyed"):
        r3 = float(metrics.r_precision(text, emb[name], top_k=3, batch_size=32, rng=rng)[0][-1])
        print(f"| {name} | {r3:.3f} | {metrics.fid(emb[name], emb['real']):.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
