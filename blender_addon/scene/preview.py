"""A preview picture of a take: a strip of frames of the posed figure, rendered headless (bpy).

Workbench renders in the bpy module without a display (software OpenGL, about 1 s to start); Cycles on the
CPU is the fallback. The armature needs its body mesh (``rig.add_body``) to show up: armatures do not
render. Everything added for the picture (camera, light, floor, world) is removed again afterwards and the
scene's render settings are restored.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import bpy
import numpy as np

TILE_W, TILE_H = 240, 320


def strip_frames(frame_start: int, frame_end: int, count: int) -> list[int]:
    """``count`` frames spread evenly over [frame_start, frame_end] (first and last included)."""
    if frame_end <= frame_start or count <= 1:
        return [frame_start]
    return sorted(set(int(round(x)) for x in np.linspace(frame_start, frame_end, count)))


class _Stage:
    """Temporary camera/floor/world + render settings; restores the scene on exit."""

    def __init__(self, scene, engine: str):
        self.scene = scene
        self.engine = engine
        self.added = []

    def __enter__(self):
        scene = self.scene
        render = scene.render
        self.saved = {
            "camera": scene.camera,
            "engine": render.engine,
            "res": (render.resolution_x, render.resolution_y, render.resolution_percentage),
            "frame": scene.frame_current,
            "world": scene.world,
            "filepath": render.filepath,
            "format": render.image_settings.file_format,
            "film": render.film_transparent,
            "view": scene.view_settings.view_transform,
        }
        try:
            scene.view_settings.view_transform = "Standard"  # true colours (AgX/Filmic would grey them)
        except TypeError:
            pass
        render.engine = self.engine
        render.resolution_x, render.resolution_y, render.resolution_percentage = TILE_W, TILE_H, 100
        render.image_settings.file_format = "PNG"
        render.film_transparent = False
        if self.engine == "BLENDER_WORKBENCH":
            shading = scene.display.shading
            shading.light = "STUDIO"
            shading.color_type = "OBJECT"
            shading.show_shadows = True
            shading.show_cavity = False
            scene.display.render_aa = "8"
        else:
            scene.cycles.samples = 8
            scene.cycles.device = "CPU"
        world = bpy.data.worlds.new("MLD_PreviewWorld")
        world.color = (0.9, 0.92, 0.95)
        scene.world = world
        self.added.append(world)
        cam_data = bpy.data.cameras.new("MLD_PreviewCamera")
        cam_data.type = "ORTHO"
        cam_data.ortho_scale = 2.4
        self.camera = bpy.data.objects.new("MLD_PreviewCamera", cam_data)
        scene.collection.objects.link(self.camera)
        scene.camera = self.camera
        self.added += [self.camera, cam_data]
        floor_mesh = bpy.data.meshes.new("MLD_PreviewFloor")
        s = 50.0
        floor_mesh.from_pydata([(-s, -s, 0), (s, -s, 0), (s, s, 0), (-s, s, 0)], [], [(0, 1, 2, 3)])
        self.floor = bpy.data.objects.new("MLD_PreviewFloor", floor_mesh)
        self.floor.color = (1.0, 1.0, 1.0, 1.0)
        scene.collection.objects.link(self.floor)
        self.added += [self.floor, floor_mesh]
        if self.engine != "BLENDER_WORKBENCH":
            sun_data = bpy.data.lights.new("MLD_PreviewSun", "SUN")
            sun_data.energy = 3.0
            sun = bpy.data.objects.new("MLD_PreviewSun", sun_data)
            sun.rotation_euler = (0.6, 0.2, 0.8)
            scene.collection.objects.link(sun)
            self.added += [sun, sun_data]
        return self

    def aim(self, center) -> None:
        """Put the camera in front of the figure (front-left, slightly above), looking at ``center``."""
        from mathutils import Vector

        target = Vector((center[0], center[1], 0.95))
        offset = Vector((2.6, -4.5, 1.0))  # the figure faces -Y: the camera sees it from the front-left
        self.camera.location = target + offset
        self.camera.rotation_euler = (-offset).to_track_quat("-Z", "Y").to_euler()

    def __exit__(self, *exc):
        scene = self.scene
        render = scene.render
        scene.camera = self.saved["camera"]
        render.engine = self.saved["engine"]
        render.resolution_x, render.resolution_y, render.resolution_percentage = self.saved["res"]
        render.filepath = self.saved["filepath"]
        render.image_settings.file_format = self.saved["format"]
        render.film_transparent = self.saved["film"]
        scene.world = self.saved["world"]
        scene.view_settings.view_transform = self.saved["view"]
        for block in self.added:
            collection = {
                bpy.types.Object: bpy.data.objects,
                bpy.types.Camera: bpy.data.cameras,
                bpy.types.Mesh: bpy.data.meshes,
                bpy.types.World: bpy.data.worlds,
                bpy.types.Light: bpy.data.lights,
            }
            for kind, data in collection.items():
                if isinstance(block, kind):
                    data.remove(block)
                    break
        scene.frame_set(self.saved["frame"])
        return False


def _read_png(path: str) -> np.ndarray:
    image = bpy.data.images.load(path, check_existing=False)
    try:
        w, h = image.size
        pixels = np.empty(w * h * 4, np.float32)
        image.pixels.foreach_get(pixels)
        return pixels.reshape(h, w, 4)
    finally:
        bpy.data.images.remove(image)


def _write_png(path: Path, pixels: np.ndarray, scene) -> None:
    """RGB PNG at maximum compression (through the scene's output settings, restored afterwards)."""
    h, w = pixels.shape[:2]
    image = bpy.data.images.new("MLD_PreviewStrip", width=w, height=h, alpha=False)
    settings = scene.render.image_settings
    view = scene.view_settings
    saved = (settings.file_format, settings.color_mode, settings.compression, view.view_transform)
    try:
        image.pixels.foreach_set(pixels.astype(np.float32).ravel())
        settings.file_format, settings.color_mode, settings.compression = "PNG", "RGB", 100
        view.view_transform = "Standard"  # the tiles are display colours already
        image.save_render(str(path), scene=scene)
    finally:
        settings.file_format, settings.color_mode, settings.compression, view.view_transform = saved
        bpy.data.images.remove(image)


def render_strip(scene, armature, out_path, frames: list[int], *, engine: str = "BLENDER_WORKBENCH") -> Path:
    """Render ``frames`` of ``armature``'s current animation side by side into one PNG (atomically)."""
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tiles = []
    with tempfile.TemporaryDirectory(prefix="mld_preview_") as tmp, _Stage(scene, engine) as stage:
        for index, frame in enumerate(frames):
            scene.frame_set(frame)
            pelvis = armature.pose.bones.get("pelvis")
            center = armature.matrix_world @ (pelvis.head if pelvis is not None else armature.location)
            stage.aim(center)
            scene.render.filepath = os.path.join(tmp, f"f{index:03d}.png")
            bpy.ops.render.render(write_still=True)
            tiles.append(_read_png(scene.render.filepath))
    gap = np.ones((TILE_H, 4, 4), np.float32)
    parts = []
    for tile in tiles:
        parts += [tile, gap]
    strip = np.concatenate(parts[:-1], axis=1)
    from mld_core.fileio import atomic_write

    return atomic_write(out_path, lambda tmp: _write_png(Path(tmp), strip, scene), suffix=".png")


def render_preview(scene, armature, out_path, *, count: int = 5, frame_start=None, frame_end=None) -> Path:
    """A strip of ``count`` frames over the scene range; Workbench first, Cycles if Workbench cannot run."""
    start = scene.frame_start if frame_start is None else frame_start
    end = scene.frame_end if frame_end is None else frame_end
    frames = strip_frames(start, end, count)
    try:
        return render_strip(scene, armature, out_path, frames, engine="BLENDER_WORKBENCH")
    except RuntimeError as exc:
        print(f"MLD: Workbench render failed ({exc}); trying Cycles on the CPU")
        return render_strip(scene, armature, out_path, frames, engine="CYCLES")
