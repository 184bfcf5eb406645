"""Round-trip error of ``data prepare bvh`` per folder (skeleton convention): BVH -> 22 joints -> features -> joints.

    python scripts/library_roundtrip.py SRC [--template "a person {name}"]

For every BVH under SRC that maps, the mapped joints (after the up axis, units, T-pose trim and 20 fps resampling,
on the one reference skeleton the features describe) against the joints recovered from their features: mean and
max joint error in mm, per top-level folder. Prints one line per folder: files, mean and max error.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mld_core.data import bvh_library as bl  # noqa: E402
from mld_core.motion.bvh import read_bvh  # noqa: E402
from mld_core.motion.features import canonical_joints, features_to_joints, joints_to_features  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    args = ap.parse_args(argv)
    errors = defaultdict(list)
    for path in bl.find_bvh(args.src):
        bvh = read_bvh(path)
        try:
            joints, _ = bl.library_joints(bvh, bl.skeleton_map(bvh), bl.LibraryOptions())
        except bl.PrepareError:
            continue  # a skeleton that does not map
        if len(joints) < 3:
            continue
        target = canonical_joints(joints)[:-1]  # (T-1, 22, 3): what the features describe
        back = features_to_joints(joints_to_features(joints))
        e = np.linalg.norm(back - target, axis=-1) * 1000
        folder = path.relative_to(args.src).parts[0] if len(path.relative_to(args.src).parts) > 1 else "."
        errors[folder].append((e.mean(), e.max()))
    for folder, rows in sorted(errors.items()):
        rows = np.array(rows)
        print(f"{folder:10s} {len(rows):4d} files  mean {rows[:, 0].mean():.4f} mm  max {rows[:, 1].max():.4f} mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
