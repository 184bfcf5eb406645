"""Live Preview in bpy: how long the main thread stalls while the user edits, and how soon the preview shows.

    python scripts/bench_live_preview.py [--model DIR] [--edits 20] [--interval 0.05] [--threads N] [--rig canonical|rigify]

The bpy module has no event loop, so this script is one: it makes ``--edits`` prompt edits ``--interval`` seconds
apart (typing), then ``--edits`` seed changes 0.4 s apart (each one outlasts the 0.3 s debounce, so each starts a
job while the last may still run), and between them calls Blender's timers when due (Live Preview's debounce
timer, the job runner's 50 ms tick). Every main-thread call is timed: the property update callbacks, the timers,
the keying of each finished preview. Prints the longest stall (target <= 50 ms), the jobs submitted, cancelled and
keyed, and the time from the last edit to its preview on the armature. Not a test: nothing is asserted.
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


class MainThread:
    """Times every call made on the main thread."""

    def __init__(self):
        self.calls: list[tuple[str, float]] = []

    def run(self, label: str, fn):
        t0 = time.perf_counter()
        result = fn()
        self.calls.append((label, time.perf_counter() - t0))
        return result

    def longest(self, label: str | None = None) -> float:
        times = [t for name, t in self.calls if label is None or name == label]
        return max(times) if times else 0.0


def event_loop(main: MainThread, until: float, next_tick: list) -> None:
    """Blender's timers until ``until`` (perf_counter): Live Preview's debounce timer when due, the runner's tick
    every 50 ms."""
    from blender_addon.ui import live_preview, runtime

    live = live_preview.live()
    while time.perf_counter() < until:
        if live.waiting and live.seconds_to_wait() == 0.0:
            main.run("debounce timer (submit)", live_preview.fire)
        if time.perf_counter() >= next_tick[0]:
            main.run("runner tick (keys a finished preview)", runtime._tick)
            next_tick[0] = time.perf_counter() + runtime.TICK_SECONDS
        time.sleep(0.002)


def edit_phase(main: MainThread, settings, edits: int, interval: float, change) -> float:
    """``edits`` edits ``interval`` apart; returns the time of the last one."""
    next_tick = [time.perf_counter()]
    last = 0.0
    for k in range(edits):
        main.run("property edit (update callbacks)", lambda: change(settings, k))
        last = time.perf_counter()
        event_loop(main, last + interval, next_tick)
    return last


def settle(main: MainThread, timeout: float = 30.0) -> float:
    """Run the loop until the newest preview is keyed; returns when that happened."""
    from blender_addon.ui import live_preview, runtime

    live = live_preview.live()
    next_tick = [time.perf_counter()]
    end = time.perf_counter() + timeout
    while time.perf_counter() < end:
        event_loop(main, time.perf_counter() + 0.01, next_tick)
        job = live.job
        if not live.waiting and (job is None or (job.ended and job.id not in runtime._targets)):
            return time.perf_counter()
    return float("nan")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", help="model folder (default: the bundled one)")
    parser.add_argument("--edits", type=int, default=20)
    parser.add_argument("--interval", type=float, default=0.05, help="seconds between typed edits")
    parser.add_argument("--threads", type=int, default=0, help="torch threads of the worker (0: default)")
    parser.add_argument("--rig", choices=("canonical", "rigify"), default="canonical")
    args = parser.parse_args(argv)
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="mld_bench_user_"))
    if args.model:
        os.environ["MLD_MODEL_DIR"] = str(args.model)
    import bpy

    import blender_addon
    from blender_addon.scene import canonical_armature, take_review
    from blender_addon.ui import live_preview, runtime

    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_addon.register()
    try:
        scene = bpy.context.scene
        if args.rig == "rigify":
            import addon_utils

            addon_utils.enable("rigify", default_set=True)
            bpy.ops.object.armature_human_metarig_add()
            metarig = bpy.context.object
            bpy.ops.pose.rigify_generate()
            obj = bpy.data.objects["rig"]
            metarig.hide_set(True)
        else:
            obj = canonical_armature.create_canonical_armature(bpy.context, body=False)
        s = scene.mld_motion
        s.target = obj
        s.prompt, s.seconds, s.seed = "a person walks forward", 4.0, 0
        pipe = runtime.cache().get(args.model, "cpu", args.threads)
        if getattr(pipe, "draft_denoiser", None) is None:
            print(f"the model {pipe.model_id} has no Draft denoiser: Live Preview needs one")
            return 2
        pipe("warm up", 4.0, draft=True)
        main_thread = MainThread()
        main_thread.run("Live Preview on", lambda: setattr(s, "live_preview", True))
        settle(main_thread)
        text = "a person walks forward and waves with the right hand"
        words = text.split()
        typed = edit_phase(main_thread, s, args.edits, args.interval,
                           lambda st, k: setattr(st, "prompt", " ".join(words[: 2 + k % (len(words) - 1)])))
        shown_typed = settle(main_thread)
        dragged = edit_phase(main_thread, s, args.edits, 0.4, lambda st, k: setattr(st, "seed", k + 1))
        shown_dragged = settle(main_thread)
        live = live_preview.live()
        preview = obj.animation_data.action
        ok = take_review.pending(obj) == [preview.name] and bool(preview.get("mld_draft"))
        main_thread.run("Live Preview off", lambda: setattr(s, "live_preview", False))
    finally:
        blender_addon.unregister()

    calls = [t for _, t in main_thread.calls]
    print(f"model: {pipe.model_id}, rig: {args.rig} ({obj.name}, {len(obj.data.bones)} bones), worker threads: "
          f"{args.threads or 'default'}")
    print(f"{args.edits} typed edits {1000 * args.interval:.0f} ms apart, then {args.edits} seed changes 400 ms apart")
    print(f"main-thread calls: {len(calls)}; longest stall {1000 * max(calls):.1f} ms (target <= 50 ms); "
          f"95th percentile {1000 * statistics.quantiles(calls, n=20)[-1]:.1f} ms")
    for label in sorted({name for name, _ in main_thread.calls}):
        print(f"  {label:42s} longest {1000 * main_thread.longest(label):6.1f} ms")
    print(f"jobs submitted {live.submitted}, cancelled {live.cancelled} (the newest wins)")
    print(f"last typed edit -> its preview keyed: {shown_typed - typed:.3f} s (0.3 s of it is the debounce)")
    print(f"last seed change -> its preview keyed: {shown_dragged - dragged:.3f} s")
    print(f"the armature shows the newest Draft preview, pending: {ok}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
