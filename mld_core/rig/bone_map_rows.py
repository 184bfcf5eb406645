"""A bone map as the panel stores it (bpy-free): one row per canonical joint (``joint -> bone``, required joints
marked) and a JSON string for the rest (source, parent overrides, pose properties); both ways."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Iterable

from mld_core.rig import bone_maps as bm

MAP_FORMAT = "mld-bone-map/1"


@dataclass(frozen=True)
class MapRow:
    joint: str
    bone: str  # '' when unmapped
    required: bool


def joint_names() -> tuple[str, ...]:
    from mld_core.motion.skeleton import JOINT_NAMES

    return tuple(JOINT_NAMES)


def map_to_rows(bone_map: bm.BoneMap | None) -> list[MapRow]:
    """One row per canonical joint, in skeleton order; unmapped joints get ''."""
    joints = bone_map.joints if bone_map is not None else {}
    return [MapRow(j, joints.get(j, ""), j in bm.REQUIRED_JOINTS) for j in joint_names()]


def map_extras(bone_map: bm.BoneMap) -> str:
    """What the rows do not hold (source, parent overrides, pose properties) as a JSON string."""
    return json.dumps(
        {
            "format": MAP_FORMAT,
            "source": bone_map.source,
            "parent_overrides": dict(bone_map.parent_overrides),
            "pose_properties": {b: dict(p) for b, p in bone_map.pose_properties.items()},
            "ik_controls": [dict(c) for c in bone_map.ik_controls],
        },
        sort_keys=True,
    )


def rows_to_map(rows: Iterable, extras: str = "") -> bm.BoneMap:
    """A BoneMap from rows (anything with ``.joint`` and ``.bone``, or (joint, bone) pairs) and the extras JSON.
    Overrides and pose properties of bones no longer in the map are dropped."""
    joints = {}
    for row in rows:
        joint, bone = (row.joint, row.bone) if hasattr(row, "joint") else (row[0], row[1])
        if bone:
            joints[str(joint)] = str(bone)
    data = {}
    if extras:
        try:
            data = json.loads(extras)
        except json.JSONDecodeError:
            data = {}
        if not isinstance(data, dict):
            data = {}
    used = set(joints.values())
    overrides = {c: p for c, p in dict(data.get("parent_overrides", {})).items() if c in used}
    props = {b: dict(p) for b, p in dict(data.get("pose_properties", {})).items()}
    try:
        chains = bm.ik_chains(data.get("ik_controls", []))
    except (bm.BoneMapError, AttributeError, TypeError):
        chains = []
    return bm.BoneMap(joints, source=str(data.get("source", "user")), parent_overrides=overrides, pose_properties=props,
                      ik_controls=chains)
