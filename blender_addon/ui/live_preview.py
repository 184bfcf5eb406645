"""Live Preview (bpy, main thread): while it is on, each edit of the prompt, seconds or seed regenerates a Draft take
onto a preview Action on the armature, once the edits pause (worker.live: 0.3 s, the newest request wins). Nothing
is kept: Keep makes the take as Generate does; turning it off gives the armature back the Action it had."""

from __future__ import annotations

import bpy

from . import runtime
from ..worker.live import LivePreview

_live: LivePreview | None = None
_plans: dict = {}  # (armature, keying settings, scene rate and start) -> its KeyPlan, read once per Live Preview


def live() -> LivePreview:
    global _live
    if _live is None:
        _live = LivePreview(_submit)
    return _live


def _submit(pending):
    request, target = pending
    return runtime.submit(request, target)


def edited(settings, context) -> None:
    """Update callback of the prompt, seconds and seed: schedule a preview once the edits pause."""
    if not getattr(settings, "live_preview", False):
        return
    live().edited()
    if not bpy.app.timers.is_registered(fire):
        bpy.app.timers.register(fire, first_interval=live().debounce_s)


def toggled(settings, context) -> None:
    """Update callback of the Live Preview toggle."""
    if settings.live_preview:
        edited(settings, context)
    else:
        stop(context)


def fire():
    """Timer: submit the newest settings as a Draft preview once the edits have paused."""
    wait = live().seconds_to_wait()
    if wait > 0:
        return wait
    context = bpy.context
    settings = getattr(context.scene, "mld_motion", None)
    if settings is None or not settings.live_preview:
        live().stop()
        return None
    pending = preview_request(context)
    if pending is None:
        live().stop()
        return None
    live().fire(pending)
    return None


def preview_request(context):
    """(request, runtime.Target) of a Draft preview of the panel's settings, or None with the reason recorded."""
    from .operators import request_from_settings, resolve_target
    from .preferences import get_prefs
    from ..scene.key_takes import check_target, settings_of
    from ..worker.validation import RequestError

    scene, settings = context.scene, context.scene.mld_motion
    obj = resolve_target(context)
    problem = check_target(obj)
    if problem:
        runtime.record_outcome(scene, error=f"Live Preview: {problem}")
        return None
    try:
        request = request_from_settings(settings, get_prefs(context), obj)
    except RequestError as exc:
        runtime.record_outcome(scene, error=f"Live Preview: {exc}")
        return None
    options = settings_of(scene)
    try:
        plan = key_plan(obj, scene, options, settings.exact)
    except ValueError as exc:
        runtime.record_outcome(scene, error=f"Live Preview: {exc}")
        return None
    request = request.with_(draft=True, variants=1, extra={**request.extra, "rank": False, "key_plan": plan})
    target = runtime.Target(obj.name, getattr(obj, "session_uid", None), scene.name, settings.exact,
                            settings.set_frame_range, options=options, preview=True, live=True)
    return request, target


def key_plan(obj, scene, options, exact: bool):
    """The armature's KeyPlan (its rest, bone map and road), read from the file once per Live Preview, keying
    settings and stored bone map (edited in the Retarget panel meanwhile: read again): the worker computes the keys
    from it, the main thread only writes them."""
    from ..scene.key_takes import read_plan, scene_fps

    data = getattr(obj, "mld_retarget", None)
    rows = tuple((row.joint, row.bone) for row in data.rows) + (data.extras,) if data is not None else ()
    key = (getattr(obj, "session_uid", None), obj.name, options, exact, scene_fps(scene), scene.frame_start, rows)
    if key not in _plans:
        _plans.clear()
        _plans[key] = read_plan(obj, scene, options, None, exact)
    return _plans[key]


def stop(context) -> str:
    """Cancel the preview job and give the armature back the Action it had before the preview."""
    from .operators import resolve_target
    from ..scene import take_review

    live().stop()
    _plans.clear()  # the next Live Preview reads the rig again (its rest or map may have changed meanwhile)
    if bpy.app.timers.is_registered(fire):
        bpy.app.timers.unregister(fire)
    obj = resolve_target(context)
    return take_review.reject(obj) if obj is not None and take_review.pending(obj) else "Nothing to restore"


def shutdown() -> None:
    global _live
    if _live is not None:
        _live.stop()
    _live = None
    _plans.clear()
    if bpy.app.timers.is_registered(fire):
        bpy.app.timers.unregister(fire)
