"""MLD text-to-motion for Blender: type a prompt, get keyframes on an armature.

Works as a Blender 4.2+ extension (``bl_ext.<repo>.mld_motion``, see ``blender_manifest.toml``) and as a
plain add-on package (``register()`` / ``unregister()``). Importing this package does not import bpy. Its folders:
``worker/`` (bpy-free: requests, the job runner, the model cache, generation), ``scene/`` (bpy: reading a rig,
writing an Action, the canonical armature, the preview) and ``ui/`` (bpy: operators, panels, properties,
preferences); ``batch.py`` runs headless. The rig math is in ``mld_core.rig``. See docs/architecture.md.
"""

# Read by Blender's legacy add-on loader (it parses this literal without running the module). The extension
# manifest carries the same version; tests/test_addon_core.py checks that the two agree.
bl_info = {
    "name": "MLD Text to Motion",
    "author": "MLD add-on contributors",
    "version": (0, 1, 0),
    "blender": (4, 2, 0),
    "location": "View3D > Sidebar > MLD",
    "description": "Generate armature animation from a text prompt (Motion Latent Diffusion)",
    "category": "Animation",
}

from . import env as _env  # noqa: E402  (bpy-free)

_env.setup_import_paths()

_bpy_modules = ()


def register():
    global _bpy_modules
    import importlib

    _env.add_user_site_packages()
    names = ("ui.preferences", "ui.properties", "ui.operators", "ui.panels")
    _bpy_modules = tuple(importlib.import_module(f"{__name__}.{n}") for n in names)
    for module in _bpy_modules:
        module.register()


def unregister():
    global _bpy_modules
    for module in reversed(_bpy_modules):
        module.unregister()
    _bpy_modules = ()
