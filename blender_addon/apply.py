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


def scene_fps(scene) -> float:
    return scene.render.fps / (scene.render.fps_base or 1.0)


def check_target(obj) -> str:
    """'' if ``obj`` can take generated motion, else a sentence saying why not."""
    if obj is None:
        return "No target armature: pick one, or create the canonical armature"
    if obj.type != "ARMATURE":
        return f"{obj.name!r} is not an armature"
    missing = rig.missing_bones(obj)
    if missing:
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
    rest = rig.rig_rest(obj)
    fps = scene_fps(scene)
    report = ApplyReport(fps=fps)
    start = scene.frame_start
    existing = {a.name for a in bpy.data.actions}
    for index, take in enumerate(result.takes):
        t0 = time.perf_counter()
        channels = posing.pose_channels(take.local_quats, take.joints, rest, src_fps=take.fps, dst_fps=fps, exact=exact)
        name = naming.unique_name(take.name or naming.action_name(take.prompt, take.seed), existing)
        existing.add(name)
        props = take.provenance()
        props["mld_scene_fps"] = float(fps)
        props["mld_exact"] = int(bool(exact))
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
