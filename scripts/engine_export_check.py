"""Takes into a game engine, measured: walks made by a model, exported in place and with a root bone, imported back.

    python scripts/engine_export_check.py [--model DIR] [--seeds 4] [--seconds 4] [--format fbx|glb] [--keep DIR]

Runs the batch (Blender as a Python module, in this process) on "a person walks forward" for each seed, plus one
looped 2 s walk, exports every take with ``--root-motion root-bone`` and again ``in-place``, imports each file into
an empty Blender and prints, per take:

* travel: the hips' net travel over the ground in the take (first frame to last) and in the in-place file;
* sway: the hips' side-to-side sway (standard deviation across the walk's direction about its 1 s moving average)
  in the take and in the in-place file;
* root-bone: the largest distance between the hips (and between any joint) played from the imported file (root +
  hips) and in the take;
* the loop's seam: the gap the model left (manifest) and the gap between the in-place file's first and last frames.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", help="model folder (default: the bundled model)")
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--format", choices=("fbx", "glb"), default="fbx")
    parser.add_argument("--keep", help="write the files here (default: a temporary folder)")
    return parser.parse_args(argv)


def played(arm, action, scene) -> tuple[np.ndarray, list]:
    """World heads (T, B, 3) of ``arm``'s bones playing ``action``, and the bones' names."""
    ad = arm.animation_data or arm.animation_data_create()
    ad.action = action
    if hasattr(ad, "action_slot") and len(getattr(action, "slots", ())):
        ad.action_slot = action.slots[0]
    first, last = (int(round(v)) for v in action.frame_range)
    heads = []
    for frame in range(first, last + 1):
        scene.frame_set(frame)
        m = np.asarray(arm.matrix_world)
        heads.append([m[:3, :3] @ np.asarray(pb.head) + m[:3, 3] for pb in arm.pose.bones])
    return np.array(heads), [pb.name for pb in arm.pose.bones]


def imported(path: Path, fmt: str, fps: float) -> dict:
    """{take: (heads (T, B, 3), bone names)} of a file imported into an empty Blender (bones disconnected: Blender's
    FBX importer connects a child whose head meets its parent's tail, which engines do not)."""
    import addon_utils
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    for module in ("io_scene_fbx", "io_scene_gltf2"):
        addon_utils.enable(module, default_set=True)
    bpy.context.scene.render.fps, bpy.context.scene.render.fps_base = int(round(fps)), 1.0
    (bpy.ops.import_scene.fbx if fmt == "fbx" else bpy.ops.import_scene.gltf)(filepath=str(path))
    arm = next(o for o in bpy.data.objects if o.type == "ARMATURE")
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    for bone in arm.data.edit_bones:
        bone.use_connect = False
    bpy.ops.object.mode_set(mode="OBJECT")
    return {a.name.split("|")[-1]: played(arm, a, bpy.context.scene) for a in bpy.data.actions}


def sway(hips: np.ndarray, direction: np.ndarray, fps: float) -> float:
    """Std (m) of the hips' ground position across ``direction`` about its own 1 s moving average: the gait's
    side-to-side sway (a stride's cycle averages out over a second), without the path's slow bends."""
    across = hips[:, :2] @ np.array([-direction[1], direction[0]])
    width = int(round(fps)) | 1  # an odd number of frames, centred
    average = np.convolve(across, np.ones(width) / width, mode="valid")
    return float(np.std(across[width // 2: width // 2 + len(average)] - average))


def main(argv=None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="mld-blender-user-"))
    import bpy

    from blender_addon import batch
    from blender_addon.scene import export_takes, key_takes
    from mld_core.fileio import OutputSet
    from mld_core.rig import engine_export as ee

    work = Path(args.keep or tempfile.mkdtemp(prefix="mld-engine-"))
    work.mkdir(parents=True, exist_ok=True)
    jobs = [{"prompt": "a person walks forward", "seconds": args.seconds, "seed": s} for s in range(args.seeds)]
    jobs.append({"prompt": "a person walks forward", "seconds": 2.0, "seed": 0, "loop": True})
    (work / "jobs.json").write_text(json.dumps({"jobs": jobs}))
    argv = ["batch.py", "--jobs", str(work / "jobs.json"), "--out", str(work / "root_bone" / "takes.blend"),
            "--export", args.format, "--root-motion", "root-bone", "--overwrite"]
    if args.model:
        argv += ["--model", args.model]
    if batch.main(argv) != 0:
        return 1
    manifest = json.loads((work / "root_bone" / "takes.json").read_text())
    scene, obj = bpy.context.scene, bpy.data.objects["MLD_Armature"]
    fps = scene.render.fps / scene.render.fps_base
    actions = [bpy.data.actions[t["name"]] for t in manifest["takes"]]
    truth = {a.name: played(obj, a, scene) for a in actions}
    settings = ee.ExportSettings((args.format,), "in-place")
    files = ee.export_files(work / "in_place", "takes", [a.name for a in actions], settings)
    with OutputSet(overwrite=True) as outputs:
        in_place = export_takes.export_takes(obj, actions, files, settings, outputs,
                                             bone_map=key_takes.bone_map_of(obj))
    rooted = {f["takes"][0]: imported(Path(f["path"]), args.format, fps) for f in manifest["export"]["files"]}
    placed = {f["takes"][0]: imported(Path(f["path"]), args.format, fps) for f in in_place["files"]}
    print(f"model {manifest['model_id']}, {args.format.upper()}, {fps:g} fps; files in {work}")
    print("| take | frames | hips travel: take / in place (cm) | sway: take / in place (cm) | root-bone: hips / "
          "any joint (mm) | loop seam: model / in place (cm) |")
    print("|---|---|---|---|---|---|")
    for record in manifest["takes"]:  # (the Actions are gone with the scene: the files were imported since)
        name = record["name"]
        heads, names = truth[name]
        hips = names.index("pelvis")
        back, back_names = rooted[name][name]
        order = [back_names.index(n) for n in names]
        error = np.linalg.norm(back[:, order] - heads, axis=-1)
        still, still_names = placed[name][name]
        still_hips = still[:, still_names.index("pelvis")]
        step = heads[-1, hips, :2] - heads[0, hips, :2]
        direction = step / max(np.linalg.norm(step), 1e-9)
        travel = np.linalg.norm(step) * 100
        travel_after = np.linalg.norm(still_hips[-1, :2] - still_hips[0, :2]) * 100
        seam = in_place["takes"][name].get("seam")
        seam_text = "-"
        if seam:
            seam_text = f"{seam['gap_cm']:.2f} / {np.linalg.norm(still[-1] - still[0], axis=-1).max() * 100:.3f}"
        print(f"| {name}{' (loop)' if record.get('loop') else ''} | {len(heads)} | {travel:.1f} / {travel_after:.2f} "
              f"| {sway(heads[:, hips], direction, fps) * 100:.2f} / {sway(still_hips, direction, fps) * 100:.2f} "
              f"| {error[:, hips].max() * 1000:.3f} / {error.max() * 1000:.3f} | {seam_text} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
