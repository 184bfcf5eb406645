"""IK controls keyed to match the FK pose (bpy, main thread): a control rig's limbs (Rigify) can then be switched
from FK to IK on any frame without jumping.

For each chain of the bone map's ``ik_controls`` ({"fk": [upper, lower, end], "ik": [root, end], "pole": bone}),
on every frame of the take, as Blender evaluates the keyed FK pose: the IK end control takes the FK end's matrix
(keeping their rest offset), the pole goes in front of the knee or elbow along the bend, then the IK root control
takes the FK upper bone's matrix (its parent may track the end control, so after an update), as Rigify's own
Snap IK->FK does. Their channels are keyed on every frame, in bulk, into the take's Action. Switched to IK, hands
and feet stay where FK puts them (within 0.3 mm); knees and elbows can move by centimetres where Rigify's IK
chain scales itself (docs/retarget.md).
"""

from __future__ import annotations

import numpy as np

from mld_core.rig.bone_maps import chain_bones
from mld_core.rig.keyframes import CurveKeys

ROTATION_PROPS = {"QUATERNION": ("rotation_quaternion", 4), "AXIS_ANGLE": ("rotation_axis_angle", 4)}


def usable_chains(obj, chains) -> list[dict]:
    pose = obj.pose.bones
    return [c for c in chains or () if all(b in pose for b in chain_bones(c))]


def ik_curves(obj, scene, chains, frames) -> list[CurveKeys]:
    """Keys (every frame of ``frames``) for the IK controls of ``chains`` matching ``obj``'s FK pose, which must be
    playing (its Action assigned)."""
    from mathutils import Matrix, Vector

    pose, bones = obj.pose.bones, obj.data.bones
    chains = usable_chains(obj, chains)
    if not chains:
        return []
    offset = {}  # IK control -> rest offset from its FK counterpart
    for c in chains:
        for fk, ik in ((c["fk"][0], c["ik"][0]), (c["fk"][2], c["ik"][1])):
            offset[ik] = (fk, bones[fk].matrix_local.inverted() @ bones[ik].matrix_local)
    poles = {c["pole"]: c for c in chains if "pole" in c}
    pole_distance = {p: (bones[p].head_local - bones[c["fk"][1]].head_local).length for p, c in poles.items()}
    controls = [c["ik"][1] for c in chains] + list(poles) + [c["ik"][0] for c in chains]
    values = {b: [] for b in controls}
    saved = scene.frame_current
    view_layer = scene.view_layers[0] if scene.view_layers else None
    try:
        for frame in frames:
            scene.frame_set(int(frame))
            for c in chains:  # 1. the end controls and the poles
                fk, rest_offset = offset[c["ik"][1]]
                pose[c["ik"][1]].matrix = pose[fk].matrix @ rest_offset
                if "pole" in c:
                    pose[c["pole"]].matrix = _pole_matrix(pose, c, pole_distance[c["pole"]], Matrix, Vector)
            if view_layer is not None:
                view_layer.update()
            for c in chains:  # 2. the root controls, whose parents may follow the end controls
                fk, rest_offset = offset[c["ik"][0]]
                pose[c["ik"][0]].matrix = pose[fk].matrix @ rest_offset
            if view_layer is not None:
                view_layer.update()
            for b in controls:
                values[b].append(_channels(pose[b]))
    finally:
        scene.frame_set(saved)
    return [curve for b in controls for curve in _curves(pose[b], np.array(values[b]), np.asarray(frames, float))]


def _pole_matrix(pose, chain, distance, Matrix, Vector):
    """The pole control's matrix: its rotation kept, in front of the middle joint along the bend, at its rest
    distance (straight limbs: along the upper bone's own bend axis)."""
    upper, middle, end = (pose[b].head for b in chain["fk"])
    line = (end - upper).normalized()
    bend = (middle - upper) - line * (middle - upper).dot(line)
    if bend.length < 1e-6:
        bend = pose[chain["fk"][0]].matrix.to_3x3() @ Vector((0.0, 0.0, 1.0))
    m = pose[chain["pole"]].matrix.copy()
    m.translation = middle + bend.normalized() * distance
    return m


def _channels(pb) -> list[float]:
    prop, _ = ROTATION_PROPS.get(pb.rotation_mode, ("rotation_euler", 3))
    return list(pb.location) + list(getattr(pb, prop))


def _curves(pb, values: np.ndarray, frames: np.ndarray) -> list[CurveKeys]:
    prop, size = ROTATION_PROPS.get(pb.rotation_mode, ("rotation_euler", 3))
    if prop == "rotation_quaternion":  # keep the signs continuous (no flips between frames)
        q = values[:, 3:]
        flip = np.cumprod(np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0))
        q[1:] *= flip[:, None]
    name = pb.name
    out = [CurveKeys(f'pose.bones["{name}"].location', i, name, frames, values[:, i]) for i in range(3)]
    return out + [CurveKeys(f'pose.bones["{name}"].{prop}', i, name, frames, values[:, 3 + i]) for i in range(size)]
