"""The panel's coverage line, "What this model knows" sub-panel and take-quality badges (bpy).

The prompt's update callback (every keystroke) hands the text to the :class:`coverage_watch.CoverageWatcher`; a
timer redraws the sidebar until the verdict arrives. The badges shown are the custom properties of the last take's
Action (the numbers the batch manifest records too).
"""

from __future__ import annotations

import bpy

from ..worker.coverage_watch import CoverageWatcher, badge_lines, coverage_line
from ..worker.model_choice import auto_line, folder_override_for, other_model_line
from ..env import missing_modules

POLL_S = 0.1

_watcher: CoverageWatcher | None = None


def _model_key(context) -> tuple:
    """(model folder, device, threads) as Generate will use them (operators.request_from_settings)."""
    from ..worker.model_choice import model_dir_for
    from .preferences import get_prefs

    prefs = get_prefs(context)
    model_dir = model_dir_for(getattr(context.scene, "mld_motion", None), prefs)
    return model_dir, prefs.device if prefs is not None else "cpu", prefs.threads if prefs is not None else 0


def _check(text: str, key: tuple):
    """The prompt's coverage by the model Generate uses (under Auto: by the default, which the route reads)."""
    from mld_core.model_route import is_auto

    from . import runtime

    model_dir, device, threads = key
    return runtime.cache().get(None if is_auto(model_dir) else model_dir, device, threads).coverage([text])[0]


def watcher() -> CoverageWatcher:
    global _watcher
    if _watcher is None:
        _watcher = CoverageWatcher(_check)
    return _watcher


def prompt_changed(settings, context) -> None:
    """The prompt's update callback (every keystroke): ask for its coverage and redraw when it arrives."""
    text = settings.prompt.strip()
    if not text or bpy.app.background or missing_modules():  # no one is typing: scripts ask the pipeline themselves
        return
    watcher().request(text, _model_key(context))
    if not bpy.app.timers.is_registered(_poll):
        bpy.app.timers.register(_poll, first_interval=POLL_S)


def _poll():
    from .runtime import tag_redraw

    tag_redraw()
    return POLL_S if _watcher is not None and _watcher.pending else None


def draw_coverage(layout, settings, context) -> None:
    """The verdict line under the prompt field (nothing while it is being checked or when unavailable)."""
    text = settings.prompt.strip()
    if not text or missing_modules():  # no PyTorch yet: the panel says how to get it
        return
    key = _model_key(context)
    cov = watcher().result(text, key)
    if cov is None:
        if bpy.app.background:
            return
        if not watcher().pending:
            watcher().request(text, key)  # e.g. a file opened with a prompt in it
        layout.label(text="Checking the prompt ...", icon="TIME")
        return
    from mld_core.model_route import is_auto

    routed = auto_line(text, cov.verdict, tuple(cov.known_contents)) if is_auto(key[0]) else ""
    if routed:  # Auto sends the prompt to the bundled model trained on its verbs
        layout.label(text=routed, icon="INFO")
        return
    line = coverage_line(cov)
    if line is not None:
        row = layout.row()
        row.alert = cov.verdict == "unknown"
        row.label(text=line[1], icon=line[0])
    from .preferences import get_prefs

    overridden = folder_override_for(get_prefs(context)) is not None
    other = other_model_line(text, cov.verdict, key[0], overridden) if line else ""
    if other:
        layout.label(text=other[0].upper() + other[1:], icon="INFO")


def draw_badges(layout, settings) -> None:
    """The last take's badges (from its Action's custom properties), one line each with its explanation."""
    names = [n for n in settings.last_actions.split(", ") if n]
    action = bpy.data.actions.get(names[0]) if names else None
    lines = badge_lines(action) if action is not None else []
    if not lines:
        return
    box = layout.box()
    box.label(text=f"Take quality: {action.name}", icon="INFO")
    col = box.column(align=True)
    for value, why in lines:
        col.label(text=value)
        col.label(text=why, icon="BLANK1")


class MLD_PT_known(bpy.types.Panel):
    bl_label = "What This Model Knows"
    bl_idname = "MLD_PT_known"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "MLD"
    bl_parent_id = "MLD_PT_generate"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        from mld_core.condition.coverage import describe_content

        settings = getattr(context.scene, "mld_motion", None)
        cov = watcher().result(settings.prompt.strip(), _model_key(context)) if settings is not None else None
        contents = list(getattr(cov, "known_contents", []) or [])
        col = self.layout.column(align=True)
        if not contents:
            col.label(text="Type a prompt to load the model's list", icon="INFO")
            return
        for label in contents:
            col.label(text=describe_content(label))


def register():
    bpy.utils.register_class(MLD_PT_known)


def unregister():
    bpy.utils.unregister_class(MLD_PT_known)
    if bpy.app.timers.is_registered(_poll):
        bpy.app.timers.unregister(_poll)
