"""The poses an armature is already keyed in (bpy, main thread): at each keyed frame of its Action within a
take's range, where the bones that play canonical joints stand, in world space, for "Use Keys on the Armature"."""

from __future__ import annotations

import re

import numpy as np

_BONE = re.compile(r'^pose\.bones\["(.+?)"\]')


def keyed_poses(obj, scene, bone_map: dict[str, str], seconds: float, *, only_selected: bool = False,
                model_fps: float = 20.0) -> dict[int, dict[str, np.ndarray]]:
    """{model frame: {joint: world position of its bone's head}} at every scene frame from ``scene.frame_start``
    over ``seconds`` where a mapped bone (or, with ``only_selected``, a selected mapped bone) has a key."""
    from .write_action import fcurves_of

    ad = obj.animation_data
    if ad is None or ad.action is None:
        return {}
    fps = scene.render.fps / (scene.render.fps_base or 1.0)
    start, end = scene.frame_start, scene.frame_start + seconds * fps
    bones = {b: j for j, b in bone_map.items() if b in obj.pose.bones}
    if only_selected:
        bones = {b: j for b, j in bones.items() if _selected(obj.pose.bones[b])}
    keyed: dict[float, set[str]] = {}
    for fc in fcurves_of(ad.action, obj):
        m = _BONE.match(fc.data_path)
        if m and m.group(1) in bones:
            for k in fc.keyframe_points:
                if start <= k.co[0] < end:
                    keyed.setdefault(round(k.co[0]), set()).add(m.group(1))
    return _evaluate(obj, scene, bones, keyed, fps, model_fps)


def _selected(pose_bone) -> bool:
    """Blender 5.0 keeps bone selection on the pose bone; 4.x on the bone."""
    return bool(getattr(pose_bone, "select", False) or getattr(pose_bone.bone, "select", False))


def _evaluate(obj, scene, bones: dict, keyed: dict, fps: float, model_fps: float) -> dict:
    current = scene.frame_current
    poses = {}
    try:
        for frame, keyed_bones in sorted(keyed.items()):
            scene.frame_set(int(frame))
            world = np.asarray(obj.matrix_world, np.float64)
            model_frame = int(round((frame - scene.frame_start) * model_fps / fps))
            poses[model_frame] = {bones[b]: world[:3, :3] @ np.asarray(obj.pose.bones[b].head) + world[:3, 3]
                                  for b in keyed_bones}
    finally:
        scene.frame_set(current)
    return poses
