"""An experiment on the feature convention: a prepared folder rebuilt with each clip's first facing unpinned.

    .venv/bin/python scripts/unpinned_features.py --data data/bandai --out data/bandai_unpinned

HumanML3D's features turn a clip to face +Z by its raw frame-0 facing, but their root rotation follows the smoothed
(IK) facing and pins frame 0 to the identity, so the yaw channel of frame 0 holds a one-frame turn (5 degrees on
average on Bandai). Here each clip (the folder's new_joints) is turned by its smoothed frame-0 facing instead, so
that turn is gone; every other channel is computed as ``joints_to_features`` does. Writes new_joint_vecs, new_joints
and Mean/Std (train split) under --out and links the rest (texts, splits, actions.json). Prints the round-trip error
and the frame-0 yaw channel before and after. docs/evaluation.md ("The VAE's global error") reports the result: the
VAE's global error does not fall on these features.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mld_core.motion import features as F  # noqa: E402

LINKED = ("texts", "LICENSE", "README.md", "actions.json", "all.txt", "train.txt", "val.txt", "test.txt")


def unpinned_features(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(features (T-1, 263), the joints they describe (T, 22, 3)) of canonical joints at 20 fps."""
    pos = F._canonicalise(F.uniform_skeleton(joints.astype(np.float64)))
    smoothed = F.normalize(F.gaussian_filter1d(F._forward(pos, hip_sign=-1.0), F.FACING_SMOOTH_SIGMA))[:1]  # (1, 3)
    pos = F.qrot(F.qbetween(smoothed, F._FORWARD[None])[:, None], pos)  # frame 0's smoothed facing along +Z
    return F.features_of(pos, F._smoothed_root_quat(pos)), pos  # frame 0's root is the identity by itself


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a prepared folder (`data prepare` output)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.out.resolve() == args.data.resolve():
        raise SystemExit("--out must differ from --data")
    if args.out.exists() and not args.out.is_dir():
        raise SystemExit(f"--out {args.out} is a file, not a folder")
    for sub in ("new_joint_vecs", "new_joints"):
        (args.out / sub).mkdir(parents=True, exist_ok=True)
    for name in LINKED:
        if (args.data / name).exists() and not (args.out / name).exists():
            os.symlink((args.data / name).resolve(), args.out / name)
    error, before, after = 0.0, [], []
    for path in sorted((args.data / "new_joints").glob("*.npy")):
        feats, pos = unpinned_features(np.load(path))
        joints = F.features_to_joints(feats)
        error = max(error, float(np.abs(joints - pos[:-1]).max()))
        before.append(abs(float(np.load(args.data / "new_joint_vecs" / path.name)[0, 0])))
        after.append(abs(float(feats[0, 0])))
        np.save(args.out / "new_joint_vecs" / path.name, feats)
        np.save(args.out / "new_joints" / path.name, joints.astype(np.float32))
    train = (args.data / "train.txt").read_text().split()
    mean, std = F.mean_std([np.load(args.out / "new_joint_vecs" / f"{cid}.npy") for cid in train])
    np.save(args.out / "Mean.npy", mean)
    np.save(args.out / "Std.npy", std)
    print(f"{len(after)} clips; round trip max error {error:.1e} m; frame-0 |yaw channel| mean "
          f"{np.mean(before):.4f} -> {np.mean(after):.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
