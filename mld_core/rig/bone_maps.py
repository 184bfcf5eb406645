"""Bone maps: which bone of a user's armature plays which joint of the canonical skeleton (numpy-free, no bpy).

A bone map is ``canonical joint name -> bone name`` (the bone whose head sits at that joint), plus what a control
rig needs to be driven (parents to follow, pose-bone properties such as Rigify's IK/FK switches). Maps come from
presets (``presets/*.json`` beside this file), from automatic detection (presets scored against the bone names,
else a fuzzy match on names, sides and the chain hierarchy), or from a JSON file the user saved.

Preset JSON: ``{"name", "label", "description", "bones": {joint: name | [alternatives...]},
"parent_overrides": {bone: followed bone}, "pose_properties": {bone: {property: value}}}``. Alternatives are
tried in order and a bone is used once, in the order the joints are listed. Names match exactly first, else with
any namespace (``mixamorig1:``, ``Armature|``) ignored and case-insensitively.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

from mld_core.motion.skeleton import JOINT_NAMES

PRESET_DIR = Path(__file__).resolve().parent / "presets"

REQUIRED_JOINTS = (
    "pelvis", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "head",
)


class BoneMapError(ValueError):
    """A bone map that cannot be used; ``missing`` lists required joints with no bone, ``absent`` bones not found."""

    def __init__(self, message: str, missing: Sequence[str] = (), absent: Sequence[str] = ()):
        super().__init__(message)
        self.missing = list(missing)
        self.absent = list(absent)


@dataclass
class BoneMap:
    """joints: canonical joint -> bone name; source: preset name, "auto" (fuzzy detection), or "file"/"user"."""

    joints: dict[str, str]
    source: str = "user"
    parent_overrides: dict[str, str] = field(default_factory=dict)
    pose_properties: dict[str, dict[str, float]] = field(default_factory=dict)
    # IK chains to key consistent with the FK pose: [{"fk": [upper, lower, end], "ik": [root, end], "pole": bone}]
    ik_controls: list[dict] = field(default_factory=list)

    def __post_init__(self) -> None:
        unknown = [j for j in self.joints if j not in JOINT_NAMES]
        if unknown:
            raise BoneMapError(f"unknown joint names in bone map: {', '.join(unknown)}")
        self.joints = {j: self.joints[j] for j in JOINT_NAMES if self.joints.get(j)}

    def missing(self) -> list[str]:
        return [j for j in REQUIRED_JOINTS if j not in self.joints]

    def validate(self, bone_names: Iterable[str]) -> None:
        """Raise :class:`BoneMapError` naming every required joint without a bone and every bone not in the rig."""
        names = set(bone_names)
        missing = self.missing()
        absent = [f"{j} -> {b!r}" for j, b in self.joints.items() if b not in names]
        dup = sorted({b for b in self.joints.values() if list(self.joints.values()).count(b) > 1})
        problems = []
        if missing:
            problems.append("no bone for the required joints: " + ", ".join(missing))
        if absent:
            problems.append("bones not in the armature: " + ", ".join(absent))
        if dup:
            problems.append("bones used for more than one joint: " + ", ".join(dup))
        if problems:
            raise BoneMapError("Bone map incomplete - " + "; ".join(problems) + ". Nothing was keyed.",
                               missing=missing, absent=[a.split(" -> ")[0] for a in absent])

    # --- JSON --------------------------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {
            "format": "mld-bone-map/1",
            "source": self.source,
            "bones": dict(self.joints),
            "parent_overrides": dict(self.parent_overrides),
            "pose_properties": {b: dict(p) for b, p in self.pose_properties.items()},
            "ik_controls": [dict(c) for c in self.ik_controls],
        }

    @classmethod
    def from_dict(cls, data: Mapping) -> "BoneMap":
        if not isinstance(data, Mapping) or not isinstance(data.get("bones"), Mapping):
            raise BoneMapError("not a bone map: expected a JSON object with a 'bones' object")
        bones = {}
        for joint, name in data["bones"].items():
            if isinstance(name, list):  # a preset file: keep the first alternative
                name = name[0] if name else ""
            if name and not isinstance(name, str):
                raise BoneMapError(f"bone name for {joint!r} must be a string")
            bones[joint] = name
        return cls(
            joints=bones,
            source=str(data.get("source", "file")),
            parent_overrides=dict(data.get("parent_overrides", {})),
            pose_properties={b: dict(p) for b, p in data.get("pose_properties", {}).items()},
            ik_controls=ik_chains(data.get("ik_controls", [])),
        )

    def save(self, path: str | os.PathLike) -> None:
        """Write as JSON (to a temporary file first, then renamed: an existing file is never half-written)."""
        from mld_core.fileio import atomic_write

        text = json.dumps(self.to_dict(), indent=2) + "\n"
        atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "BoneMap":
        """A map saved by :meth:`save` (read by the JSON reader of every user file: mld_core.inputs)."""
        from mld_core.inputs import InputError, parse_json

        with open(path, encoding="utf-8") as fh:
            text = fh.read()
        try:
            data = parse_json(text, os.fspath(path))
        except InputError as exc:
            raise BoneMapError(str(exc)) from None
        return cls.from_dict(data)


# --------------------------------------------------------------------------------------------------------------
# Presets.


@dataclass
class Preset:
    name: str
    label: str
    description: str
    bones: dict[str, list[str]]
    parent_overrides: dict[str, str] = field(default_factory=dict)
    pose_properties: dict[str, dict[str, float]] = field(default_factory=dict)
    ik_controls: list[dict] = field(default_factory=list)


def ik_chains(data) -> list[dict]:
    """IK chains from JSON: each {"fk": [upper, lower, end], "ik": [root control, end control], optionally "pole"
    (the pole control)}; malformed ones raise BoneMapError."""
    if data is not None and not isinstance(data, list):
        raise BoneMapError(f"'ik_controls' must be a list of IK chains, got {data!r}")
    chains = []
    for chain in data or []:
        if not isinstance(chain, dict):
            raise BoneMapError(f"an IK chain is an object {{'fk': [...], 'ik': [...]}}, got {chain!r}")
        fk, ik = chain.get("fk"), chain.get("ik")
        optional = {k: chain[k] for k in ("pole",) if chain.get(k)}
        if not (isinstance(fk, list) and len(fk) == 3 and isinstance(ik, list) and len(ik) == 2
                and all(isinstance(b, str) and b for b in fk + ik) and all(isinstance(b, str) for b in optional.values())):
            raise BoneMapError(f"an IK chain needs 'fk': [upper, lower, end], 'ik': [root, end] and optionally a 'pole' "
                               f"bone name, got {chain!r}")
        chains.append({"fk": list(fk), "ik": list(ik), **optional})
    return chains


def chain_bones(chain: dict) -> list[str]:
    """Every bone an IK chain names: its FK bones, its IK controls and its pole (if any)."""
    return chain["fk"] + chain["ik"] + ([chain["pole"]] if "pole" in chain else [])


def load_presets(directory: str | os.PathLike | None = None) -> dict[str, Preset]:
    """All presets in ``directory`` (default: the add-on's presets folder), by name, in a stable order."""
    directory = Path(directory) if directory is not None else PRESET_DIR
    presets = {}
    for path in sorted(directory.glob("*.json")):
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
        bones = {j: ([n] if isinstance(n, str) else list(n)) for j, n in data["bones"].items()}
        unknown = [j for j in bones if j not in JOINT_NAMES]
        if unknown:
            raise BoneMapError(f"preset {path.name} names unknown joints: {', '.join(unknown)}")
        presets[data["name"]] = Preset(
            name=data["name"],
            label=data.get("label", data["name"]),
            description=data.get("description", ""),
            bones=bones,
            parent_overrides=dict(data.get("parent_overrides", {})),
            pose_properties={b: dict(p) for b, p in data.get("pose_properties", {}).items()},
            ik_controls=ik_chains(data.get("ik_controls", [])),
        )
    order = ["canonical", "rigify", "rigify_metarig", "mixamo", "bandai", "bvh_common", "cmu_asf"]
    return dict(sorted(presets.items(), key=lambda kv: (order.index(kv[0]) if kv[0] in order else len(order), kv[0])))


def _key(name: str) -> str:
    """Namespace-free, case-free form of a bone name ("mixamorig1:LeftArm" -> "leftarm")."""
    return re.split(r"[:|]", name)[-1].lower()


def _lookup(wanted: str, names: Sequence[str], by_key: Mapping[str, list[str]]) -> tuple[str | None, bool]:
    if wanted in names:
        return wanted, True
    found = by_key.get(_key(wanted), [])
    return (found[0], False) if found else (None, False)


def apply_preset(preset: Preset, bone_names: Sequence[str]) -> tuple[BoneMap, int]:
    """The preset resolved against a rig's bone names, and how many of its names matched exactly."""
    names = list(bone_names)
    name_set = set(names)
    by_key: dict[str, list[str]] = {}
    for n in names:
        by_key.setdefault(_key(n), []).append(n)
    used: set[str] = set()
    joints = {}
    exact = 0
    for joint, alternatives in preset.bones.items():
        for alt in alternatives:
            found, is_exact = _lookup(alt, name_set, by_key)
            if found is not None and found not in used:
                joints[joint] = found
                used.add(found)
                exact += int(is_exact)
                break
    rename = {}
    for alt_names in preset.bones.values():
        for alt in alt_names:
            found, _ = _lookup(alt, name_set, by_key)
            if found is not None:
                rename[alt] = found

    def resolve(b: str) -> str | None:
        return rename.get(b) or _lookup(b, name_set, by_key)[0]

    overrides = {resolve(c): resolve(p) for c, p in preset.parent_overrides.items() if resolve(c) and resolve(p)}
    props = {resolve(b): dict(p) for b, p in preset.pose_properties.items() if resolve(b)}
    chains = []
    for chain in preset.ik_controls:  # a chain with a bone the rig lacks is left out
        bones = {k: ([resolve(b) for b in v] if isinstance(v, list) else resolve(v)) for k, v in chain.items()}
        if all(bones["fk"]) and all(bones["ik"]) and ("pole" not in chain or bones["pole"]):
            chains.append(bones)
    return BoneMap(joints, source=preset.name, parent_overrides=overrides, pose_properties=props,
                   ik_controls=chains), exact


# --------------------------------------------------------------------------------------------------------------
# Detection.


@dataclass
class Detection:
    """The detected map, where it came from, and every preset's score (matched joints, required joints covered)."""

    bone_map: BoneMap
    source: str
    scores: dict[str, tuple[int, int]]

    @property
    def missing(self) -> list[str]:
        return self.bone_map.missing()


def detect_bone_map(
    bone_names: Sequence[str],
    parents: Sequence[int] | Sequence[str | None] | None = None,
    presets: Mapping[str, Preset] | None = None,
) -> Detection:
    """Pick the preset that covers the rig best, else a fuzzy match on names, sides and hierarchy.

    bone_names: the armature's bones; parents: each bone's parent (index or name, -1 / None for roots), used by the
    fuzzy matcher. A preset wins when it maps every required joint (ties: more joints, then more exact names, then
    preset order); a preset matching at least half its names but not every required joint is kept and completed
    by the fuzzy match ("mixamo+auto"). The result may still miss required joints: see ``Detection.missing``.
    """
    names = list(bone_names)
    presets = load_presets() if presets is None else presets
    best = None
    partial = None
    scores = {}
    for preset in presets.values():
        bmap, exact = apply_preset(preset, names)
        required = sum(j in bmap.joints for j in REQUIRED_JOINTS)
        scores[preset.name] = (len(bmap.joints), required)
        rank = (len(bmap.joints), exact)
        if required == len(REQUIRED_JOINTS):
            if best is None or rank > best[0]:
                best = (rank, bmap)
        elif len(bmap.joints) >= len(preset.bones) / 2 and (partial is None or rank > partial[0]):
            partial = (rank, bmap)
    if best is not None:
        return Detection(best[1], best[1].source, scores)
    fuzzy = fuzzy_bone_map(names, parents)
    if partial is None:
        return Detection(fuzzy, "auto", scores)
    # The rig mostly follows a preset's naming: keep that, fill its gaps from the fuzzy match.
    base = partial[1]
    used = set(base.joints.values())
    for joint, bone in fuzzy.joints.items():
        if joint not in base.joints and bone not in used:
            base.joints[joint] = bone
            used.add(bone)
    merged = BoneMap(base.joints, source=f"{base.source}+auto", parent_overrides=base.parent_overrides,
                     pose_properties=base.pose_properties, ik_controls=base.ik_controls)
    return Detection(merged, merged.source, scores)


_SIDE_WORDS = {"l": "left", "left": "left", "lft": "left", "r": "right", "right": "right", "rgt": "right"}
_IGNORE_PREFIXES = ("mixamorig", "bip01", "bip001", "bip", "ccbase", "def", "b", "j", "jnt", "bn", "bone", "sk", "c")
_EXCLUDE = {
    "end", "nub", "top", "site", "tip", "twist", "roll", "ik", "pole", "target", "tweak", "mch", "org", "vis",
    "thumb", "index", "middle", "ring", "pinky", "finger", "fingers", "eye", "eyes", "jaw", "tongue", "teeth", "lip",
    "brow", "lid", "ear", "nose", "cheek", "chin", "breast", "heel", "palm", "parent", "socket", "helper", "pivot",
    "master", "prop", "weapon", "ctrl", "control", "offset", "null", "dummy", "upper_arm_parent", "hair", "tail",
    "share",
}
_ROLE_WORDS = {
    "pelvis": ("hips", "pelvis", "hip", "cog"),
    "spine": ("spine", "chest", "torso", "abdomen", "back", "waist", "upperchest", "lowerback", "belly", "stomach"),
    "neck": ("neck",),
    "head": ("head",),
    "collar": ("clavicle", "collar", "collarbone", "shoulder"),
    "upperarm": ("upperarm", "uparm", "arm", "humerus", "bicep", "shldr"),  # DAZ: lCollar -> lShldr -> lForeArm
    "forearm": ("forearm", "lowerarm", "loarm", "elbow"),
    "hand": ("hand", "wrist"),
    "thigh": ("thigh", "upleg", "upperleg", "femur", "hip", "uleg"),
    "shin": ("shin", "calf", "leg", "lowerleg", "loleg", "knee", "crus", "lleg"),
    "foot": ("foot", "ankle"),
    "toe": ("toe", "toes", "toebase", "ball"),
}


def split_name(name: str) -> tuple[str | None, str, list[str]]:
    """(side or None, core word without digits, tokens) of a bone name, e.g. "mixamorig:LeftUpLeg" ->
    ("left", "upleg", ["up", "leg"]), "thigh.L" -> ("left", "thigh", ["thigh"])."""
    core = re.split(r"[:|]", name)[-1]
    spaced = re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])|(?<=[A-Za-z])(?=[0-9])|(?<=[0-9])(?=[A-Za-z])",
                    " ", core)
    tokens = [t.lower() for t in re.split(r"[^A-Za-z0-9]+", spaced) if t]
    side = None
    kept = []
    for i, tok in enumerate(tokens):
        if tok in _SIDE_WORDS and side is None and (len(tokens) > 1):
            side = _SIDE_WORDS[tok]
            continue
        kept.append(tok)
    while kept and kept[0] in _IGNORE_PREFIXES and len(kept) > 1:
        kept = kept[1:]
    if side is None and kept:  # glued sides: "leftupleg", "lthigh" is not reliable enough; "leftarm" is
        for word, s in (("left", "left"), ("right", "right")):
            if kept[0].startswith(word) and len(kept[0]) > len(word):
                side, kept[0] = s, kept[0][len(word):]
                break
    words = [t for t in kept if not t.isdigit()]
    return side, "".join(words), words


