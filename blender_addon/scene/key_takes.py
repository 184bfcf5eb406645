"""Generated takes -> Actions on an armature (bpy; main thread only).

``apply_result(obj, result, scene, ...)`` is what the operator (interactive and headless) and the batch script
call: one new Action per take, named from prompt and seed, keyed in bulk at the scene's frame rate from its start
frame, provenance stored as custom properties; the first take is assigned (or each goes onto its own NLA track,
a prompt sequence's take as one strip per segment).

One road for every rig: ``read_rig.read_rig`` (the rest as arrays) + the armature's bone map (stored by the
Retarget panel, else detected; the identity on the canonical armature) + the options -> ``keying.take_keys``
(bpy-free) -> one ``keyframes.BakedKeys`` per take -> ``write_action.keys_to_action``. Every take is computed before
the first Action is created: a map that lacks required bones raises ValueError with a message and keys nothing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mld_core.rig import bone_maps
from mld_core.rig.keying import (
    KeyPlan,
    RetargetSettings,
    canonical_map,
    detections,
    exact_road,
    map_problem,
    missing_message,
    plan_takes,
    segment_strips,
)

from ..worker import naming
from . import canonical_armature, read_rig, write_action


@dataclass
class ApplyReport:
    actions: list = field(default_factory=list)  # Action names, in take order
    frames: int = 0  # scene frames of the first take
    fps: float = 0.0
    key_seconds: float = 0.0  # time spent computing and writing keys
    keys: int = 0  # keyframes written in total
    retargeted: bool = False  # True: through keyedit (bone map), False: the canonical exact path
    bone_map: str = ""  # where the map came from (preset name, "auto", "user", "file" ...)
    reduction_ratios: list = field(default_factory=list)  # per take: keys kept / keys on every frame (1.0: none)
    nla: bool = False
    ik_keys: int = 0  # keys on IK controls matching the FK pose (control rigs: Rigify)

    @property
    def reduction_ratio(self) -> float:
        return sum(self.reduction_ratios) / len(self.reduction_ratios) if self.reduction_ratios else 1.0


def scene_fps(scene) -> float:
    return scene.render.fps / (scene.render.fps_base or 1.0)


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


# -- keying -----------------------------------------------------------------------------------------------------
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
    report = ApplyReport(fps=scene_fps(scene), nla=options.nla)
    planned, bone_map = plan_keys(obj, result, scene, options, bone_map, exact, report)
    write_keys(obj, planned, bone_map, options, exact, scene, assign, report, ik_controls)
    panel = getattr(scene, "mld_motion", None)
    if panel is not None and hasattr(panel, "last_reduction"):
        panel.last_reduction = report.reduction_ratio if report.retargeted and options.reduce else 1.0
    if set_frame_range and report.frames:
        scene.frame_end = scene.frame_start + report.frames - 1
    return report


def read_plan(obj, scene, options: RetargetSettings, bone_map=None, exact: bool = True) -> KeyPlan:
    """What keying ``obj`` needs, read from the file (main thread): its rest, bone map, rotation modes, the road."""
    canonical = canonical_armature.is_canonical(obj)
    modes = read_rig.rotation_modes(obj)
    on_exact_road = exact_road(canonical, bone_map is not None, options, modes)
    if on_exact_road:
        problem = check_target(obj)
        if problem:
            raise ValueError(problem)
    rest = read_rig.read_rig(obj)
    if bone_map is None:
        bone_map = canonical_map(rest.names) if canonical and stored_map(obj) is None else bone_map_of(obj)
    return KeyPlan(rest, bone_map, options, scene_fps(scene), scene.frame_start, on_exact_road, modes, exact)


def plan_keys(obj, result, scene, options: RetargetSettings, bone_map, exact: bool, report: ApplyReport):
    """Every take's keys, computed before anything in the file changes: ([(take, keys, seconds)], bone map). Keys
    already computed on the worker for this armature and these settings (``result.planned``: (KeyPlan, planned))
    are used as they are."""
    ready = getattr(result, "planned", None)
    if ready is not None and bone_map is None and ready[0].rig.name == obj.name and ready[0].settings == options \
            and ready[0].fps == scene_fps(scene) and ready[0].frame_start == scene.frame_start:
        plan, planned = ready
    else:
        plan = read_plan(obj, scene, options, bone_map, exact)
        try:
            planned = plan_takes(result.takes, plan)
        except bone_maps.BoneMapError as exc:
            raise ValueError(missing_message(exc, obj.name)) from None
    report.retargeted = not plan.exact
    report.bone_map = plan.bone_map.source if report.retargeted else ""
    return planned, plan.bone_map


def write_keys(obj, planned, bone_map, options: RetargetSettings, exact: bool, scene, assign: bool,
               report: ApplyReport, ik_controls: bool = True) -> None:
    """One Action per planned take, through the one writer; fills ``report``. ``ik_controls``: also key the map's
    IK controls to match the FK pose (scene.ik_controls)."""
    import bpy

    existing = {a.name for a in bpy.data.actions}
    for index, (take, keys, seconds) in enumerate(planned):
        t0 = time.perf_counter()
        name = naming.unique_name(take.name or naming.action_name(take.prompt, take.seed), existing)
        existing.add(name)
        props = take.provenance()
        props.update(mld_scene_fps=float(report.fps), mld_exact=int(bool(exact) and not report.retargeted),
                     mld_retargeted=int(report.retargeted))
        if report.retargeted:
            props.update(mld_bone_map=bone_map.source, mld_reduce=int(options.reduce),
                         mld_tolerance_deg=float(options.tolerance_deg), mld_rotation_mode=options.rotation_mode,
                         mld_foot_lock=int(options.foot_lock), mld_keys=int(keys.num_keys),
                         mld_reduction_ratio=float(keys.stats["reduction_ratio"]))
        segments = getattr(take, "segments", None)
        strips = segment_strips(segments, take.frames, take.fps, report.fps, keys.frame_start) if segments \
            and options.nla else None
        action = write_action.keys_to_action(
            obj, keys, name, assign=assign and index == 0, nla=options.nla, properties=props,
            pose_properties=bone_map.pose_properties if report.retargeted else {}, segments=strips)
        if report.retargeted and ik_controls and bone_map.ik_controls:
            report.ik_keys += key_ik_controls(obj, scene, action, keys, bone_map.ik_controls)
        report.reduction_ratios.append(float(keys.stats.get("reduction_ratio", 1.0)))
        report.key_seconds += seconds + time.perf_counter() - t0
        report.actions.append(action.name)
        report.keys += keys.num_keys
        if index == 0:
            report.frames = keys.num_frames


def key_ik_controls(obj, scene, action, keys, chains) -> int:
    """Key ``chains``' IK controls into ``action`` to match its FK pose (played for it on ``scene``, the take's own,
    then the armature's assignment restored); returns the keys written."""
    from . import ik_controls

    ad = obj.animation_data or obj.animation_data_create()
    before = (ad.action, getattr(ad, "action_slot", None))
    write_action.assign_action(obj, action)
    try:
        frames = keys.frame_start + np.arange(keys.num_frames, dtype=np.float64)
        curves = ik_controls.ik_curves(obj, scene, chains, frames)
        writer = write_action.ChannelWriter.of(action, obj)
        for curve in curves:
            write_action.write_keys(writer.fcurve(curve.data_path, curve.index, curve.group), curve.frames,
                                    curve.values, keys.interpolation, handle_type=keys.handle_type,
                                    auto_smoothing=keys.auto_smoothing)
    finally:
        write_action.assign_action(obj, before[0], before[1] if before[0] is not None else None)
    return int(sum(len(c.frames) for c in curves))
