"""A simple low-poly body for the canonical armature (bpy-free geometry).

Six-sided tapered tubes along each bone segment plus a ball for the head, each part rigidly bound to one
bone (one vertex group per bone). It only exists so renders (and the preview image) show the figure;
armatures themselves do not render.
"""

from __future__ import annotations

import numpy as np

SIDES = 6
TORSO = {"pelvis", "spine1", "spine2", "spine3"}


def _radius(parent: str, child: str) -> float:
    if parent in TORSO and child in TORSO | {"neck"}:
        return 0.085
    if parent in TORSO:  # pelvis -> hips, spine3 -> collars
        return 0.06
    if "hip" in parent or "knee" in parent:
        return 0.055
    if "ankle" in parent or "foot" in parent:
        return 0.04
    if "collar" in parent or "shoulder" in parent:
        return 0.045
    if "elbow" in parent or "wrist" in parent:
        return 0.035
    return 0.045  # neck


def _frame(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to ``direction``."""
    d = direction / np.linalg.norm(direction)
    helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


def tube(start, end, r0: float, r1: float, sides: int = SIDES):
    """Vertices (2*sides + 2, 3) and faces of a closed tapered tube from start to end."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    u, v = _frame(end - start)
    angles = np.arange(sides) * (2 * np.pi / sides)
    ring = np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v  # (sides, 3)
    verts = np.concatenate([start + r0 * ring, end + r1 * ring, [start, end]])
    faces = []
    for i in range(sides):
        k = (i + 1) % sides
        faces.append((i, k, sides + k, sides + i))
        faces.append((2 * sides, k, i))
        faces.append((2 * sides + 1, sides + i, sides + k))
    return verts, faces


def ball(center, radius: float, rings: int = 5, segments: int = 8):
    """A low-poly UV sphere: vertices and faces."""
    center = np.asarray(center, float)
    verts = [center + [0, 0, radius]]
    for i in range(1, rings):
        theta = np.pi * i / rings
        for k in range(segments):
            phi = 2 * np.pi * k / segments
            verts.append(center + radius * np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)]))
    verts.append(center - [0, 0, radius])
    faces = []
    for k in range(segments):
        faces.append((0, 1 + k, 1 + (k + 1) % segments))
    for i in range(rings - 2):
        a, b = 1 + i * segments, 1 + (i + 1) * segments
        for k in range(segments):
            kk = (k + 1) % segments
            faces.append((a + k, b + k, b + kk, a + kk))
    last = len(verts) - 1
    base = 1 + (rings - 2) * segments
    for k in range(segments):
        faces.append((last, base + (k + 1) % segments, base + k))
    return np.asarray(verts), faces


def body_geometry(names, parents, heads, tails):
    """(vertices (V, 3), faces, bone name per vertex) for the whole figure in rest pose."""
    verts, faces, owners = [], [], []

    def add(part_verts, part_faces, bone):
        offset = sum(len(v) for v in verts)
        verts.append(np.asarray(part_verts))
        faces.extend(tuple(i + offset for i in f) for f in part_faces)
        owners.extend([bone] * len(part_verts))

    has_child = set(p for p in parents if p >= 0)
    for j, p in enumerate(parents):
        if p < 0:
            continue
        r = _radius(names[p], names[j])
        add(*tube(heads[p], heads[j], r, r * 0.85), names[p])
    for j, name in enumerate(names):
        if j in has_child:
            continue
        if name == "head":
            center = (np.asarray(heads[j]) + np.asarray(heads[parents[j]])) / 2 + [0, 0, 0.06]
            add(*ball(center, 0.1), name)
        else:
            r = 0.035 if "wrist" in name else 0.04
            add(*tube(heads[j], tails[j], r, r * 0.7), name)
    return np.concatenate(verts), faces, owners
