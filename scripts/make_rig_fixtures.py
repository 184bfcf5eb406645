"""Write the rest poses of a few real rigs to tests/fixtures/rigs/ (needs bpy; run with the dev venv's python).

    python scripts/make_rig_fixtures.py [--bvh tests/fixtures/bandai/dataset-1_bye_normal_001.bvh]

Writes canonical.json (the canonical armature built in Blender from retarget.canonical_rig()), rigify_metarig.json
(Rigify's human metarig), rigify.json (the rig Rigify generates from it) and bandai_bvh.json (a Bandai clip
imported with Blender's own BVH importer at scale 0.01). Each is a RigRest: names, parents, rest matrices
(bone.matrix_local, armature space), tails and the object's world matrix.

Also writes source_takes.npz: the Bandai fixture clips (tests/fixtures/bandai/*.bvh) as the model's data sees them
(canonical joints (T, 22, 3) at 20 fps, facing +Z; foot contacts (T, 4)), so retargeting tests need neither torch
nor the BVH reader.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def write_source_takes(path: Path) -> None:
    import numpy as np

    from mld_core.data.bandai import clip_joints
    from mld_core.motion import features as F

    arrays = {}
    for bvh in sorted((REPO / "tests/fixtures/bandai").glob("*.bvh")):
        joints = F.canonical_joints(clip_joints(bvh.read_bytes(), source=str(bvh)))
        contacts = F.joints_to_features(joints)[:, F.FOOT_CONTACT]
        arrays[f"{bvh.stem}_joints"] = joints.astype(np.float32)
        arrays[f"{bvh.stem}_contacts"] = np.concatenate([contacts, contacts[-1:]], 0).astype(np.float32)
    np.savez_compressed(path, **arrays)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bvh", default=str(REPO / "tests/fixtures/bandai/dataset-1_bye_normal_001.bvh"))
    parser.add_argument("--out", default=str(REPO / "tests/fixtures/rigs"))
    args = parser.parse_args(argv)
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="mld_bpy_"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_source_takes(out / "source_takes.npz")

    import bpy  # noqa: I001 - bpy first: it puts addon_utils on the path
    import addon_utils

    from mld_core.rig import retarget as rt
    from blender_addon.scene import read_rig as rig_io

    bpy.ops.wm.read_factory_settings(use_empty=True)

    canonical = rig_io.build_armature(rt.canonical_rig(), "canonical")
    rig_io.read_rig(canonical).save(out / "canonical.json")

    addon_utils.enable("rigify", default_set=True)
    bpy.ops.object.armature_human_metarig_add()
    metarig = bpy.context.object
    rig_io.read_rig(metarig).save(out / "rigify_metarig.json")
    bpy.ops.pose.rigify_generate()
    rig_io.read_rig(bpy.context.object).save(out / "rigify.json")

    addon_utils.enable("io_anim_bvh", default_set=True)
    bpy.ops.import_anim.bvh(filepath=args.bvh, global_scale=0.01)
    bvh_rig = rig_io.read_rig(bpy.context.object)
    bvh_rig.name = "bandai_bvh"
    bvh_rig.save(out / "bandai_bvh.json")
    for path in sorted(out.glob("*.json")):
        print(f"{path.relative_to(REPO)}: {path.stat().st_size / 1024:.0f} KB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
