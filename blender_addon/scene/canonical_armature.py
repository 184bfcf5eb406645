"""The canonical armature: the model's own 22-joint skeleton as Blender bones (bpy; main thread only).

Bones are named like the model's joints (``pelvis``, ``left_hip`` ...; Blender's name flipping knows the
left_/right_ prefixes), each bone's head sits on its joint, bones are not connected (so every bone's
location can be keyed and the posed heads equal the generated joints exactly), rotation is quaternion.
"""

from __future__ import annotations

import bpy
import numpy as np

from mld_core.rig import canonical_pose

CANONICAL_NAME = "MLD_Armature"
BODY_NAME = "MLD_Body"
CANONICAL_TAG = "mld_canonical"  # custom property on the armature object


def canonical_names() -> tuple:
    from mld_core.motion.skeleton import JOINT_NAMES

    return tuple(JOINT_NAMES)


def missing_bones(obj) -> list[str]:
    """Canonical bone names that ``obj`` (an armature) lacks."""
    if obj is None or obj.type != "ARMATURE":
        return list(canonical_names())
    bones = obj.data.bones
    return [n for n in canonical_names() if n not in bones]


def is_canonical(obj) -> bool:
    return obj is not None and obj.type == "ARMATURE" and not missing_bones(obj)


def _ensure_object_mode(context) -> None:
    obj = context.view_layer.objects.active
    if obj is not None and obj.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")


def create_canonical_armature(context, name: str = CANONICAL_NAME, *, location=(0.0, 0.0, 0.0), body: bool = True):
    """Create, link (to the active collection) and select the canonical armature; returns the object."""
    names, parents, heads, tails = canonical_pose.canonical_rig()
    _ensure_object_mode(context)
    arm = bpy.data.armatures.new(name)
    obj = bpy.data.objects.new(name, arm)
    obj.location = location
    obj[CANONICAL_TAG] = 1
    collection = context.collection or context.scene.collection
    collection.objects.link(obj)
    for other in context.view_layer.objects:
        if other.select_get():
            other.select_set(False)
    context.view_layer.objects.active = obj
    obj.select_set(True)
    bpy.ops.object.mode_set(mode="EDIT")
    try:
        edit_bones = arm.edit_bones
        created = []
        for j, bone_name in enumerate(names):
            bone = edit_bones.new(bone_name)
            bone.head = heads[j]
            bone.tail = tails[j]
            bone.roll = 0.0
            bone.use_connect = False
            bone.use_deform = True
            created.append(bone)
        for j, p in enumerate(parents):
            if p >= 0:
                created[j].parent = created[p]
    finally:
        bpy.ops.object.mode_set(mode="OBJECT")
    for pose_bone in obj.pose.bones:
        pose_bone.rotation_mode = "QUATERNION"
    arm.display_type = "OCTAHEDRAL"
    obj.show_in_front = True
    if body:
        add_body(obj, collection, names, parents, heads, tails)
    return obj


def add_body(armature_obj, collection, names, parents, heads, tails, name: str = BODY_NAME):
    """A low-poly mesh bound rigidly to the armature's bones (so renders show the figure)."""
    from .body import body_geometry

    verts, faces, owners = body_geometry(names, parents, heads, tails)
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(v) for v in verts], [], faces)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    obj.parent = armature_obj
    collection.objects.link(obj)
    groups = {n: obj.vertex_groups.new(name=n) for n in names}
    by_bone: dict[str, list[int]] = {}
    for index, bone in enumerate(owners):
        by_bone.setdefault(bone, []).append(index)
    for bone, indices in by_bone.items():
        groups[bone].add(indices, 1.0, "REPLACE")
    modifier = obj.modifiers.new("Armature", "ARMATURE")
    modifier.object = armature_obj
    obj.color = (0.85, 0.55, 0.3, 1.0)
    obj.hide_select = True
    return obj


def posed_heads(obj, scene, frames) -> np.ndarray:
    """Head positions (F, J, 3) of the canonical bones in armature space at each scene frame."""
    names = canonical_names()
    out = np.empty((len(frames), len(names), 3))
    for f, frame in enumerate(frames):
        scene.frame_set(int(frame))
        pose = obj.pose.bones
        out[f] = [pose[n].head[:] for n in names]
    return out
