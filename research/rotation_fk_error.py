"""How well the per-joint local rotations reproduce the joints: FK of ``features_to_rotations`` vs the joints
recovered from the same features, in millimetres.

    python research/rotation_fk_error.py [--data data/bandai] [--split test] [--every N] [--limit N]
                                        [--generated] [--prompt TEXT ...] [--seconds 4] [--json OUT]

For every motion (real clips of a HumanML3D-format folder's split, and/or takes the bundled default model
generates) it computes the local rotations (``mld_core.motion.rotations.features_to_rotations``), runs forward
kinematics and compares with ``features_to_joints`` (the positions the add-on's exact mode keys), two ways:

* ``reference``: on the canonical skeleton's rest offsets (``skeleton.REST_OFFSETS``), what the canonical armature
  plays when only rotations + the root are keyed ("Match Joints Exactly" off);
* ``fitted``: on rest offsets fitted to the motion's own pelvis and chest (``rest_offsets_from_joints``, reference
  bone lengths);
* ``own lengths``: the fitted rest with every bone at the motion's median length: what is left is the error of the
  rotations themselves plus the bone lengths changing over time (generated joints do not keep them fixed).

Prints mean / 95th percentile / max over all joints and frames, and the mean of per-motion maxima.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DEFAULT_PROMPTS = (
    "a person walks forward",
    "a person waves with the right hand",
    "a person jumps up and down",
    "a person kicks with the left leg",
    "a person bows",
    "a person runs in a circle",
)


def fk_errors_mm(features: np.ndarray) -> dict[str, np.ndarray]:
    """Per joint and frame FK error (T, 22) in mm for one motion's features (T, 263), both rest choices."""
    from mld_core.motion import features as F
    from mld_core.motion import rotations as R
    from mld_core.motion import skeleton as sk

    feats = np.asarray(features, dtype=np.float64)
    joints = F.features_to_joints(feats)  # (T, 22, 3)
    out = {}
    quats, root = R.features_to_rotations(feats)
    out["reference"] = np.linalg.norm(R.fk(quats, root) - joints, axis=-1) * 1000
    rest = R.rest_offsets_from_joints(joints)
    quats, root = R.features_to_rotations(feats, offsets=rest)
    out["fitted"] = np.linalg.norm(R.fk(quats, root, rest) - joints, axis=-1) * 1000
    parents = sk.PARENTS
    lengths = np.array([np.median(np.linalg.norm(joints[:, j] - joints[:, p], axis=-1)) if p >= 0 else 0.0
                        for j, p in enumerate(parents)])
    own = rest / np.maximum(np.linalg.norm(rest, axis=-1, keepdims=True), 1e-9) * lengths[:, None]
    quats, root = R.features_to_rotations(feats, offsets=own)
    out["own lengths"] = np.linalg.norm(R.fk(quats, root, own) - joints, axis=-1) * 1000
    return out


def summarise(errors: list[dict[str, np.ndarray]]) -> dict:
    rows = {}
    for kind in ("reference", "fitted", "own lengths"):
        flat = np.concatenate([e[kind].ravel() for e in errors])
        rows[kind] = {
            "motions": len(errors),
            "mean_mm": float(flat.mean()),
            "p95_mm": float(np.percentile(flat, 95)),
            "max_mm": float(flat.max()),
            "mean_of_motion_max_mm": float(np.mean([e[kind].max() for e in errors])),
        }
    return rows


def real_motions(data: Path, split: str, limit: int | None, every: int = 1) -> list[np.ndarray]:
    ids = [line.strip() for line in (data / f"{split}.txt").read_text().splitlines() if line.strip()]
    ids = ids[:: max(1, every)]
    if limit:
        ids = ids[:limit]
    motions = []
    for clip in ids:
        path = data / "new_joint_vecs" / f"{clip}.npy"
        if path.is_file():
            feats = np.load(path)
            if len(feats) >= 2:
                motions.append(feats)
    return motions


def generated_motions(prompts, seconds: float, seed: int) -> list[np.ndarray]:
    from mld_core.pipeline import MLDPipeline

    pipe = MLDPipeline.from_pretrained()
    out = pipe(list(prompts), seconds=seconds, seed=seed)
    return [np.asarray(out.features[i, : int(out.lengths[i])]) for i in range(len(prompts))]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/bandai"),
                        help="HumanML3D-format folder (default: data/bandai, as data prepare bandai writes it)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--limit", type=int, default=None, help="only the first N clips of the split")
    parser.add_argument("--every", type=int, default=1, help="every N-th clip of the split (1: all)")
    parser.add_argument("--no-real", action="store_true", help="skip the real clips")
    parser.add_argument("--generated", action="store_true", help="also takes from the bundled default model")
    parser.add_argument("--prompt", action="append", default=None, help="prompts for --generated (repeatable)")
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)

    results = {}
    if not args.no_real:
        t0 = time.perf_counter()
        motions = real_motions(args.data, args.split, args.limit, args.every)
        if not motions:
            print(f"no motions found in {args.data} ({args.split}.txt)", file=sys.stderr)
            return 2
        results[f"real {args.split}"] = summarise([fk_errors_mm(m) for m in motions])
        print(f"{len(motions)} real clips ({args.split}, every {args.every}) in {time.perf_counter() - t0:.1f} s")
    if args.generated:
        motions = generated_motions(args.prompt or DEFAULT_PROMPTS, args.seconds, args.seed)
        results["generated"] = summarise([fk_errors_mm(m) for m in motions])
    print(f"{'set':16s} {'rest':11s} {'motions':>7s} {'mean mm':>8s} {'p95 mm':>8s} {'max mm':>8s} {'mean max':>8s}")
    for name, rows in results.items():
        for kind, r in rows.items():
            print(f"{name:16s} {kind:11s} {r['motions']:7d} {r['mean_mm']:8.2f} {r['p95_mm']:8.2f} {r['max_mm']:8.2f} "
                  f"{r['mean_of_motion_max_mm']:8.2f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
