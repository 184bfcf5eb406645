"""Generated takes -> Actions on an armature (bpy; main thread only).

``apply_result(obj, result, scene, ...)`` is the one function the operator (interactive and headless) and
the batch script share: one new Action per take, named from prompt and seed, keyed in bulk at the scene's
frame rate from the scene's start frame, provenance stored as custom properties; the first take is assigned.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from . import keys, naming, posing, rig


@dataclass
class ApplyReport:
    actions: list = field(default_factory=list)  # Action names, in take order
    frames: int = 0  # scene frames of the first take
    fps: float = 0.0
    key_seconds: float = 0.0  # time spent writing keys
    keys: int = 0  # keyframes written in total


# Other rigs: a provider ``fn(obj, take, scene_fps) -> posing.BoneChannels`` (bone names of ``obj``) that
# retargets a take, registered by the retarget feature. ``check_target`` then accepts armatures without the
# canonical bones (the provider raises ValueError with a message when it cannot map one).
_channel_providers: list = []


def register_channels_provider(fn) -> None:
    if fn not in _channel_providers:
        _channel_providers.append(fn)


def unregister_channels_provider(fn) -> None:
    if fn in _channel_providers:
        _channel_providers.remove(fn)


def scene_fps(scene) -> float:
    return scene.render.fps / (scene.render.fps_base or 1.0)


def check_target(obj) -> str:
    """'' if ``obj`` can take generated motion, else a sentence saying why not."""
    if obj is None:
        return "No target armature: pick one, or create the canonical armature"
    if obj.type != "ARMATURE":
        return f"{obj.name!r} is not an armature"
    missing = rig.missing_bones(obj)
    if missing and not _channel_providers:
        shown = ", ".join(missing[:4]) + (" ..." if len(missing) > 4 else "")
        return (
            f"{obj.name!r} lacks {len(missing)} of the model's bones ({shown}): "
            "use the canonical armature (Create Armature) or retarget the take"
        )
    return ""


def apply_result(obj, result, scene, *, exact: bool = True, set_frame_range: bool = False, assign: bool = True) -> ApplyReport:
    """Key every take of ``result`` (a generation.GenerationResult) onto ``obj`` as new Actions."""
    import bpy

    problem = check_target(obj)
    if problem:
        raise ValueError(problem)
    canonical = rig.is_canonical(obj)
    rest = rig.rig_rest(obj) if canonical else None
    fps = scene_fps(scene)
    report = ApplyReport(fps=fps)
    start = scene.frame_start
    existing = {a.name for a in bpy.data.actions}
    for index, take in enumerate(result.takes):
        t0 = time.perf_counter()
        if canonical:
            channels = posing.pose_channels(take.local_quats, take.joints, rest, src_fps=take.fps, dst_fps=fps, exact=exact)
        else:
            channels = _channel_providers[-1](obj, take, fps)
        name = naming.unique_name(take.name or naming.action_name(take.prompt, take.seed), existing)
        existing.add(name)
        props = take.provenance()
        props["mld_scene_fps"] = float(fps)
        props["mld_exact"] = int(bool(exact) and canonical)
        props["mld_retargeted"] = int(not canonical)
        action = keys.channels_to_action(
            obj, channels, name, frame_start=start, assign=assign and index == 0, properties=props
        )
        report.key_seconds += time.perf_counter() - t0
        report.actions.append(action.name)
        report.keys += channels.frames * (4 * len(channels.names) + 3 * len(channels.keyed_locations))
        if index == 0:
            report.frames = channels.frames
    if set_frame_range and report.frames:
        scene.frame_start = start
        scene.frame_end = start + report.frames - 1
    return report