def _roles(name: str) -> tuple[str | None, list[tuple[str, int]]]:
    """The side and the roles a bone name suggests, each with a strength (2 exact word, 1 contained)."""
    side, core, words = split_name(name)
    if not core or any(w in _EXCLUDE for w in words) or core in _EXCLUDE:
        return side, []
    roles = []
    for role, vocab in _ROLE_WORDS.items():
        if core in vocab:
            roles.append((role, 2))
        elif any(v in core for v in vocab if len(v) >= 4) and not core.endswith(("end", "nub", "top")):
            roles.append((role, 1))
    return side, roles


def fuzzy_bone_map(bone_names: Sequence[str], parents: Sequence | None = None) -> BoneMap:
    """Best-effort map from name keywords, left/right markers and the chain hierarchy (root -> leaves)."""
    match = _FuzzyMatch(list(bone_names), parents)
    for side in ("left", "right"):
        match.leg(side)
        match.arm(side)
    match.trunk()
    return BoneMap({j: match.names[i] for j, i in match.joints.items()}, source="auto")


class _FuzzyMatch:
    """The bones of one rig with their parents, depths and name roles, and the joints matched so far."""

    def __init__(self, names: list[str], parents: Sequence | None):
        self.names = names
        n = len(names)
        index = {nm: i for i, nm in enumerate(names)}
        self.par = [-1] * n
        for i, p in enumerate(parents if parents is not None else ()):
            self.par[i] = index.get(p, -1) if isinstance(p, str) else (-1 if p is None else int(p))
        self.depth = [len(self.ancestors(i)) for i in range(n)]
        self.info = [_roles(nm) for nm in names]
        self.joints: dict[str, int] = {}
        self.used: set[int] = set()

    def ancestors(self, i: int) -> list[int]:
        out = []
        while self.par[i] >= 0 and len(out) <= len(self.names):
            i = self.par[i]
            out.append(i)
        return out

    def candidates(self, role: str, side: str | None, under: int | None = None,
                   exclude: set[int] = frozenset()) -> list[int]:
        """Bones named for ``role`` on ``side`` (below ``under``): closest to the chain start first, exact words
        before contained ones."""
        found = []
        for i, (s, roles) in enumerate(self.info):
            if i in exclude or s != side:
                continue
            strength = max((st for r, st in roles if r == role), default=0)
            if not strength or (under is not None and under not in self.ancestors(i)):
                continue
            found.append((self.depth[i] - (self.depth[under] if under is not None else 0), -strength, i))
        return [i for _, _, i in sorted(found)]

    def take(self, joint: str, i: int | None) -> int | None:
        if i is not None:
            self.joints[joint] = i
            self.used.add(i)
        return i

    def first_of(self, role: str, side: str | None, under: int | None = None) -> int | None:
        found = self.candidates(role, side, under, self.used)
        return found[0] if found else None

    def lca(self, a: int, b: int) -> int | None:
        chain_b = set([b] + self.ancestors(b))
        return next((x for x in [a] + self.ancestors(a) if x in chain_b), None)

    def leg(self, side: str) -> None:
        thigh = self.take(f"{side}_hip", self.first_of("thigh", side))
        shin = self.take(f"{side}_knee", self.first_of("shin", side, thigh)) if thigh is not None else None
        foot = self.take(f"{side}_ankle", self.first_of("foot", side, shin)) if shin is not None else None
        if foot is not None:  # toes by name, else a foot-named bone below the ankle ("left_ankle" > "left_foot")
            toe = self.candidates("toe", side, foot, self.used) or self.candidates("foot", side, foot, self.used)
            self.take(f"{side}_foot", toe[0] if toe else None)

    def arm(self, side: str) -> None:
        upper = self.first_of("upperarm", side)
        collars = self.candidates("collar", side, exclude=self.used)
        if upper is None:  # "shoulder" naming the upper arm: the collar-like bone nearest the forearm
            with_forearm = [c for c in collars if self.candidates("forearm", side, c, self.used)]
            upper = max(with_forearm, key=lambda c: self.depth[c], default=None)
            collars = [c for c in collars if c != upper]
        self.take(f"{side}_shoulder", upper)
        if upper is None:
            return
        anc = set(self.ancestors(upper))
        self.take(f"{side}_collar", next((c for c in collars if c in anc), None))
        fore = self.take(f"{side}_elbow", self.first_of("forearm", side, upper))
        if fore is not None:
            self.take(f"{side}_wrist", self.first_of("hand", side, fore))

    def trunk(self) -> None:
        """The pelvis is where the legs branch (a "root" or "COG" above it is left alone), else a pelvis-like name;
        the spine runs from it to where the arms branch; neck and head above."""
        joints = self.joints
        pelvis = None
        if "left_hip" in joints and "right_hip" in joints:
            pelvis = self.lca(joints["left_hip"], joints["right_hip"])
        if pelvis is None:
            pelvis = self.first_of("pelvis", None)
        if pelvis is None:
            return
        self.take("pelvis", pelvis)
        arm_roots = [joints.get(f"{s}_collar", joints.get(f"{s}_shoulder")) for s in ("left", "right")]
        chest = self.lca(*arm_roots) if None not in arm_roots else None
        if chest is None or chest == pelvis:
            return
        # The spine starts at the pelvis, or where it branches off beside it (iClone: Hip -> Pelvis -> legs and
        # Hip -> Waist -> spine).
        base = pelvis if pelvis in self.ancestors(chest) else self.lca(pelvis, chest)
        if base is None or base == chest:
            return
        below = self.ancestors(chest)
        path = list(reversed([chest] + below[: below.index(base)]))  # just above the base .. the chest
        self.take("spine3", chest)
        if len(path) >= 2:
            self.take("spine1", path[0])
        if len(path) >= 3:
            self.take("spine2", path[len(path) // 2])
        head = self.take("head", self.first_of("head", None, chest))
        if head is None:
            return
        up_to_chest = self.ancestors(head)[: self.ancestors(head).index(chest)]
        between = list(reversed(up_to_chest))  # bones from the chest (exclusive) to the head (exclusive)
        necks = [a for a in between if any(r == "neck" for r, _ in self.info[a][1])]
        if necks or between:
            self.take("neck", (necks or between)[0])
