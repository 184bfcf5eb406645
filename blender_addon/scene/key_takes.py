"""Generated takes -> Actions on an armature (bpy; main thread only).

``apply_result(obj, result, scene, ...)`` is the one function the operator (interactive and headless) and
the batch script share: one new Action per take, named from prompt and seed, keyed in bulk at the scene's
frame rate from the scene's start frame, provenance stored as custom properties; the first take is assigned
(or every take goes onto its own NLA track with "Push to NLA").

Two paths:

* the canonical armature (the model's 22 bones): ``posing.pose_channels``, quaternion keys on every frame,
  optionally bone offsets so every joint lands exactly on the generated position;
* any other humanoid rig, and the canonical armature when key reduction, Euler rotations or foot locking is
  asked for: ``rig_io.read_rig`` -> the armature's bone map (the one stored on it by the Retarget panel, else
  the detected one) -> ``keyedit.take_to_keys`` -> ``keys.baked_to_action``. Keys go on mapped bones only.

Every take is computed before the first Action is created: a map that lacks required bones (or any other
problem) raises ValueError with a message and keys nothing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from mld_core.rig import bone_maps
from ..scene import write_action as keys
from ..worker import naming
from mld_core.rig import canonical_pose as posing
from ..scene import canonical_armature as rig
from mld_core.rig.keying import (
    RetargetSettings,
    canonical_map,
    detections,
    map_problem,
    missing_message,
    take_contacts,
    uses_keyedit,
)


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
    from mld_core.rig.keying import rows_to_map

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
    if rig.is_canonical(obj):
        return ""
    return map_problem(bone_map_of(obj), obj.data.bones.keys(), obj.name)


def settings_of(scene) -> RetargetSettings:
    panel = getattr(scene, "mld_motion", None)
    return RetargetSettings.from_settings(panel) if panel is not None else RetargetSettings()


# -- keying -----------------------------------------------------------------------------------------------------
def apply_result(
    obj,
    result,
    scene,
    *,
    exact: bool = True,
    set_frame_range: bool = False,
    assign: bool = True,
    options: RetargetSettings | None = None,
    bone_map=None,
) -> ApplyReport:
    """Key every take of ``result`` (a generation.GenerationResult) onto ``obj`` as new Actions.

    options: how to key (reduction, rotation mode, foot lock, NLA); default: the scene's panel settings.
    bone_map: a ``bone_maps.BoneMap`` to use instead of the armature's own (stored or detected).
    Raises ValueError (nothing keyed, no Action created) when the armature cannot take the motion.
    """
    import bpy

    from ..scene import read_rig as rig_io

    options = options if options is not None else settings_of(scene)
    if obj is None or obj.type != "ARMATURE":
        raise ValueError(check_target(obj))
    canonical = rig.is_canonical(obj)
    modes = rig_io.rotation_modes(obj)
    through_keyedit = bone_map is not None or uses_keyedit(canonical, options, modes)
    if not through_keyedit:
        problem = check_target(obj)
        if problem:
            raise ValueError(problem)
    fps = scene_fps(scene)
    start = scene.frame_start
    report = ApplyReport(fps=fps, retargeted=through_keyedit, nla=options.nla)

    # 1. Compute every take's keys (nothing in the file changes yet).
    planned = []
    if through_keyedit:
        from mld_core.rig import keyframes as keyedit

        rest = rig_io.read_rig(obj)
        if bone_map is None:
            bone_map = canonical_map(rest.names) if canonical and stored_map(obj) is None else bone_map_of(obj)
        report.bone_map = bone_map.source
        try:
            bone_map.validate(rest.names)
        except bone_maps.BoneMapError as exc:
            raise ValueError(missing_message(exc, obj.name)) from None
        bake = options.bake_options(fps, start)
        per_bone = options.rotation_modes(modes, bone_map.joints.values())
        for take in result.takes:
            t0 = time.perf_counter()
            contacts = take_contacts(take) if options.foot_lock else None
            if options.foot_lock and contacts is None:
                raise ValueError("Foot Lock needs a take of at least 2 frames; nothing was keyed")
            try:
                baked, _ = keyedit.take_to_keys(
                    take.joints, rest, bone_map, bake_options=bake, contacts=contacts,
                    rotation_modes=per_bone, fps=take.fps,
                )
            except bone_maps.BoneMapError as exc:
                raise ValueError(missing_message(exc, obj.name)) from None
            planned.append((take, baked, time.perf_counter() - t0))
    else:
        rest = rig.rig_rest(obj)
        for take in result.takes:
            t0 = time.perf_counter()
            channels = posing.pose_channels(take.local_quats, take.joints, rest, src_fps=take.fps, dst_fps=fps, exact=exact)
            planned.append((take, channels, time.perf_counter() - t0))

    # 2. Write them.
    existing = {a.name for a in bpy.data.actions}
    for index, (take, keyed, seconds) in enumerate(planned):
        t0 = time.perf_counter()
        name = naming.unique_name(take.name or naming.action_name(take.prompt, take.seed), existing)
        existing.add(name)
        props = take.provenance()
        props["mld_scene_fps"] = float(fps)
        props["mld_exact"] = int(bool(exact) and not through_keyedit)
        props["mld_retargeted"] = int(through_keyedit)
        first = assign and index == 0
        if through_keyedit:
            props.update(
                mld_bone_map=bone_map.source,
                mld_reduce=int(options.reduce),
                mld_tolerance_deg=float(options.tolerance_deg),
                mld_rotation_mode=options.rotation_mode,
                mld_foot_lock=int(options.foot_lock),
                mld_keys=int(keyed.num_keys),
                mld_reduction_ratio=float(keyed.stats["reduction_ratio"]),
            )
            action = keys.baked_to_action(
                obj, keyed, name, assign=first, nla=options.nla, properties=props,
                pose_properties=bone_map.pose_properties,
            )
            frames, n_keys = keyed.num_frames, keyed.num_keys
            report.reduction_ratios.append(float(keyed.stats["reduction_ratio"]))
        else:
            action = keys.channels_to_action(
                obj, keyed, name, frame_start=start, assign=first and not options.nla, properties=props
            )
            if options.nla:
                keys.push_to_nla(obj, action, keys.action_slot(action), start)
            frames = keyed.frames
            n_keys = keyed.frames * (4 * len(keyed.names) + 3 * len(keyed.keyed_locations))
            report.reduction_ratios.append(1.0)
        report.key_seconds += seconds + time.perf_counter() - t0
        report.actions.append(action.name)
        report.keys += n_keys
        if index == 0:
            report.frames = frames
    panel = getattr(scene, "mld_motion", None)
    if panel is not None and hasattr(panel, "last_reduction"):
        panel.last_reduction = report.reduction_ratio if through_keyedit and options.reduce else 1.0
    if set_frame_range and report.frames:
        scene.frame_start = start
        scene.frame_end = start + report.frames - 1
    return report
