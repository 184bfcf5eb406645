"""Writing keyframes in bulk (bpy; main thread only): the keying road's last stage, :func:`write_takes`, writes
every planned take (``keying.TakeKeys``) as a new Action, keys IK controls to match (control rigs) and fills
an :class:`ApplyReport`.

Works with slotted Actions (Blender 4.4+, the only kind in 5.0: ``Action.fcurves`` is gone there) and with
the older flat Actions of 4.2/4.3. Every F-curve gets its keys with one ``keyframe_points.add`` and one
``foreach_set("co", ...)``; interpolation is set in bulk too.

The previous Action of the armature is never lost: it gets a fake user before the new one is assigned (it
stays in the file and in the Action browser). Generated Actions have a fake user too, so variants that are
not assigned survive saving.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import bpy
import numpy as np


def slotted_actions() -> bool:
    """True where Actions have slots and layers (Blender 4.4+)."""
    return hasattr(bpy.types.Action, "bl_rna") and "slots" in bpy.types.Action.bl_rna.properties


class ChannelWriter:
    """Creates F-curves (grouped per bone) on an Action for one object, either API."""

    def __init__(self, action, obj):
        self.action = action
        self.obj = obj
        self.slot = None
        self._groups = {}
        if slotted_actions():
            self.slot = action.slots.new(id_type="OBJECT", name=obj.name)
            layer = action.layers.new("Layer")
            strip = layer.strips.new(type="KEYFRAME")
            self._bag = strip.channelbag(self.slot, ensure=True)
        else:  # Blender 4.2 / 4.3
            self._bag = None

    def fcurve(self, data_path: str, index: int, group: str):
        if self._bag is not None:
            fc = self._bag.fcurves.new(data_path, index=index)
            grp = self._groups.get(group)
            if grp is None:
                grp = self._groups[group] = self._bag.groups.new(group)
            fc.group = grp
            return fc
        return self.action.fcurves.new(data_path, index=index, action_group=group)

    @classmethod
    def of(cls, action, obj) -> "ChannelWriter":
        """A writer adding F-curves to an Action made here (its first slot, layer and strip)."""
        writer = cls.__new__(cls)
        writer.action, writer.obj, writer._groups = action, obj, {}
        writer.slot = action_slot(action)
        writer._bag = action.layers[0].strips[0].channelbag(writer.slot, ensure=True) if writer.slot else None
        if writer._bag is not None:
            writer._groups = {g.name: g for g in writer._bag.groups}
        return writer

    def assign(self) -> None:
        assign_action(self.obj, self.action, self.slot)


def assign_action(obj, action, slot=None) -> None:
    """Play ``action`` (or nothing, None) on ``obj``: assign it and its slot (default: the Action's own)."""
    ad = obj.animation_data or obj.animation_data_create()
    ad.action = action
    slot = slot if slot is not None else (action_slot(action) if action is not None else None)
    if slot is not None:
        ad.action_slot = slot


def fcurves_of(action, obj=None) -> list:
    """All F-curves of an Action (either API)."""
    if not slotted_actions():
        return list(action.fcurves)
    curves = []
    for layer in action.layers:
        for strip in layer.strips:
            for slot in action.slots:
                bag = strip.channelbag(slot)
                if bag is not None:
                    curves.extend(bag.fcurves)
    return curves


def write_keys(fc, frames: np.ndarray, values: np.ndarray, interpolation: str = "LINEAR", *,
               handle_type: str | None = None, auto_smoothing: str | None = None) -> None:
    """Add ``len(frames)`` keys to an empty F-curve in bulk (replaces nothing).

    ``handle_type`` (e.g. 'AUTO_CLAMPED') sets both handles; ``auto_smoothing`` is set first, because Blender
    computes the handles from it when the curve updates (keyedit's key reduction assumes 'NONE').
    """
    if auto_smoothing is not None and hasattr(fc, "auto_smoothing"):
        fc.auto_smoothing = auto_smoothing
    n = len(frames)
    co = np.empty((n, 2), np.float32)  # (n, [frame, value])
    co[:, 0] = frames
    co[:, 1] = values
    points = fc.keyframe_points
    points.add(n)
    points.foreach_set("co", co.ravel())
    points.foreach_set("interpolation", np.full(n, _enum_index(bpy.types.Keyframe, "interpolation", interpolation), np.int32))
    if handle_type is not None:
        handle = np.full(n, _enum_index(bpy.types.Keyframe, "handle_left_type", handle_type), np.int32)
        points.foreach_set("handle_left_type", handle)
        points.foreach_set("handle_right_type", handle)
    fc.update()


def _enum_index(struct, prop: str, value: str) -> int:
    """The integer foreach_set wants for an enum value (read from RNA, so it follows Blender's numbering)."""
    items = list(struct.bl_rna.properties[prop].enum_items.keys())
    return items.index(value)


def keep_previous_action(obj) -> object | None:
    """Give the armature's current Action a fake user so replacing it loses nothing; returns it."""
    ad = obj.animation_data
    previous = ad.action if ad is not None else None
    if previous is not None and not previous.use_fake_user:
        previous.use_fake_user = True
    return previous


def _new_action(obj, bones, name: str, properties: dict | None):
    """A new Action (fake user, ``properties`` as custom properties) for keys on ``bones`` of armature ``obj``;
    refuses before creating anything when the armature lacks one of them."""
    missing = [b for b in bones if b not in obj.pose.bones]
    if missing:
        raise ValueError(f"armature {obj.name!r} has no bones named {', '.join(missing)}")
    action = bpy.data.actions.new(name)
    action.use_fake_user = True
    for key, value in (properties or {}).items():
        action[key] = value
    return action


def set_pose_properties(obj, pose_properties: dict) -> list[str]:
    """Set a bone map's ``pose_properties`` (e.g. Rigify's IK_FK = 1.0) on the pose bones; returns what was set."""
    done = []
    for bone, props in (pose_properties or {}).items():
        pb = obj.pose.bones.get(bone)
        if pb is None:
            continue
        for key, value in props.items():
            pb[key] = value
            done.append(f"{bone}[{key}]")
    return done


def posed_links(obj, keyed) -> list[str]:
    """Bones without keys between keyed ones whose pose is not their rest (a BVH import leaves its motion's pose on
    them when its Action is removed): the retargeting assumed them at rest, so the Action keys them there. Bones
    above every keyed one (Rigify's root control) keep their pose: that is where the user placed the character."""
    keyed = set(keyed)
    links = set()
    for name in keyed:
        bone = obj.data.bones.get(name)
        parent, between = (bone.parent if bone is not None else None), []
        while parent is not None:
            if parent.name in keyed:  # the unkeyed bones passed on the way up lie between two keyed ones
                links.update(between)
                between = []
            else:
                between.append(parent.name)
            parent = parent.parent
    identity = np.eye(4)
    return sorted(n for n in links
                  if not np.allclose(np.array(obj.pose.bones[n].matrix_basis, dtype=np.float64), identity, atol=1e-6))


def rest_curves(obj, bones, frame: float) -> list:
    """One key per channel holding each of ``bones`` at rest at ``frame`` (keyframes.CurveKeys)."""
    from mld_core.rig.keyframes import CurveKeys

    rest = {"QUATERNION": ("rotation_quaternion", (1.0, 0.0, 0.0, 0.0)),
            "AXIS_ANGLE": ("rotation_axis_angle", (0.0, 0.0, 1.0, 0.0))}
    curves = []
    for name in bones:
        rotation = rest.get(obj.pose.bones[name].rotation_mode, ("rotation_euler", (0.0, 0.0, 0.0)))
        for prop, values in (("location", (0.0, 0.0, 0.0)), rotation, ("scale", (1.0, 1.0, 1.0))):
            for index, value in enumerate(values):
                curves.append(CurveKeys(f'pose.bones["{name}"].{prop}', index, name, np.array([frame]),
                                        np.array([value])))
    return curves


def property_curves(pose_properties: dict | None, frame: float) -> list:
    """The bone map's ``pose_properties`` (Rigify's IK_FK switches ...) as one key each: stored with the Action, so
    playing another Action and coming back restores them."""
    from mld_core.rig.keyframes import CurveKeys

    return [CurveKeys(f'pose.bones["{bone}"]["{key}"]', 0, bone, np.array([frame]), np.array([float(value)]))
            for bone, props in (pose_properties or {}).items() for key, value in props.items()]


def push_to_nla(obj, action, slot, frame_start: float, segments=None):
    """Put ``action`` on a new NLA track of ``obj``: one strip starting at ``frame_start``, or with ``segments``
    ``[(name, first frame, last frame)]`` one strip per segment, each playing its own frames of the Action (a prompt
    sequence's take). Returns the strips."""
    ad = obj.animation_data or obj.animation_data_create()
    track = ad.nla_tracks.new()
    track.name = action.name
    strips = []
    for name, first, last in segments or [(action.name, frame_start, None)]:
        strip = track.strips.new(name, int(round(first)), action)
        if last is not None:  # the strip plays frames first..last of the Action, where they were keyed
            strip.action_frame_start, strip.action_frame_end = first, last
        if slot is not None and hasattr(strip, "action_slot") and strip.action_slot != slot:
            strip.action_slot = slot  # Blender 4.4+: a strip plays one slot of its action
        strips.append(strip)
    return strips


def keys_to_action(
    obj,
    baked,
    name: str,
    *,
    assign: bool = True,
    nla: bool = False,
    properties: dict | None = None,
    pose_properties: dict | None = None,
    segments: list | None = None,
):
    """A new Action holding ``baked`` (``keyframes.BakedKeys``, the one keys object of every rig) for ``obj``.

    Sets each keyed pose bone's rotation mode (``baked.rotation_modes``) and the bone map's ``pose_properties``;
    unkeyed bones above keyed ones that are not at rest get one key at rest (``posed_links``);
    with ``nla`` the Action goes onto a new NLA track as a strip, or one strip per ``segments`` entry (name, first
    and last frame; the active Action is left alone), otherwise it is assigned if asked (the previous Action keeps
    a fake user). Returns the Action.
    """
    pose_bones = obj.pose.bones
    bones = sorted({c.group for c in baked.curves})
    action = _new_action(obj, bones, name, properties)
    writer = ChannelWriter(action, obj)
    properties_here = {b: p for b, p in (pose_properties or {}).items() if b in pose_bones}
    extra = rest_curves(obj, posed_links(obj, bones), baked.frame_start) + property_curves(properties_here,
                                                                                            baked.frame_start)
    for curve in baked.curves + extra:
        fc = writer.fcurve(curve.data_path, curve.index, curve.group)
        write_keys(fc, curve.frames, curve.values, baked.interpolation, handle_type=baked.handle_type,
                   auto_smoothing=baked.auto_smoothing)
    for bone, mode in baked.rotation_modes.items():
        if bone in pose_bones:
            pose_bones[bone].rotation_mode = mode
    set_pose_properties(obj, pose_properties or {})
    if nla:
        push_to_nla(obj, action, writer.slot, baked.frame_start, segments)
    elif assign:
        keep_previous_action(obj)
        writer.assign()
    return action


def action_slot(action):
    """The (first) slot of an Action made here, or None before Blender 4.4."""
    if not slotted_actions() or not len(action.slots):
        return None
    return action.slots[0]


# -- the keying road's write stage ----------------------------------------------------------------------------
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


def write_takes(obj, scene, plan, planned, *, assign: bool = True, ik_controls: bool = True,
                set_frame_range: bool = False) -> ApplyReport:
    """One new Action per planned take (``keying.TakeKeys`` under ``plan``, a ``keying.KeyPlan``), named from its
    prompt and seed, the first assigned if ``assign`` (or each pushed to NLA); ``ik_controls``: also key the map's
    IK controls to match the FK pose. Then the panel's last reduction and, with ``set_frame_range``, the scene's
    end frame. Returns what was written."""
    from ..worker import naming

    retargeted, bone_map = not plan.exact, plan.bone_map
    report = ApplyReport(fps=plan.fps, nla=plan.settings.nla, retargeted=retargeted,
                         bone_map=bone_map.source if retargeted else "")
    existing = {a.name for a in bpy.data.actions}
    for index, planned_take in enumerate(planned):
        take, keys = planned_take.take, planned_take.keys
        t0 = time.perf_counter()
        name = naming.unique_name(take.name or naming.action_name(take.prompt, take.seed), existing)
        existing.add(name)
        action = keys_to_action(obj, keys, name, assign=assign and index == 0, nla=plan.settings.nla,
                                properties={**take.provenance(), **planned_take.properties},
                                pose_properties=bone_map.pose_properties if retargeted else {},
                                segments=planned_take.strips)
        if retargeted and ik_controls and bone_map.ik_controls:
            report.ik_keys += key_ik_controls(obj, scene, action, keys, bone_map.ik_controls)
        report.reduction_ratios.append(float(keys.stats.get("reduction_ratio", 1.0)))
        report.key_seconds += planned_take.seconds + time.perf_counter() - t0
        report.actions.append(action.name)
        report.keys += keys.num_keys
        if index == 0:
            report.frames = keys.num_frames
    panel = getattr(scene, "mld_motion", None)
    if panel is not None and hasattr(panel, "last_reduction"):
        panel.last_reduction = report.reduction_ratio if retargeted and plan.settings.reduce else 1.0
    if set_frame_range and report.frames:
        scene.frame_end = scene.frame_start + report.frames - 1
    return report


def key_ik_controls(obj, scene, action, keys, chains) -> int:
    """Key ``chains``' IK controls into ``action`` to match its FK pose (played for it on ``scene``, the take's own,
    then the armature's assignment restored); returns the keys written."""
    from . import ik_controls

    ad = obj.animation_data or obj.animation_data_create()
    before = (ad.action, getattr(ad, "action_slot", None))
    assign_action(obj, action)
    try:
        frames = keys.frame_start + np.arange(keys.num_frames, dtype=np.float64)
        curves = ik_controls.ik_curves(obj, scene, chains, frames)
        writer = ChannelWriter.of(action, obj)
        for curve in curves:
            write_keys(writer.fcurve(curve.data_path, curve.index, curve.group), curve.frames, curve.values,
                       keys.interpolation, handle_type=keys.handle_type, auto_smoothing=keys.auto_smoothing)
    finally:
        assign_action(obj, before[0], before[1] if before[0] is not None else None)
    return int(sum(len(c.frames) for c in curves))
