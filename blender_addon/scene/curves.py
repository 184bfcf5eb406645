"""Reading a curve object's shape (bpy, main thread): its evaluated points in world space, in order."""

from __future__ import annotations

import numpy as np


def curve_points(obj) -> np.ndarray:
    """(N, 3) world-space points along ``obj`` (a curve object), as Blender evaluates it (resolution, modifiers)."""
    import bpy

    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        local = np.zeros(len(mesh.vertices) * 3)
        mesh.vertices.foreach_get("co", local)
        local = local.reshape(-1, 3)  # (N, 3)
    finally:
        evaluated.to_mesh_clear()
    world = np.asarray(obj.matrix_world, np.float64)
    return local @ world[:3, :3].T + world[:3, 3]
