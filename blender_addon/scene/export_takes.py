"""Takes into a game engine (bpy; main thread only): chosen Actions of an armature written as FBX, GLB or BVH files
by Blender's own exporters, with the settings engines need.

``export_takes(obj, actions, files, settings, outputs)`` is what the batch (``--export``) and the panel's Export
Takes call. Each Action is played on the armature and read back as armature-space bone matrices; the math
(root motion, a loop's seam, the keys) is ``mld_core.rig.engine_export``, numpy only. The keys go onto a temporary
copy of the armature (named ``Armature``, its bones renamed for the engine, a root bone added for root motion,
its skinned meshes copied with renamed vertex groups), one NLA track per take named after it, and each file is
staged in ``outputs`` (``mld_core.fileio.OutputSet``: every file of a batch appears together or none does).
The copy, its keys and meshes are removed afterwards; the user's armature, Actions and scene are as before.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import bpy
import numpy as np

from mld_core.inputs import InputError
from mld_core.rig import engine_export as ee

from . import read_rig, write_action

EXPORT_NAME = "Armature"  # the exported armature object: Unreal takes a top node so named as no bone
EXPORTER_ADDONS = {"fbx": "io_scene_fbx", "glb": "io_scene_gltf2", "bvh": "io_anim_bvh"}

# Blender's FBX exporter, set for game engines (docs/game_engines.md): metres written as FBX units (Unity, Unreal
# and Godot read the file's unit scale), Y up / -Z forward (each engine converts the file's axis system), no leaf
# bones, every bone, each NLA strip its own animation (take), a key on every frame, none simplified away.
FBX_SETTINGS = dict(
    use_selection=True, object_types={"ARMATURE", "MESH"}, global_scale=1.0, apply_unit_scale=True,
    apply_scale_options="FBX_SCALE_UNITS", axis_forward="-Z", axis_up="Y", use_space_transform=True,
    bake_space_transform=False, add_leaf_bones=False, primary_bone_axis="Y", secondary_bone_axis="X",
    use_armature_deform_only=False, armature_nodetype="NULL", mesh_smooth_type="FACE", use_mesh_modifiers=False,
    bake_anim=True, bake_anim_use_all_bones=True, bake_anim_use_nla_strips=True, bake_anim_use_all_actions=False,
    bake_anim_force_startend_keying=True, bake_anim_step=1.0, bake_anim_simplify_factor=0.0, use_custom_props=False,
    path_mode="AUTO", embed_textures=False, batch_mode="OFF", check_existing=False,
)
# Blender's glTF exporter (binary .glb): Y up, each NLA track one animation (take) starting at 0 s, sampled on every
# frame with no key dropped, every bone, no leaf bones, the armature's rest as the skin's bind pose.
GLB_SETTINGS = dict(
    export_format="GLB", use_selection=True, export_yup=True, export_apply=False, export_animations=True,
    export_animation_mode="NLA_TRACKS", export_anim_slide_to_zero=True, export_force_sampling=True,
    export_frame_step=1, export_optimize_animation_size=False, export_anim_single_armature=True,
    export_def_bones=False, export_leaf_bone=False, export_reset_pose_bones=True, export_rest_position_armature=True,
    export_skins=True, export_morph=False, export_cameras=False, export_lights=False, export_extras=False,
    check_existing=False,
)
BVH_UNITS_PER_METRE = 100.0  # BVH in centimetres, like the batch's --bvh-dir (import with scale 0.01)


# -- checks -----------------------------------------------------------------------------------------------------
def hips_bone(bone_map) -> str:
    """The bone that plays the hips (the map's pelvis)."""
    return bone_map.joints.get("pelvis", "")


def root_problem(obj, actions, bone_map) -> str:
    """'' when every Action keys the hips bone of ``obj``'s bone map, else a sentence naming the first that does
    not (its travel could not be found, and an engine would get a still body)."""
    from .armature_keys import _BONE

    hips = hips_bone(bone_map)
    if not hips or hips not in obj.data.bones:
        return f"{obj.name!r} has no bone mapped to the hips (pelvis): map one in the Retarget panel"
    for action in actions:
        keyed = {m.group(1) for fc in write_action.fcurves_of(action, obj) if (m := _BONE.match(fc.data_path))}
        if hips not in keyed:
            return (f"Action {action.name!r} has no keys on {hips!r}, the bone mapped to the hips: it cannot be "
                    "exported as a take of this armature (key the hips, or pick another Action)")
    return ""


def ensure_exporters(settings: ee.ExportSettings) -> None:
    """Enable Blender's own exporters the settings need (they ship with Blender)."""
    import addon_utils

    for fmt in settings.formats:
        addon_utils.enable(EXPORTER_ADDONS[fmt], default_set=True)


# -- reading the takes ------------------------------------------------------------------------------------------
def sample_action(obj, action, scene) -> tuple[int, np.ndarray]:
    """(first frame, (T, B, 4, 4) armature-space matrices of every bone) over the Action's frame range, played on
    ``obj`` alone (its NLA tracks muted meanwhile); the armature's own Action, slot, NLA and the scene's frame are
    put back."""
    ad = obj.animation_data or obj.animation_data_create()
    before = (ad.action, getattr(ad, "action_slot", None), scene.frame_current, ad.use_nla)
    start, end = (int(round(v)) for v in action.frame_range)
    bones = obj.pose.bones
    flat = np.empty(len(bones) * 16, np.float32)
    pose = np.empty((end - start + 1, len(bones), 4, 4))
    try:
        ad.use_nla = False
        write_action.assign_action(obj, action)
        for i, frame in enumerate(range(start, end + 1)):
            scene.frame_set(frame)
            bones.foreach_get("matrix", flat)
            pose[i] = flat.reshape(-1, 4, 4).transpose(0, 2, 1)  # foreach_get gives each matrix column by column
    finally:
        ad.action = before[0]
        if before[0] is not None and before[1] is not None and hasattr(ad, "action_slot"):
            ad.action_slot = before[1]
        ad.use_nla = before[3]
        scene.frame_set(before[2])
    return start, pose


def world_up(obj) -> np.ndarray:
    """The world's up (+Z) in ``obj``'s armature space."""
    m = np.asarray(obj.matrix_world, np.float64)[:3, :3]
    up = np.linalg.solve(m, np.array([0.0, 0.0, 1.0]))
    return up / np.linalg.norm(up)


def metres_per_unit(obj, scene) -> float:
    scale = float(np.cbrt(abs(np.linalg.det(np.asarray(obj.matrix_world, np.float64)[:3, :3]))))
    return scale * float(scene.unit_settings.scale_length or 1.0)


# -- the exported armature --------------------------------------------------------------------------------------
class _ExportScene:
    """The temporary armature (and mesh copies) an export keys and writes; ``remove()`` takes it all away.

    ``axes``: a rotation (4, 4) from the user's armature space to the copy's (the copy's object matrix undoes it, so
    it stands where the armature stands): BVH files hold armature space, and a Y-up one is what BVH readers expect.
    The keys are the same in any armature space (only the rest turns)."""

    def __init__(self, obj, rig, out: ee.ExportRig, renames: dict, scene, axes=None, meshes: bool = True):
        from mathutils import Matrix

        self.scene, self.objects, self.actions = scene, [], []
        self._renamed = self._free_name(EXPORT_NAME)
        arm = bpy.data.armatures.new(EXPORT_NAME)
        self.armature = bpy.data.objects.new(EXPORT_NAME, arm)
        self.objects.append(self.armature)
        scene.collection.objects.link(self.armature)
        axes = np.eye(4) if axes is None else np.asarray(axes, np.float64)
        self.armature.matrix_world = obj.matrix_world @ Matrix(np.linalg.inv(axes).tolist())
        self._build_bones(obj, rig, out, axes)
        for pose_bone in self.armature.pose.bones:
            pose_bone.rotation_mode = "QUATERNION"
        for mesh in _skinned_meshes(obj) if meshes else ():
            self.objects.append(self._copy_mesh(mesh, renames))

    @staticmethod
    def _free_name(name: str):
        """Give the name ``name`` up for the export: an object already so named is renamed until ``remove``."""
        holder = bpy.data.objects.get(name)
        if holder is None:
            return None
        holder.name = name + ".mld_export_hold"
        return holder

    def _build_bones(self, obj, rig, out: ee.ExportRig, axes: np.ndarray) -> None:
        from mathutils import Matrix

        view_layer = bpy.context.view_layer
        previous = view_layer.objects.active
        view_layer.objects.active = self.armature
        bpy.ops.object.mode_set(mode="EDIT")
        try:
            edit = self.armature.data.edit_bones
            lengths = [max(float(np.linalg.norm(rig.tails[i] - rig.heads[i])), 1e-3) for i in range(len(rig.names))]
            made = []
            for name, source, rest in zip(out.names, out.source, out.rest):
                bone = edit.new(name)
                bone.head, bone.tail = (0.0, 0.0, 0.0), (0.0, lengths[source] if source >= 0 else max(lengths), 0.0)
                bone.matrix = Matrix((axes @ rest).tolist())
                bone.use_connect = False
                bone.use_deform = bool(obj.data.bones[rig.names[source]].use_deform) if source >= 0 else False
                made.append(bone)
            for bone, parent in zip(made, out.parents):
                if parent >= 0:
                    bone.parent = made[parent]
        finally:
            bpy.ops.object.mode_set(mode="OBJECT")
            view_layer.objects.active = previous

    def _copy_mesh(self, mesh, renames: dict):
        copy = mesh.copy()
        copy.data = mesh.data.copy()  # vertex group names live on the mesh: rename them on a copy only
        copy.hide_select = False
        self.scene.collection.objects.link(copy)
        for group in copy.vertex_groups:  # two passes, so a swap of names never collides
            group.name = f"mld_tmp_{group.index}"
        for group in copy.vertex_groups:
            old = mesh.vertex_groups[group.index].name
            group.name = renames.get(old, old)
        copy.parent = self.armature
        copy.matrix_parent_inverse = mesh.matrix_parent_inverse.copy()
        for modifier in copy.modifiers:
            if modifier.type == "ARMATURE":
                modifier.object = self.armature
        return copy

    def key(self, name: str, keys) -> object:
        action = write_action.keys_to_action(self.armature, keys, f"{name}.mld_export", assign=False)
        self.actions.append(action)
        return action

    def play_only(self, takes) -> None:
        """One NLA track per take (track and strip named after it), nothing else playing."""
        ad = self.armature.animation_data or self.armature.animation_data_create()
        ad.action = None
        for track in list(ad.nla_tracks):
            ad.nla_tracks.remove(track)
        for name, action, frame_start in takes:
            track = ad.nla_tracks.new()
            track.name = name
            strip = track.strips.new(name, int(frame_start), action)
            strip.name = name
            slot = write_action.action_slot(action)
            if slot is not None and hasattr(strip, "action_slot"):
                strip.action_slot = slot

    def select(self) -> None:
        view_layer = bpy.context.view_layer
        for other in view_layer.objects:
            if other.select_get():
                other.select_set(False)
        for obj in self.objects:
            obj.select_set(True)
        view_layer.objects.active = self.armature

    def remove(self) -> None:
        for action in self.actions:
            if action.name not in bpy.data.actions:
                continue
            bpy.data.actions.remove(action)
        for obj in reversed(self.objects):
            data = obj.data
            bpy.data.objects.remove(obj)
            if data is not None and data.users == 0:
                (bpy.data.armatures if isinstance(data, bpy.types.Armature) else bpy.data.meshes).remove(data)
        if self._renamed is not None:
            self._renamed.name = EXPORT_NAME


def y_up_axes(obj) -> np.ndarray:
    """(4, 4) the rotation from ``obj``'s armature space to a Y-up space facing as the world does (BVH's axes)."""
    m = np.asarray(obj.matrix_world, np.float64)[:3, :3]
    rotation = m / np.cbrt(abs(np.linalg.det(m)))
    out = np.eye(4)
    out[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]) @ rotation  # world Z up -> Y up
    return out


