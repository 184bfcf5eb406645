"""Benchmark the add-on in bpy: model load, Generate -> keys on the canonical rig (Final and Draft), key writing.

    python scripts/bench_addon.py [--model DIR] [--prompt TEXT] [--seconds 4] [--steps 50] [--repeat 5] [--threads N]

Prints numbers (targets: load <= 2 s, Generate -> keys <= 0.5 s for one 4 s prompt with the model loaded,
key writing <= 10 ms). Without --model it uses the bundled default model, or a tiny random model when none
is bundled (then only the add-on's own overhead is meaningful). Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


CPU_TIMES: dict = {}


def median_time(fn, repeat: int, label: str = "") -> tuple[float, float]:
    """Median and min wall time; the median CPU time of this process goes to CPU_TIMES[label] (on a busy
    machine wall time includes waiting for a core, CPU time does not; with one torch thread they agree when
    the machine is idle)."""
    times, cpu = [], []
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    if label:
        CPU_TIMES[label] = statistics.median(cpu)
    return statistics.median(times), min(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", help="model folder (default: bundled, else a tiny random one)")
    parser.add_argument("--prompt", default="a person walks forward and waves with the right hand")
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--threads", type=int, default=0)
    parser.add_argument("--fps", type=int, default=24, help="scene frame rate (keys are resampled to it)")
    args = parser.parse_args(argv)
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="mld_bench_user_"))

    t0 = time.perf_counter()
    import torch

    t_torch = time.perf_counter() - t0
    if args.threads:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    import bpy

    t_bpy = time.perf_counter() - t0

    import blender_addon
    from blender_addon import env
    from blender_addon.scene import canonical_armature, read_rig, write_action
    from blender_addon.ui import runtime
    from mld_core.rig import keying

    model_dir = args.model
    note = ""
    if model_dir is None and env.bundled_model_dir() is None:
        from mld_core.testing import tiny_model

        model_dir = str(tiny_model(Path(tempfile.mkdtemp(prefix="mld_bench_")) / "tiny"))
        note = " (no bundled model: a TINY RANDOM model, so only the add-on overhead is meaningful)"
    if model_dir:
        os.environ["MLD_MODEL_DIR"] = str(model_dir)

    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_addon.register()
    try:
        scene = bpy.context.scene
        scene.render.fps = args.fps
        obj = canonical_armature.create_canonical_armature(bpy.context, body=False)
        scene.mld_motion.target = obj
        s = scene.mld_motion
        s.prompt, s.seconds, s.steps, s.seed = args.prompt, args.seconds, args.steps, 0

        c0, t0 = time.process_time(), time.perf_counter()
        pipe = runtime.cache().get(model_dir, "cpu", args.threads)
        t_load = time.perf_counter() - t0
        CPU_TIMES["load"] = time.process_time() - c0
        # warm-up (first call pays one-off allocations)
        bpy.ops.mld.generate()

        gen_med, gen_min = median_time(lambda: bpy.ops.mld.generate(), args.repeat, "generate")
        draft_med = draft_min = None
        if getattr(pipe, "draft_denoiser", None) is not None:
            s.mode = "DRAFT"
            bpy.ops.mld.generate()
            draft_med, draft_min = median_time(lambda: bpy.ops.mld.generate(), args.repeat, "draft")
            s.mode = "FINAL"

        # split: pipeline alone, rotations, pose math, key writing
        out = pipe([s.prompt], seconds=args.seconds, num_inference_steps=args.steps, seed=0)
        pipe_med, _ = median_time(
            lambda: pipe([s.prompt], seconds=args.seconds, num_inference_steps=args.steps, seed=0), args.repeat, "pipeline"
        )
        from mld_core.motion.rotations import features_to_rotations

        n = int(out.lengths[0])
        feats = out.features[0, :n]
        rot_med, _ = median_time(lambda: features_to_rotations(feats), args.repeat, "rotations")
        quats, _root = features_to_rotations(feats)
        rest = read_rig.read_rig(obj)
        fps = scene.render.fps / scene.render.fps_base
        take = keying.Take(out.joints[0, :n], quats, None, 20)
        bone_map = keying.canonical_map(rest.names)
        settings = keying.RetargetSettings()

        def plan():
            return keying.take_keys(take, rest, bone_map, settings, fps=fps, frame_start=1, exact=True)

        pose_med, _ = median_time(plan, args.repeat, "pose")
        keys = plan()
        created = []

        def write():
            created.append(write_action.keys_to_action(obj, keys, "bench", assign=False))

        key_med, key_min = median_time(write, max(args.repeat, 10), "keys")
        n_keys = keys.num_keys
        for action in created:
            bpy.data.actions.remove(action)
    finally:
        blender_addon.unregister()

    c = CPU_TIMES
    print(f"model: {getattr(pipe, 'model_id', '?')}{note}")
    print(f"cpu threads: {torch.get_num_threads()}, scene {args.fps} fps, {args.seconds:g} s prompt, {args.steps} steps")
    print(f"{'':38s}{'wall':>9s} {'(min)':>9s} {'cpu':>9s}")
    print(f"{'import torch':38s}{t_torch:9.3f}")
    print(f"{'import bpy':38s}{t_bpy:9.3f}")
    print(f"{'model load (once; target <= 2 s)':38s}{t_load:9.3f} {'':9s} {c['load']:9.3f}")
    print(f"{'Generate -> keys (target <= 0.5 s)':38s}{gen_med:9.3f} {gen_min:9.3f} {c['generate']:9.3f}")
    if draft_med is not None:
        print(f"{'Generate -> keys, Draft':38s}{draft_med:9.3f} {draft_min:9.3f} {c['draft']:9.3f}"
              f"   ({draft_med / gen_med:.2f} x Final)")
    else:
        print("Generate -> keys, Draft: the model has no Draft denoiser")
    print(f"{'  pipeline (text, DDIM, decode)':38s}{pipe_med:9.3f} {'':9s} {c['pipeline']:9.3f}")
    print(f"{'  features -> rotations':38s}{rot_med:9.4f} {'':9s} {c['rotations']:9.4f}")
    print(f"{'  pose channels (+ resample)':38s}{pose_med:9.4f} {'':9s} {c['pose']:9.4f}")
    print(f"{f'  key writing ({n_keys} keys; <= 10 ms)':38s}{key_med:9.4f} {key_min:9.4f} {c['keys']:9.4f}")
    print("seconds; wall = median elapsed, cpu = median CPU time of this process")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
