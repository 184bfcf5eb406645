"""Generated takes -> Actions on an armature (bpy; main thread only).

``apply_result(obj, result, scene, ...)`` is what the operator (interactive and headless) and the batch script
call: one new Action per take, named from prompt and seed, keyed in bulk at the scene's frame rate from its start
frame, provenance stored as custom properties; the first take is assigned (or each goes onto its own NLA track,
a prompt sequence's take as one strip per segment).

One road for every rig, in three stages: read (``read_rig.read_record``: the rest, the stored bone map, the rotation
modes and the scene's rate, once, into a bpy-free ``keying.RigRecord``) -> plan (``keying.plan_keys``, numpy: the
bone map, stored by the Retarget panel, else detected, the identity on the canonical armature; the road; one
``keyframes.BakedKeys`` per take) -> write (``write_action.write_takes``). Every take is computed before the first
Action is created: a map that lacks required bones raises ValueError with a message and keys nothing.
Also here: the checks polls use (``check_target``) and the armature's bone map for the panels (``bone_map_of``).
"""

from __future__ import annotations

from mld_core.rig import bone_maps
from mld_core.rig.keying import KeyPlan, RetargetSettings, detections, map_problem, plan_keys, plan_of

from . import canonical_armature, read_rig, write_action
from .read_rig import scene_fps
from .write_action import ApplyReport


# -- the armature's bone map ----------------------------------------------------------------------------------
def stored_map(obj):
    """The bone map the Retarget panel stored on ``obj`` (``obj.mld_retarget``), or None when there is none."""
    data = getattr(obj, "mld_retarget", None)
    if data is None or not any(row.bone for row in data.rows):
        return None
    from mld_core.rig.bone_map_rows import rows_to_map

    return rows_to_map(data.rows, data.extras)


def rig_parents(obj) -> list:
    return [b.parent.name if b.parent is not None else None for b in obj.data.bones]


def detected_map(obj) -> bone_maps.Detection:
    """Detection for ``obj``'s bones (cached per set of bone names and parents)."""
    return detections.get(obj.data.bones.keys(), rig_parents(obj))


def bone_map_of(obj):
    """The map ``obj`` is keyed with: the stored one, else the detected one."""
    return stored_map(obj) or detected_map(obj).bone_map


def not_editable(obj) -> str:
    """'' if keys can be written onto ``obj`` and saved with the file, else why not (linked from a library)."""
    if getattr(obj, "library", None) is not None:
        return (f"{obj.name!r} is linked from {obj.library.filepath!r} and cannot take new keys: make it local or "
                "add a library override (Object > Library Override > Make), then generate onto that")
    return ""


def check_target(obj) -> str:
    """'' if ``obj`` can take generated motion, else a sentence saying why not (cheap: detection is cached)."""
    if obj is None:
        return "No target armature: pick one, or create the canonical armature"
    if obj.type != "ARMATURE":
        return f"{obj.name!r} is not an armature"
    if len(obj.data.bones) == 0:
        return f"{obj.name!r} has no bones"
    locked = not_editable(obj)
    if locked:
        return locked
    if canonical_armature.is_canonical(obj):
        return ""
    return map_problem(bone_map_of(obj), obj.data.bones.keys(), obj.name)


def settings_of(scene) -> RetargetSettings:
    panel = getattr(scene, "mld_motion", None)
    return RetargetSettings.from_settings(panel) if panel is not None else RetargetSettings()


# -- keying ---------------------------------------------------------------------------------------------------
def apply_result(obj, result, scene, *, exact: bool = True, set_frame_range: bool = False, assign: bool = True,
                 options: RetargetSettings | None = None, bone_map=None, ik_controls: bool = True) -> ApplyReport:
    """Key every take of ``result`` (a generation.GenerationResult) onto ``obj`` as new Actions.

    exact: on the canonical armature, key every bone's location too (each joint exactly on the generated one);
    options: how to key (reduction, rotation mode, foot lock, NLA); default: the scene's panel settings.
    bone_map: a ``bone_maps.BoneMap`` to use instead of the armature's own (stored or detected).
    ik_controls: key the map's IK controls to match the FK pose (Rigify; about 20 ms a frame, so previews skip it).
    Raises ValueError (nothing keyed, no Action created) when the armature cannot take the motion.
    """
    options = options if options is not None else settings_of(scene)
    if obj is None or obj.type != "ARMATURE":
        raise ValueError(check_target(obj))
    problem = not_editable(obj)
    if problem:
        raise ValueError(problem)
    ready = ready_keys(result, obj, scene, options, bone_map)
    if ready is None:
        record = read_rig.read_record(obj, scene)  # 1. the file, read once
        ready = plan_keys(result.takes, record, options, bone_map, exact)  # 2. every take's keys (numpy)
    return write_action.write_takes(obj, scene, *ready, assign=assign, ik_controls=ik_controls,  # 3. written
                                    set_frame_range=set_frame_range)


def ready_keys(result, obj, scene, options: RetargetSettings, bone_map):
    """(KeyPlan, [TakeKeys]) computed on the worker for this armature and these settings (``result.planned``:
    Live Preview), or None."""
    ready = getattr(result, "planned", None)
    if ready is not None and bone_map is None and ready[0].rig.name == obj.name and ready[0].settings == options \
            and ready[0].fps == scene_fps(scene) and ready[0].frame_start == scene.frame_start:
        return ready
    return None


def read_plan(obj, scene, options: RetargetSettings, bone_map=None, exact: bool = True) -> KeyPlan:
    """How ``obj`` is keyed (its rest, bone map, rotation modes, the road), read from the file (main thread)."""
    return plan_of(read_rig.read_record(obj, scene), options, bone_map, exact)