def _skinned_meshes(obj) -> list:
    """Meshes deformed by ``obj`` (an Armature modifier pointing at it)."""
    return [o for o in bpy.data.objects if o.type == "MESH" and any(
        m.type == "ARMATURE" and m.object == obj for m in o.modifiers) and o.name in bpy.context.scene.objects]


# -- writing ----------------------------------------------------------------------------------------------------
def _write(fmt: str, path: str, export: _ExportScene, takes: list) -> None:
    """Write ``takes`` [(name, action, first frame, last frame)] of the export armature into ``path``."""
    export.select()
    if fmt == "fbx":
        export.play_only([(n, a, s) for n, a, s, _ in takes])
        result = bpy.ops.export_scene.fbx(filepath=path, **FBX_SETTINGS)
    elif fmt == "glb":
        export.play_only([(n, a, s) for n, a, s, _ in takes])
        result = bpy.ops.export_scene.gltf(filepath=path, **GLB_SETTINGS)
    else:
        (name, action, start, end), = takes
        export.play_only([])
        write_action.assign_action(export.armature, action)
        result = bpy.ops.export_anim.bvh(filepath=path, global_scale=BVH_UNITS_PER_METRE * _unit_scale(export.scene),
                                         frame_start=int(start), frame_end=int(end), rotate_mode="NATIVE",
                                         root_transform_only=False, check_existing=False)
    if "FINISHED" not in result:
        raise RuntimeError(f"Blender's {fmt.upper()} exporter did not finish writing {path}")


