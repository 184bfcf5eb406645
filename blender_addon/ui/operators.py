"""Operators: thin adapters from the UI to plain functions (bpy).

``do_generate(obj, request, ...)`` is the plain function; ``MLD_OT_generate`` only reads the context into
its arguments. Interactive runs go to the worker thread and return at once (the timer in ``runtime`` keys
the result); in background mode (``blender -b``, the bpy module) or with ``wait=True`` the operator runs the
job to the end itself, so scripts and tests get the keys when the call returns, as one undo step.
"""

from __future__ import annotations

import random

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from .. import env
from . import runtime
from ..scene.key_takes import check_target, settings_of
from ..worker.model_choice import has_draft, model_dir_for
from ..worker.validation import RequestError, validate_request


# -- plain functions ------------------------------------------------------------------------------------------
def resolve_target(context):
    """The armature to key: the panel's choice, else the active object if it is an armature."""
    settings = context.scene.mld_motion
    if settings.target is not None:
        return settings.target
    obj = context.view_layer.objects.active if context.view_layer else None
    return obj if obj is not None and obj.type == "ARMATURE" else None


def request_from_settings(settings, prefs, target=None):
    """A validated request from the panel settings and the preferences (raises RequestError); the armature's keys
    (of ``target``), Loop and Follow Curve ride along as constraints."""
    request = validate_request(
        settings.prompt,
        settings.seconds,
        settings.seed,
        settings.steps,
        settings.guidance,
        settings.variants,
        model_dir=model_dir_for(settings, prefs),
        device=prefs.device if prefs is not None else "cpu",
        threads=prefs.threads if prefs is not None else 0,
        draft=getattr(settings, "mode", "FINAL") == "DRAFT",
    )
    rows = [(row.prompt, row.seconds) for row in getattr(settings, "sequence", ())]
    if rows:  # one take from the sequence's segments (the first one's prompt and length name it)
        return request.with_(prompt=rows[0][0], extra={"sequence": sequence_of(rows, request.model_dir)})
    constraints = direction_of(settings, request.frames, target)
    return request.with_(extra={"constraints": constraints}) if constraints else request


def sequence_of(rows, model_dir) -> list[tuple[str, float]]:
    """The panel's sequence rows, checked like generate --sequence (a later segment also makes 0.5 s of overlap)."""
    from mld_core.inputs import check_prompt, check_seconds, model_limits

    from ..worker.batchfile import SEQUENCE_OVERLAP_S

    limits = model_limits(model_dir)
    out = []
    for n, (prompt, seconds) in enumerate(rows, start=1):
        try:
            text = check_prompt(prompt)
            check_seconds(seconds + (SEQUENCE_OVERLAP_S if n > 1 else 0.0), limits, "Length")
        except RequestError as exc:
            raise RequestError(f"Sequence segment {n}: {exc}") from None
        out.append((text, float(seconds)))
    return out


def direction_of(settings, frames: int, obj=None):
    """The panel's Use Keys on the Armature (``obj``'s keys), Loop and Follow Curve as a
    mld_core.take_fixes.constraints.Constraints (empty when none is set)."""
    from mld_core.take_fixes.constraints import Constraints, Loop, keys_from_blender, path_along

    from ..scene.curves import curve_points

    items = []
    if getattr(settings, "use_armature_keys", False) and obj is not None:
        from ..scene.armature_keys import keyed_poses
        from ..scene.key_takes import bone_map_of

        poses = keyed_poses(obj, bpy.context.scene, bone_map_of(obj).joints, frames / 20.0,
                            only_selected=settings.keys_selected_only)
        items.append(keys_from_blender(poses, tuple(obj.matrix_world.translation)))
    if getattr(settings, "loop", False):
        items.append(Loop())
    curve = getattr(settings, "follow_curve", None)
    if curve is not None:
        items.append(path_along(curve_points(curve), frames))
    return Constraints(items)


def do_generate(obj, scene, request, *, exact=True, set_frame_range=True, wait=False):
    """Generate for ``obj``: wait=True runs to the end and returns (level, message); otherwise submits the
    job and returns ("INFO", message) at once."""
    # the keying options are read now, so changing the panel while the job runs does not change this take
    target = runtime.Target(obj.name, getattr(obj, "session_uid", None), scene.name, exact, set_frame_range,
                            options=settings_of(scene), preview=bool(getattr(scene.mld_motion, "preview", False)))
    if wait:
        job = runtime.runner().run_now(request)
        return runtime.finish_job(job, target)
    runtime.submit(request, target)
    runtime.record_outcome(scene, message="Generating ...")
    return "INFO", f"Generating {request.seconds:g} s of '{request.prompt}'"


