"""The add-on's live state: the model cache, the job runner, the timer that applies finished jobs (bpy).

The worker thread never touches bpy. ``bpy.app.timers`` calls :func:`_tick` on the main thread while jobs
are in flight; it applies finished jobs to their armatures (one undo step each), stores the outcome on the
scene settings for the panel, and redraws the sidebar.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from ..worker.generation import make_work
from ..installer import DependencyInstaller
from ..worker.jobs import CANCELLED, DONE, JobRunner
from ..worker.model_cache import PipelineCache

TICK_SECONDS = 0.05

_cache: PipelineCache | None = None
_runner: JobRunner | None = None
_installer: DependencyInstaller | None = None


@dataclass
class Target:
    """Where a submitted job's result goes (looked up again when it finishes: the user may have moved on)."""

    object_name: str
    object_uid: int | None
    scene_name: str
    exact: bool
    set_frame_range: bool
    options: object = None  # apply.RetargetSettings as they were when Generate was pressed (None: read them at the end)
    preview: bool = False  # the takes stay pending until Accept or Reject (scene/take_review.py)
    live: bool = False  # a Live Preview take (ui/live_preview.py): dropped if Live Preview was turned off meanwhile


_targets: dict[int, Target] = {}


def cache() -> PipelineCache:
    global _cache
    if _cache is None:
        _cache = PipelineCache()
    return _cache


def runner() -> JobRunner:
    global _runner
    if _runner is None:
        _runner = JobRunner(make_work(cache()))
    return _runner


def installer() -> DependencyInstaller:
    global _installer
    if _installer is None:
        _installer = DependencyInstaller()
    return _installer


def busy() -> bool:
    return _runner is not None and _runner.busy


def current_job():
    return _runner.current if _runner is not None else None


def submit(request, target: Target):
    job = runner().submit(request)
    _targets[job.id] = target
    ensure_timer()
    return job


def ensure_timer() -> None:
    import bpy

    if not bpy.app.timers.is_registered(_tick):
        bpy.app.timers.register(_tick, first_interval=TICK_SECONDS)


def _find_object(target: Target):
    import bpy

    if target.object_uid is not None:
        for obj in bpy.data.objects:
            if getattr(obj, "session_uid", None) == target.object_uid:
                return obj
    return bpy.data.objects.get(target.object_name)


def settings_of(scene):
    return getattr(scene, "mld_motion", None)


def record_outcome(scene, *, message: str = "", error: str = "", seconds: float = 0.0, frames: int = 0, actions=()):
    """Store the last outcome on the scene settings (shown by the panel)."""
    settings = settings_of(scene)
    if settings is None:
        return
    settings.last_error = error
    settings.last_message = message
    settings.last_seconds = seconds
    settings.last_frames = frames
    settings.last_actions = ", ".join(actions)


def finish_job(job, target: Target | None) -> tuple[str, str]:
    """Apply (or report) one ended job on the main thread; returns (level, message) for a report."""
    import bpy

    from mld_core.take_report import seam_lines, side_report

    from ..scene.key_takes import apply_result

    scene = bpy.data.scenes.get(target.scene_name) if target else None
    scene = scene or bpy.context.scene
    if job.state == CANCELLED and target is not None and target.live:
        return "INFO", "Live Preview: a newer edit replaced this take"
    if job.state == CANCELLED:
        record_outcome(scene, message="Cancelled")
        return "WARNING", "Generation cancelled"
    if job.state != DONE:
        if job.details:
            print(f"MLD: generation failed:\n{job.details}", file=sys.stderr)
        record_outcome(scene, error=job.error)
        return "ERROR", job.error
    if target.live and not getattr(settings_of(scene), "live_preview", False):
        return "INFO", "Live Preview is off: its last take was dropped"
    obj = _find_object(target) if target else None
    if obj is None:
        error = f"The armature {target.object_name if target else ''!r} is gone; nothing was keyed"
        record_outcome(scene, error=error)
        return "ERROR", error
    previous = obj.animation_data.action.name if obj.animation_data and obj.animation_data.action else ""
    try:
        report = apply_result(obj, job.result, scene, exact=target.exact, set_frame_range=target.set_frame_range,
                              options=target.options, ik_controls=not target.live)
        if target.preview:
            from ..scene import take_review

            take_review.mark_pending(obj, report.actions, previous)
    except Exception as exc:  # noqa: BLE001 - reach the user as a message, never a traceback
        import traceback

        traceback.print_exc()
        record_outcome(scene, error=str(exc))
        return "ERROR", str(exc)
    elapsed = job.elapsed
    message = f"{', '.join(report.actions)}: {report.frames} frames at {report.fps:g} fps in {elapsed:.2f} s"
    first = job.result.takes[0] if job.result.takes else None
    if first is not None:
        _, side_text = side_report(first.prompt, getattr(first.badges, "side", None), first.draw,
                                   redrawn_for=first.redrawn_for, verb=getattr(first.badges, "verb", None))
        message += f"; {side_text}" if side_text else ""
        for seam in seam_lines(first.seams, [prompt for prompt, _ in first.segments or []]):
            message += f"; {seam}"
    if target.live:
        message = f"Live Preview: {message}"
    record_outcome(scene, message=message, seconds=elapsed, frames=report.frames, actions=report.actions)
    return "INFO", message


def _tick():
    import bpy

    run = _runner
    if run is None:
        return None
    for job in run.finished():
        target = _targets.pop(job.id, None)
        if target is None:
            continue  # submitted before another file was loaded: its armature is not in this file
        level, message = finish_job(job, target)
        if target.live and level != "ERROR":
            continue  # previews are not undo steps and do not fill the status bar
        if job.state == DONE and level == "INFO":
            try:  # the keys are one undo step
                bpy.ops.ed.undo_push(message="Generate Motion")
            except Exception:  # noqa: BLE001 - undo is a convenience
                pass
        print(f"MLD: {message}", file=sys.stderr if level == "ERROR" else sys.stdout)
        _notify(level, message)
    tag_redraw()
    return TICK_SECONDS if run.busy else None


def _notify(level: str, message: str) -> None:
    """Show a message in the status bar (reports from a timer have no operator to carry them)."""
    import bpy

    wm = bpy.context.window_manager
    if wm is None or not wm.windows:
        return
    try:
        with bpy.context.temp_override(window=wm.windows[0]):
            bpy.ops.mld.report("INVOKE_DEFAULT", level=level, message=message[:500])
    except Exception:  # noqa: BLE001 - no window: the panel still shows it
        pass


def tag_redraw() -> None:
    import bpy

    wm = bpy.context.window_manager
    if wm is None:
        return
    for window in wm.windows:
        for area in window.screen.areas:
            if area.type in {"VIEW_3D", "PREFERENCES"}:
                area.tag_redraw()


def forget_targets(*_args) -> None:
    """Before another file loads: cancel running jobs, their armatures belong to the old file."""
    if _runner is not None:
        _runner.cancel_all()
    _targets.clear()


def shutdown() -> None:
    """Cancel jobs and stop the worker and the timer (unregister)."""
    global _runner
    import bpy

    if _runner is not None:
        _runner.shutdown(cancel=True, timeout=2.0)
        _runner = None
    _targets.clear()
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)