def _unit_scale(scene) -> float:
    return float(scene.unit_settings.scale_length or 1.0)


def _sha256(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def export_takes(obj, actions, files, settings: ee.ExportSettings, outputs, *, bone_map, scene=None) -> dict:
    """Stage every file of ``files`` (``engine_export.ExportFile``, takes named after ``actions``) in ``outputs``;
    returns the manifest's ``export`` section: the settings, each file with its takes and sha256, each take's frames,
    frame rate, travel and loop seam. Raises InputError (nothing staged) for a take without keys on the hips bone or
    bone names that would collide."""
    scene = scene or bpy.context.scene
    problem = root_problem(obj, actions, bone_map)
    if problem:
        raise InputError(problem)
    rig = read_rig.read_rig(obj)
    renames, root_name = ee.bone_renames(settings.bone_names, bone_map.joints, rig.names,
                                         root=settings.root_motion == "root-bone")
    out = ee.export_rig(rig, renames, root_name)
    ensure_exporters(settings)
    keys, reports = take_keys(obj, actions, rig, out, settings, bone_map, scene)
    state = _SceneState(scene)
    records = {}
    try:
        for bvh in (False, True):  # FBX and GLB from a copy in the armature's own space; BVH from a Y-up one
            chosen = [f for f in files if (f.format == "bvh") == bvh]
            if not chosen:
                continue
            export = _ExportScene(obj, rig, out, renames, scene, axes=y_up_axes(obj) if bvh else None,
                                  meshes=not bvh)
            try:
                keyed = {name: (export.key(name, baked), start, start + baked.num_frames - 1)
                         for name, (baked, start) in keys.items()}
                for f in chosen:
                    records[f.path] = _stage(outputs, f, export, [(name, *keyed[name]) for name in f.takes])
            finally:
                export.remove()
    finally:
        state.restore()
    return {"settings": settings.to_dict(), "armature": EXPORT_NAME, "bone_names": dict(renames),
            "root_bone": root_name or "", "files": [records[f.path] for f in files], "takes": reports}


def take_keys(obj, actions, rig, out: ee.ExportRig, settings: ee.ExportSettings, bone_map, scene
              ) -> tuple[dict, dict]:
    """({take: (keys for the exported armature, first frame)}, {take: its manifest report}): each Action played on
    ``obj`` and read back, its travel handled and, for a loop (the Action's ``mld_loop``), its seam closed."""
    fps = scene.render.fps / (scene.render.fps_base or 1.0)
    hips, up, unit = rig.index(hips_bone(bone_map)), world_up(obj), metres_per_unit(obj, scene)
    keys, reports = {}, {}
    for action in actions:
        start, pose = sample_action(obj, action, scene)
        take = ee.export_pose(rig, out, pose, hips, up, fps, settings.motion, loop=bool(action.get("mld_loop")),
                              metres_per_unit=unit)
        keys[action.name] = (ee.pose_keys(out.names, take.bases, start, fps), start)
        reports[action.name] = take.report
    return keys, reports


def stager(obj, names, plan, bone_map, scene):
    """For the batch: a function staging ``plan``'s files (``worker.export_plan.ExportPlan``) for the Actions
    ``names`` of ``obj`` in an OutputSet, returning the manifest's ``export`` section. ``bone_map``: the batch's
    --bone-map, else (None) the armature's own."""
    from . import key_takes

    bone_map = bone_map if bone_map is not None else key_takes.bone_map_of(obj)
    actions = [bpy.data.actions[name] for name in names]

    def stage(outputs) -> dict:
        section = export_takes(obj, actions, plan.files, plan.settings, outputs, bone_map=bone_map, scene=scene)
        return {"folder": str(plan.folder), **section}

    return stage


def _stage(outputs, f, export: _ExportScene, takes: list) -> dict:
    """Stage one file in ``outputs``; its manifest record (path, format, takes, sha256, bytes)."""
    record = {"path": str(f.path), "format": f.format, "takes": list(f.takes)}

    def write(tmp):
        _write(f.format, tmp, export, takes)
        record["sha256"], record["bytes"] = _sha256(tmp), Path(tmp).stat().st_size

    outputs.stage(f.path, write, suffix=ee.EXTENSIONS[f.format])
    return record


class _SceneState:
    """The selection, the active object, its mode and the frame, put back after an export (which works in Object
    Mode: the copy's bones are made in Edit Mode)."""

    def __init__(self, scene):
        view_layer = bpy.context.view_layer
        self.scene, self.frame = scene, scene.frame_current
        self.active = view_layer.objects.active
        self.selected = [o for o in view_layer.objects if o.select_get()]
        self.mode = getattr(self.active, "mode", "OBJECT")
        if self.active is not None and self.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")

    def restore(self) -> None:
        view_layer = bpy.context.view_layer
        for obj in view_layer.objects:
            obj.select_set(obj in self.selected)
        view_layer.objects.active = self.active
        if self.active is not None and self.mode != "OBJECT":
            bpy.ops.object.mode_set(mode=self.mode)
        self.scene.frame_set(self.frame)