def generate_problem(context) -> str:
    """'' when Generate can run, else why not (shown as the disabled button's tooltip)."""
    missing = env.missing_modules()
    if missing:
        return env.dependency_message(missing)
    if runtime.busy():
        return "A generation is running: wait for it or press Cancel"
    settings = getattr(context.scene, "mld_motion", None)
    if settings is None:
        return "The add-on is not registered for this scene"
    if not settings.prompt.strip():
        return "Type a prompt first"
    from .preferences import get_prefs

    if getattr(settings, "mode", "FINAL") == "DRAFT" and not has_draft(model_dir_for(settings, get_prefs(context))):
        return "This model has no Draft: use Final"
    problem = check_target(resolve_target(context))
    return problem


# -- operators ------------------------------------------------------------------------------------------------
class MLD_OT_generate(bpy.types.Operator):
    """Generate motion from the prompt and key it onto the armature as a new Action"""

    bl_idname = "mld.generate"
    bl_label = "Generate Motion"
    bl_options = {"REGISTER", "UNDO"}

    wait: BoolProperty(
        name="Wait",
        description="Run to the end before returning (always so in background mode)",
        default=False,
        options={"SKIP_SAVE", "HIDDEN"},
    )

    @classmethod
    def poll(cls, context):
        problem = generate_problem(context)
        if problem:
            cls.poll_message_set(problem)
            return False
        return True

    def execute(self, context):
        wait = self.wait or bpy.app.background
        level = generate_from_panel(self, context, wait)
        runtime.tag_redraw()
        if not wait:
            # Nothing changed yet: no undo step now. The timer pushes exactly one when the keys land.
            return {"CANCELLED"}
        return {"FINISHED"} if level == "INFO" else {"CANCELLED"}


def generate_from_panel(op, context, wait: bool, stop_live_preview: bool = False) -> str | None:
    """The panel's settings as a request, generated and keyed onto the target (operators Generate and Keep);
    reports on ``op`` and returns the report's level, or None when the settings are refused (nothing changes).
    ``stop_live_preview``: turn Live Preview off first (it gives the armature back its Action)."""
    from .preferences import get_prefs

    settings = context.scene.mld_motion
    obj = resolve_target(context)
    try:
        request = request_from_settings(settings, get_prefs(context), obj)
    except RequestError as exc:
        runtime.record_outcome(context.scene, error=str(exc))
        op.report({"ERROR"}, str(exc))
        return None
    if stop_live_preview:
        settings.live_preview = False
    level, message = do_generate(obj, context.scene, request, exact=settings.exact,
                                 set_frame_range=settings.set_frame_range, wait=wait)
    op.report({level}, message)
    return level


class MLD_OT_keep_live(bpy.types.Operator):
    """Make the take for real, as Generate does (in the chosen mode), and turn Live Preview off"""

    bl_idname = "mld.keep_live"
    bl_label = "Keep"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        settings = getattr(context.scene, "mld_motion", None)
        if settings is None or not settings.live_preview:
            cls.poll_message_set("Live Preview is off")
            return False
        problem = check_target(resolve_target(context))
        if problem:
            cls.poll_message_set(problem)
            return False
        return True

    def execute(self, context):
        wait = bpy.app.background
        level = generate_from_panel(self, context, wait, stop_live_preview=True)
        return {"FINISHED"} if wait and level == "INFO" else {"CANCELLED"}


class MLD_OT_cancel(bpy.types.Operator):
    """Stop the running generation (within one diffusion step)"""

    bl_idname = "mld.cancel"
    bl_label = "Cancel"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        if not runtime.busy():
            cls.poll_message_set("Nothing is running")
            return False
        return True

    def execute(self, context):
        runtime.runner().cancel_all()
        self.report({"INFO"}, "Cancelling ...")
        return {"FINISHED"}


class MLD_OT_randomize_seed(bpy.types.Operator):
    """Pick a new random seed"""

    bl_idname = "mld.randomize_seed"
    bl_label = "Random Seed"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        context.scene.mld_motion.seed = random.randint(0, 999_999)
        return {"FINISHED"}


