"""Our BVH reading against Blender's own BVH importer: the same files, the 22 mapped joints, frame by frame.

    python scripts/bvh_import_check.py SRC [--per-folder 3] [--frames 60]

For the first files of each top-level folder under SRC: Blender imports the file (Y up -> Z up, scale 1, file units),
and the world position of every mapped bone's head is compared with ``mld_core``'s forward kinematics of the same
frames (``Bvh.joint_positions``), as a fraction of the leg length. Runs Blender as a Python module in this process.
Prints one line per folder: the files compared and the largest joint difference as a fraction of the leg length.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mld_core.data import bvh_library as bl  # noqa: E402
from mld_core.motion.bvh import read_bvh  # noqa: E402
from mld_core.rig.bone_maps import detect_bone_map  # noqa: E402


def blender_heads(bpy, path: Path, bones: list[str], frames: int) -> np.ndarray:
    """(F, len(bones), 3) world heads after Blender's import, in Blender axes (Z up)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_anim.bvh(filepath=str(path), global_scale=1.0, frame_start=1, use_fps_scale=False,
                            update_scene_fps=False, update_scene_duration=True, rotate_mode="NATIVE")
    obj = bpy.context.object
    scene = bpy.context.scene
    out = np.zeros((frames, len(bones), 3))
    for f in range(frames):
        scene.frame_set(f + 1)
        world = np.asarray(obj.matrix_world, np.float64)
        out[f] = [world[:3, :3] @ np.asarray(obj.pose.bones[b].head) + world[:3, 3] for b in bones]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("--per-folder", type=int, default=3)
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args(argv)
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="mld-bvh-check-"))
    import bpy

    chosen = defaultdict(list)
    for path in bl.find_bvh(args.src):
        folder = path.relative_to(args.src).parts[0]
        if len(chosen[folder]) < args.per_folder:
            chosen[folder].append(path)
    for folder, paths in sorted(chosen.items()):
        errors = []
        for path in paths:
            bvh = read_bvh(path)
            found = detect_bone_map(bvh.names, list(bvh.parents))
            bones = list(found.bone_map.joints.values())
            frames = min(args.frames, bvh.num_frames)
            ours = bvh.joint_positions()[:frames][:, [bvh.index(b) for b in bones]]  # (F, K, 3) file axes
            ours = np.stack([ours[..., 0], -ours[..., 2], ours[..., 1]], axis=-1)  # Y up -> Blender's Z up
            theirs = blender_heads(bpy, path, bones, frames)
            leg = bl.leg_length(bl.mapped_joints(bvh, found.bone_map)[:frames])
            errors.append(np.linalg.norm(ours - theirs, axis=-1).max() / leg)
        print(f"{folder:8s} {len(paths)} files: largest joint difference {max(errors):.2e} of the leg length")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
