"""An Action played on an armature, read back as the 22 joints (bpy, main thread): for "Export Actions as
Training Data". The armature's own Action, slot and the scene frame are put back afterwards."""

from __future__ import annotations

import numpy as np

from mld_core.motion.skeleton import JOINT_NAMES


def animates(action, obj, bone_map: dict[str, str]) -> bool:
    """Whether ``action`` keys any bone that plays a canonical joint on ``obj``."""
    from .armature_keys import _BONE
    from .write_action import fcurves_of

    bones = set(bone_map.values())
    return any((m := _BONE.match(fc.data_path)) and m.group(1) in bones for fc in fcurves_of(action, obj))


def action_joints(obj, action, scene, bone_map: dict[str, str]) -> np.ndarray:
    """World positions (T, 22, 3) of the mapped bones' heads at every frame of the Action's range (NaN for joints
    the map lacks; a missing toe is the ankle bone's tail)."""
    ad = obj.animation_data or obj.animation_data_create()
    before = (ad.action, getattr(ad, "action_slot", None), scene.frame_current)
    start, end = (int(round(v)) for v in action.frame_range)
    out = np.full((end - start + 1, 22, 3), np.nan)
    try:
        ad.action = action
        if hasattr(ad, "action_slot") and len(getattr(action, "slots", ())):
            ad.action_slot = action.slots[0]
        for i, frame in enumerate(range(start, end + 1)):
            scene.frame_set(frame)
            world = np.asarray(obj.matrix_world, np.float64)
            for k, joint in enumerate(JOINT_NAMES):
                bone = obj.pose.bones.get(bone_map.get(joint, ""))
                if bone is not None:
                    out[i, k] = world[:3, :3] @ np.asarray(bone.head) + world[:3, 3]
            for side in ("left", "right"):
                ankle = obj.pose.bones.get(bone_map.get(f"{side}_ankle", ""))
                toe = JOINT_NAMES.index(f"{side}_foot")
                if np.isnan(out[i, toe, 0]) and ankle is not None:
                    out[i, toe] = world[:3, :3] @ np.asarray(ankle.tail) + world[:3, 3]
    finally:
        ad.action = before[0]
        if before[1] is not None and hasattr(ad, "action_slot"):
            ad.action_slot = before[1]
        scene.frame_set(before[2])
    return out
