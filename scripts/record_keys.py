"""Record the F-curves the add-on writes, so a change of its code can prove that its output did not change.

    python scripts/record_keys.py --out tests/fixtures/rigs/keys_reference.npz     # record (bpy module)
    python scripts/record_keys.py --compare tests/fixtures/rigs/keys_reference.npz # compare, print the largest gap

Keys the fixture takes (tests/fixtures/rigs/source_takes.npz: real Bandai clips as the model sees them: a turning walk, and a wave on
the canonical armature) onto
the canonical armature (its exact road, and the bone-map road with key reduction, Euler rotations and foot lock),
Rigify's human metarig (default options, and reduced) and a Bandai clip imported by Blender's BVH importer, all
through ``apply.apply_result`` (what the Generate operator and the batch call). Every F-curve of every new Action
is stored: data path, index, keyframe coordinates, handles and interpolation. Runs Blender as a Python module in
this process (point BLENDER_USER_RESOURCES at a scratch folder).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

TAKES = REPO / "tests/fixtures/rigs/source_takes.npz"
BVH_RIG = REPO / "tests/fixtures/bandai/dataset-1_bye_normal_001.bvh"
INTERPOLATIONS = ("CONSTANT", "LINEAR", "BEZIER")

# (name, rig, options for RetargetSettings, exact)
CASES = [
    ("canonical_exact", "canonical", {}, True),
    ("canonical_reduced_euler_footlock", "canonical",
     {"reduce": True, "rotation_mode": "XYZ", "foot_lock": True}, True),
    ("metarig", "rigify_metarig", {}, True),
    ("metarig_reduced", "rigify_metarig", {"reduce": True}, True),
    ("bandai_bvh_reduced", "bandai_bvh", {"reduce": True}, True),
]


def source_takes():
    """Takes of the add-on's kind from the fixture joints (features -> rotations, as generation does)."""
    from blender_addon.worker.generation import Take, rotations_from_features
    from blender_addon.worker.validation import validate_request
    from mld_core.motion.features import features_to_joints, joints_to_features

    data = np.load(TAKES)
    takes = []
    for i, key in enumerate(["dataset-2_walk-turn-left_normal_027_joints", "dataset-2_wave-right-hand_normal_026_joints"]):
        features = joints_to_features(np.asarray(data[key], np.float64))
        quats, root = rotations_from_features(features)
        joints = np.asarray(features_to_joints(features), np.float64)
        request = validate_request("a person walks", 2.0, seed=i)
        takes.append(Take(prompt=key[: -len("_joints")], seed=i, variant=0, request=request, joints=joints,
                          local_quats=quats, root_positions=root, fps=20, model_id="fixture", guidance=None, steps=50,
                          seconds_generated=0.0, name=f"take{i}", contacts=np.asarray(features[:, -4:], np.float64)))
    return takes


def build_rig(bpy, kind: str):
    import addon_utils

    from blender_addon.scene import canonical_armature as rig

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.context.scene.render.fps = 24  # resampling is part of the road
    if kind == "canonical":
        return rig.create_canonical_armature(bpy.context, body=False)
    if kind == "rigify_metarig":
        addon_utils.enable("rigify", default_set=True)
        bpy.ops.object.armature_human_metarig_add()
        return bpy.context.object
    addon_utils.enable("io_anim_bvh", default_set=True)
    bpy.ops.import_anim.bvh(filepath=str(BVH_RIG), global_scale=0.01)
    obj = bpy.context.object
    obj.animation_data.action = None
    return obj


def record(bpy) -> dict:
    from blender_addon.scene import key_takes as apply
    from blender_addon.worker.generation import GenerationResult
    from blender_addon.scene.write_action import fcurves_of
    from mld_core.rig.keying import RetargetSettings

    arrays = {}
    takes = source_takes()
    for name, kind, options, exact in CASES:
        obj = build_rig(bpy, kind)
        result = GenerationResult(takes if kind == "canonical" else takes[:1], takes[0].request)
        report = apply.apply_result(obj, result, bpy.context.scene, exact=exact, options=RetargetSettings(**options))
        for t, action_name in enumerate(report.actions):
            for fc in fcurves_of(bpy.data.actions[action_name]):
                n = len(fc.keyframe_points)
                values = {}
                for attr in ("co", "handle_left", "handle_right"):
                    flat = np.zeros(2 * n, np.float64)
                    fc.keyframe_points.foreach_get(attr, flat)
                    values[attr] = flat.reshape(n, 2)
                interp = np.array([INTERPOLATIONS.index(k.interpolation) for k in fc.keyframe_points], np.int8)
                key = f"{name}/{t}/{fc.data_path}/{fc.array_index}"
                arrays[key + "/co"] = values["co"].astype(np.float32)
                arrays[key + "/handles"] = np.stack([values["handle_left"], values["handle_right"]], 1).astype(np.float32)
                arrays[key + "/interpolation"] = interp
    return arrays


def compare(recorded: dict, reference: dict) -> tuple[float, list]:
    """(largest absolute difference over matching arrays, list of problems: missing/extra curves, shape changes)."""
    problems = sorted(f"missing {k}" for k in set(reference) - set(recorded))
    problems += sorted(f"extra {k}" for k in set(recorded) - set(reference))
    worst = 0.0
    for key in sorted(set(reference) & set(recorded)):
        a, b = np.asarray(recorded[key]), np.asarray(reference[key])
        if a.shape != b.shape:
            problems.append(f"{key}: shape {a.shape} != {b.shape}")
            continue
        if key.endswith("/interpolation"):
            if (a != b).any():
                problems.append(f"{key}: interpolation differs")
            continue
        worst = max(worst, float(np.abs(a - b).max()) if a.size else 0.0)
    return worst, problems


def main(argv=None) -> int:
    import os
    import tempfile

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--out", type=Path, help="write the recording here (.npz)")
    group.add_argument("--compare", type=Path, help="compare with this recording; exit 1 when it differs")
    parser.add_argument("--tolerance", type=float, default=1e-5,
                        help="largest difference allowed (float32 storage: ~4e-6 on frame numbers near 50)")
    args = parser.parse_args(argv)
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="mld_record_keys_"))
    import bpy

    arrays = record(bpy)
    if args.out:
        np.savez_compressed(args.out, **arrays)
        print(f"wrote {args.out}: {sum(k.endswith('/co') for k in arrays)} F-curves")
        return 0
    reference = dict(np.load(args.compare))
    worst, problems = compare(arrays, reference)
    print(f"{sum(k.endswith('/co') for k in reference)} F-curves; largest difference {worst:.3g}; "
          f"{len(problems)} structural differences")
    for line in problems[:20]:
        print("  " + line)
    return 0 if worst <= args.tolerance and not problems else 1


if __name__ == "__main__":
    raise SystemExit(main())