class MLD_OT_create_armature(bpy.types.Operator):
    """Create the model's own 22-bone armature (with a simple body mesh) and make it the target"""

    bl_idname = "mld.create_armature"
    bl_label = "Create Canonical Armature"
    bl_options = {"REGISTER", "UNDO"}

    body: BoolProperty(name="Body Mesh", description="Add a simple mesh bound to the bones", default=True)

    @classmethod
    def poll(cls, context):
        if env.mld_core_location() is None:
            cls.poll_message_set("mld_core is missing from the add-on (a broken install?)")
            return False
        if context.mode not in {"OBJECT", "POSE"}:
            cls.poll_message_set("Switch to Object Mode first")
            return False
        return True

    def execute(self, context):
        from ..scene.canonical_armature import create_canonical_armature

        obj = create_canonical_armature(context, location=tuple(context.scene.cursor.location), body=self.body)
        context.scene.mld_motion.target = obj
        self.report({"INFO"}, f"Created {obj.name}")
        return {"FINISHED"}


class MLD_OT_install_dependencies(bpy.types.Operator):
    """Download and install PyTorch (CPU), safetensors and tqdm for Blender's Python into the add-on's user folder"""

    bl_idname = "mld.install_dependencies"
    bl_label = "Install Dependencies"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        if runtime.installer().running:
            cls.poll_message_set("An installation is running")
            return False
        if env.user_site_dir() is None:
            cls.poll_message_set("No user folder for the add-on")
            return False
        if not getattr(bpy.app, "online_access", True):
            cls.poll_message_set("Online access is off: allow it in Preferences > System > Network")
            return False
        return True

    def invoke(self, context, event):
        return context.window_manager.invoke_confirm(self, event)

    def execute(self, context):
        from ..installer import install_commands

        target = env.user_site_dir()
        target.mkdir(parents=True, exist_ok=True)

        def done(installer):
            env.add_user_site_packages(target)

        runtime.installer().start(install_commands(target), on_done=done)
        bpy.app.timers.register(_redraw_while_installing, first_interval=0.5)
        self.report({"INFO"}, f"Installing into {target} (see the system console)")
        return {"FINISHED"}


def _redraw_while_installing():
    runtime.tag_redraw()
    return 0.5 if runtime.installer().running else None


class MLD_OT_report(bpy.types.Operator):
    """Show a message from a finished background job"""

    bl_idname = "mld.report"
    bl_label = "Motion Report"
    bl_options = {"INTERNAL"}

    level: EnumProperty(items=[(x, x, "") for x in ("INFO", "WARNING", "ERROR")], default="INFO")
    message: StringProperty(default="")

    def invoke(self, context, event):
        self.report({self.level}, self.message)
        return {"FINISHED"}

    def execute(self, context):
        self.report({self.level}, self.message)
        return {"FINISHED"}


class _ReviewTake:
    """Accept / Reject: enabled while the target armature has takes made in preview."""

    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        from ..scene import take_review

        if not take_review.pending(resolve_target(context)):
            cls.poll_message_set("No take in preview: turn Preview on and Generate")
            return False
        return True


class MLD_OT_accept_take(_ReviewTake, bpy.types.Operator):
    """Keep the takes in preview as ordinary takes"""

    bl_idname = "mld.accept_take"
    bl_label = "Accept"

    def execute(self, context):
        from ..scene import take_review

        self.report({"INFO"}, take_review.accept(resolve_target(context)))
        return {"FINISHED"}


class MLD_OT_reject_take(_ReviewTake, bpy.types.Operator):
    """Delete the takes in preview and give the armature back the Action it had"""

    bl_idname = "mld.reject_take"
    bl_label = "Reject"

    def execute(self, context):
        from ..scene import take_review

        self.report({"INFO"}, take_review.reject(resolve_target(context)))
        return {"FINISHED"}


classes = (
    MLD_OT_generate,
    MLD_OT_keep_live,
    MLD_OT_accept_take,
    MLD_OT_reject_take,
    MLD_OT_cancel,
    MLD_OT_randomize_seed,
    MLD_OT_create_armature,
    MLD_OT_install_dependencies,
    MLD_OT_report,
)


@bpy.app.handlers.persistent
def _on_load_pre(*args):
    runtime.forget_targets()


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.app.handlers.load_pre.append(_on_load_pre)


def unregister():
    from . import live_preview

    if _on_load_pre in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_on_load_pre)
    live_preview.shutdown()
    runtime.shutdown()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
