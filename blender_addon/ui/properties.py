"""Per-scene settings of the panel: ``scene.mld_motion`` (bpy)."""

from __future__ import annotations

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty,
                       StringProperty)

from mld_core.rig.keying import DEFAULT_TOLERANCE_DEG, MATCH_CHOICES, ROTATION_CHOICES

from . import live_preview, quality_panel
from ..worker.model_choice import model_items
from ..worker.validation import MAX_STEPS, MAX_VARIANTS, SEED_MAX, model_limits

_LIMITS = model_limits()  # the bundled model's lengths (config.json only); another model's are checked on Generate


def _prompt_changed(self, context):
    quality_panel.prompt_changed(self, context)
    live_preview.edited(self, context)


_MODEL_ITEMS = model_items()  # kept alive: Blender reads a dynamic enum's strings after the callback returns


def _models(self, context):
    return _MODEL_ITEMS


def _setting_changed(self, context):
    live_preview.edited(self, context)


def _live_toggled(self, context):
    live_preview.toggled(self, context)


def _is_armature(self, obj):
    return obj.type == "ARMATURE"


def _is_curve(self, obj):
    return obj.type == "CURVE"


class MLD_SequenceRow(bpy.types.PropertyGroup):
    """One segment of a prompt sequence: what happens, for how long."""

    prompt: StringProperty(name="Prompt", description="What happens in this segment", default="a person walks forward")
    seconds: FloatProperty(name="Seconds", description="Length of this segment", default=3.0, min=_LIMITS.min_seconds,
                           max=_LIMITS.max_seconds - 0.5, step=50, precision=1, unit="TIME_ABSOLUTE")


class MLD_SceneSettings(bpy.types.PropertyGroup):
    prompt: StringProperty(
        name="Prompt",
        description="What the character does, in plain English (e.g. 'a person walks forward and waves')",
        default="a person walks forward and waves with the right hand",
        update=_prompt_changed,  # coverage as the user types
        options={"TEXTEDIT_UPDATE"},
    )
    seconds: FloatProperty(
        name="Seconds",
        description=f"Length of the motion (the model makes {_LIMITS.min_seconds:g} to {_LIMITS.max_seconds:g} "
        f"seconds at {_LIMITS.fps} fps)",
        default=4.0,
        min=_LIMITS.min_seconds,
        max=_LIMITS.max_seconds,
        step=50,
        precision=2,
        unit="TIME_ABSOLUTE",
        update=_setting_changed,
    )
    seed: IntProperty(name="Seed", description="Same seed + same settings = same motion", default=0, min=0, max=SEED_MAX,
                      update=_setting_changed)
    model: EnumProperty(
        name="Model",
        description="The bundled model Generate uses (a model folder set in the add-on's Preferences wins over it)",
        items=_models,
        update=_prompt_changed,  # coverage and Live Preview read the new model
    )
    mode: EnumProperty(
        name="Mode",
        description="Draft: a step of the model's distilled denoiser and a guided step of its own, about 10x faster, "
        "for trying prompts; "
        "Final: the full sampler (Steps)",
        items=[("FINAL", "Final", "The full sampler with the Steps below"),
               ("DRAFT", "Draft", "A distilled step and a guided step: about 10x faster")],
        default="FINAL",
    )
    live_preview: BoolProperty(
        name="Live Preview",
        description="While on, editing the prompt, seconds or seed regenerates a Draft take on the armature; nothing "
        "is kept until Keep, and turning it off gives the armature back its Action",
        default=False,
        update=_live_toggled,
        options=set(),
    )
    guidance: FloatProperty(
        name="Guidance",
        description="How strongly the prompt steers the motion (0: the model's default, about 4)",
        default=0.0,
        min=0.0,
        max=30.0,
        precision=1,
    )
    steps: IntProperty(name="Steps", description="Diffusion steps (more: slower, finer)", default=50, min=1, max=MAX_STEPS)
    variants: IntProperty(
        name="Variants",
        description="How many different takes to make (seeds seed, seed+1, ...): each becomes its own Action",
        default=1,
        min=1,
        max=MAX_VARIANTS,
    )
    sequence: CollectionProperty(type=MLD_SequenceRow, name="Sequence",
                                 description="Prompt segments made as one take, each continuing the previous one")
    sequence_index: IntProperty(name="Segment", default=0, min=0)
    preview: BoolProperty(name="Preview", description="New takes play as a preview until you Accept or Reject them "
                          "(Reject gives the armature back the Action it had)", default=False)
    use_armature_keys: BoolProperty(
        name="Use Keys on the Armature",
        description="Poses the armature is already keyed in, within the take's range, become poses the take must hit",
        default=False,
    )
    keys_selected_only: BoolProperty(name="Selected Bones Only", description="Use only the selected bones' keys",
                                     default=False)
    loop: BoolProperty(name="Loop", description="The take's last frame continues into its first (a cycle)",
                       default=False)
    follow_curve: PointerProperty(
        name="Follow Curve",
        description="The root follows this curve's shape over the take, from where the armature stands (empty: free)",
        type=bpy.types.Object,
        poll=_is_curve,
    )
    target: PointerProperty(
        name="Armature",
        description="The armature that gets the keys (empty: the active armature)",
        type=bpy.types.Object,
        poll=_is_armature,
    )
    exact: BoolProperty(
        name="Match Joints Exactly",
        description="Also key bone locations so every joint lands exactly on the generated position",
        default=True,
    )
    set_frame_range: BoolProperty(
        name="Set Frame Range",
        description="Set the scene's end frame to the end of the generated motion",
        default=True,
    )
    # how keys are written (Retarget sub-panel; blender_addon/retarget_wiring.RetargetSettings)
    reduce_keys: BoolProperty(
        name="Reduce Keys",
        description="Keep only the keys needed to stay within the tolerance on every frame (Bezier, auto-clamped "
        "handles); off: a key on every frame",
        default=False,
    )
    reduce_tolerance: FloatProperty(
        name="Tolerance",
        description="Largest rotation error key reduction may introduce, in degrees (locations: 2 mm)",
        default=DEFAULT_TOLERANCE_DEG,
        min=0.01,
        max=45.0,
        soft_max=5.0,
        precision=2,
    )
    rotation_mode: EnumProperty(
        name="Rotation",
        description="Rotation channels to key",
        items=list(ROTATION_CHOICES),
        default="QUATERNION",
    )
    match: EnumProperty(
        name="Match",
        description="What the keyed rig keeps of the take when its proportions differ",
        items=list(MATCH_CHOICES),
        default="EFFECTORS",
    )
    foot_lock: BoolProperty(
        name="Foot Lock",
        description="Hold a foot in place while the motion says it is on the ground (the leg is re-solved)",
        default=False,
    )
    push_nla: BoolProperty(
        name="Push to NLA",
        description="Put each new Action on a new NLA track as a strip instead of assigning it",
        default=False,
    )
    # the last outcome (shown in the panel)
    last_message: StringProperty(name="Last Result", default="")
    last_error: StringProperty(name="Last Error", default="")
    last_seconds: FloatProperty(name="Time Taken", default=0.0)
    last_frames: IntProperty(name="Frames", default=0)
    last_actions: StringProperty(name="Actions", default="")
    last_reduction: FloatProperty(name="Keys Kept", description="Keys kept by key reduction (1: every frame)", default=1.0)


classes = (MLD_SequenceRow, MLD_SceneSettings)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.mld_motion = PointerProperty(type=MLD_SceneSettings)


def unregister():
    del bpy.types.Scene.mld_motion
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
