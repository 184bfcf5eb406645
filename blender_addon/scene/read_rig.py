"""The thin bpy side of retargeting: read an armature (and its scene) into plain records, build an armature from
arrays.

``read_record`` is the keying road's one read of the file: everything keying needs, as a bpy-free
``keying.RigRecord``. Everything else (the math) lives in :mod:`retarget`, :mod:`bone_maps` and :mod:`keyedit`, which never import bpy.
bpy is imported inside the functions, so this module imports anywhere.
"""

from __future__ import annotations

import numpy as np

from mld_core.rig.keying import RigRecord
from mld_core.rig.retarget import RigRest


def scene_fps(scene) -> float:
    """The scene's frame rate (fps / fps_base)."""
    return scene.render.fps / (scene.render.fps_base or 1.0)


def read_record(obj, scene) -> RigRecord:
    """What keying ``obj`` in ``scene`` needs, read once (main thread): the rest, the bone map the Retarget panel
    stored on it (``obj.mld_retarget``: rows and extras), each pose bone's rotation mode, the scene's rate and
    first frame."""
    modes = rotation_modes(obj)
    rest = read_rig(obj)
    data = getattr(obj, "mld_retarget", None)
    rows = tuple((row.joint, row.bone) for row in data.rows) if data is not None else ()
    return RigRecord(rest, rows, data.extras if data is not None else "", modes, scene_fps(scene), scene.frame_start)


def read_rig(obj) -> RigRest:
    """An armature object's rest pose (``bone.matrix_local``, tails, parents) and its world matrix."""
    if obj is None or getattr(obj, "type", None) != "ARMATURE":
        raise ValueError("select an armature object (the active object is not an armature)")
    bones = list(obj.data.bones)
    if not bones:
        raise ValueError(f"armature {obj.name!r} has no bones")
    _update_transforms(obj)
    index = {b.name: i for i, b in enumerate(bones)}
    parents = [index[b.parent.name] if b.parent is not None else -1 for b in bones]
    matrices = np.array([[list(row) for row in b.matrix_local] for b in bones], dtype=np.float64)  # (B, 4, 4)
    tails = np.array([tuple(b.tail_local) for b in bones], dtype=np.float64)
    return RigRest(
        names=[b.name for b in bones],
        parents=parents,
        matrices=matrices,
        tails=tails,
        object_matrix=np.array([list(row) for row in obj.matrix_world], dtype=np.float64),
        use_connect=[b.use_connect for b in bones],
        name=obj.name,
    )


def _update_transforms(obj) -> None:
    """Bring ``obj.matrix_world`` up to date: an object appended, linked or moved by a script keeps a stale
    (often identity) world matrix until the view layer is evaluated, and the rig's rotation and scale (a Mixamo FBX
    import: 90 degrees about X, scale 0.01) would be ignored."""
    import bpy

    view_layer = getattr(bpy.context, "view_layer", None)
    if view_layer is not None:  # (an object just linked is not even listed in view_layer.objects before this)
        view_layer.update()


def rotation_modes(obj) -> dict[str, str]:
    """Each pose bone's rotation mode ('QUATERNION', 'XYZ', ..., 'AXIS_ANGLE')."""
    return {pb.name: pb.rotation_mode for pb in obj.pose.bones}


def build_armature(rig: RigRest, name: str = "Armature", rolls: np.ndarray | None = None):
    """Create an armature object from ``rig`` (heads, tails, parents; rolls taken from the rest matrices).

    Returns the new object, linked to the active collection. Used to build the canonical armature and fixtures.
    """
    import bpy

    arm = bpy.data.armatures.new(name)
    obj = bpy.data.objects.new(name, arm)
    bpy.context.collection.objects.link(obj)
    obj.matrix_world = [list(r) for r in rig.object_matrix]
    prev_active = bpy.context.view_layer.objects.active
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode="EDIT")
    try:
        ebones = []
        for i, bone_name in enumerate(rig.names):
            eb = arm.edit_bones.new(bone_name)
            eb.head = tuple(rig.heads[i])
            eb.tail = tuple(rig.tails[i])
            # align_roll makes the bone's Z axis point along the given vector: the rest matrix's Z column.
            eb.align_roll(tuple(rig.matrices[i, :3, 2]))
            ebones.append(eb)
        for i, p in enumerate(rig.parents):
            if p >= 0:
                ebones[i].parent = ebones[p]
                connected = rig.use_connect is not None and rig.use_connect[i]
                ebones[i].use_connect = bool(connected)
    finally:
        bpy.ops.object.mode_set(mode="OBJECT")
        if prev_active is not None:
            bpy.context.view_layer.objects.active = prev_active
    return obj


def evaluated_heads(obj, depsgraph=None) -> dict[str, np.ndarray]:
    """World-space head of every pose bone as Blender evaluates the current frame (for checks and tests)."""
    import bpy

    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(depsgraph)
    mw = np.array([list(r) for r in ev.matrix_world])
    out = {}
    for pb in ev.pose.bones:
        h = np.array(tuple(pb.head), dtype=np.float64)
        out[pb.name] = mw[:3, :3] @ h + mw[:3, 3]
    return out
