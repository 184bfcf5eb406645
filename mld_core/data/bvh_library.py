"""``data prepare bvh``: a folder of BVH files in any skeleton, with captions, -> a HumanML3D-format training folder.

Per file: parse; map the skeleton onto the 22 joints with the add-on's bone-map detection (presets, then names and
hierarchy; ``--bone-map`` overrides); joints the skeleton lacks between mapped ones are interpolated (spine, neck,
collars) and a missing toe comes from the ankle's End Site; detect the up axis (Y or Z) and the units (from the leg
length); drop leading T-pose frames and leading frames that jump impossibly into the next (a rest or calibration
pose, ``mld_core.data.take_checks``); resample to 20 fps; cut each caption's span into training segments of at most
9.8 s; write only segments that pass the plausibility check (body height, feet reaching the floor, joint speeds);
mirror (captions' side words swapped). A file or segment that cannot be used is skipped with its reason in
``prepare_report.json`` and a summary line, never silently. The output layout is ``data prepare bandai``'s.
"""

from __future__ import annotations

import csv
import json
import re
import shutil
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mld_core.data import captions as cap
from mld_core.data import terms
from mld_core.data.bandai import (FORMAT_VERSION, MANIFEST, TARGET_FPS, PrepareError, _write_clip, assign_splits,
                                  check_out, resample_joints, source_fps, swap_into_place, write_splits,
                                  written_files)
from mld_core.data.take_checks import implausible, leading_jump_frames
from mld_core.motion.bvh import BVHError, read_bvh
from mld_core.motion.skeleton import JOINT_NAMES

REPORT = "prepare_report.json"
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
LEG_M = 0.85  # a typical hip-to-ankle length; the units whose leg is nearest to it (in log scale) win
MIN_SECONDS = 2.0
MAX_SECONDS = 9.8
_J = {name: i for i, name in enumerate(JOINT_NAMES)}
_SPINE = ("pelvis", "spine1", "spine2", "spine3", "neck")


@dataclass
class LibraryOptions:
    captions: Path | None = None  # CSV/TSV: file, caption[, start_s, end_s]
    caption_template: str | None = None  # e.g. "a person {name}" ({name}: the file name in words, {folder})
    bone_map: Path | None = None  # a saved bone map (JSON) instead of detection
    units: str | None = None  # m, cm, mm, in, ft or metres per unit; None: detect
    up: str | None = None  # "y" or "z"; None: detect
    mirror: bool = True
    licence: str = "its owner's"  # the library's terms, as terms.json records them (mld_core.data.terms)
    commercial: bool | None = None  # may weights trained on it go into commercial products; None: not said
    max_seconds: float = MAX_SECONDS
    min_seconds: float = MIN_SECONDS


@dataclass
class Caption:
    text: str
    start_s: float = 0.0
    end_s: float = 0.0  # 0: to the end of the clip


# --------------------------------------------------------------------------------------------------------------
# captions


def read_caption_table(path: Path) -> dict[str, list[Caption]]:
    """A CSV or TSV of ``file, caption[, start_s, end_s]`` rows (a header row is allowed): key -> captions, keyed by
    the file's path as written, its name and its stem (lower case)."""
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise PrepareError(f"cannot read --captions {path}: {getattr(exc, 'strerror', None) or exc}") from None
    dialect = "excel-tab" if text.strip() and "\t" in text.splitlines()[0] else "excel"
    table: dict[str, list[Caption]] = {}
    for n, row in enumerate(csv.reader(text.splitlines(), dialect=dialect), start=1):
        row = [c.strip() for c in row]
        if not any(row):
            continue
        if n == 1 and len(row) >= 2 and row[0].lower() in ("file", "filename", "path", "clip"):
            continue
        if len(row) < 2 or not row[1]:
            raise PrepareError(f"{path}, line {n}: expected 'file, caption[, start_s, end_s]'")
        try:
            start = float(row[2]) if len(row) > 2 and row[2] else 0.0
            end = float(row[3]) if len(row) > 3 and row[3] else 0.0
        except ValueError:
            raise PrepareError(f"{path}, line {n}: start_s and end_s must be numbers of seconds") from None
        if start < 0 or (end and end <= start):
            raise PrepareError(f"{path}, line {n}: the span {start}-{end} s is empty or negative")
        caption = Caption(row[1], start, end)
        for key in {row[0].lower(), Path(row[0]).name.lower(), Path(row[0]).stem.lower()}:
            table.setdefault(key, []).append(caption)
    return table


def _words(name: str) -> str:
    text = re.sub(r"[_\-.]+", " ", name)
    text = re.sub(r"(?<=[a-z])(?=[A-Z])", " ", text)
    return re.sub(r"\s+", " ", re.sub(r"\d+", " ", text)).strip().lower()


def file_captions(path: Path, src: Path, table: dict | None, template: str | None) -> list[Caption]:
    """The file's captions: rows of the table, else a .txt beside it (one caption per line), else the template."""
    if table:
        rel = path.relative_to(src).as_posix().lower()
        rows = {id(c): c for key in (rel, path.name.lower(), path.stem.lower()) for c in table.get(key, [])}
        if rows:  # a row may name the file by path, name or stem; each row once
            return list(rows.values())
    beside = path.with_suffix(".txt")
    if beside.is_file():
        lines = [ln.strip() for ln in beside.read_text(encoding="utf-8-sig").splitlines()]
        found = [Caption(ln) for ln in lines if ln]
        if found:
            return found
    if template:
        folder = _words(path.parent.name) if path.parent != src else ""
        text = template.replace("{name}", _words(path.stem)).replace("{folder}", folder)
        text = re.sub(r"\s+", " ", text).strip()
        if re.search(r"[A-Za-z]", text):
            return [Caption(text)]
    return []


# --------------------------------------------------------------------------------------------------------------
# skeleton -> 22 joints


def mapped_joints(bvh, bone_map) -> np.ndarray:
    """World positions (F, 22, 3) in file units and axes: mapped joints from the BVH, the rest filled in."""
    rot, pos = bvh.world_transforms()  # (F, J, 3, 3), (F, J, 3)
    out = np.full((bvh.num_frames, 22, 3), np.nan)
    for joint, bone in bone_map.joints.items():
        out[:, _J[joint]] = pos[:, bvh.index(bone)]
    for side in ("left", "right"):
        toe, ankle = _J[f"{side}_foot"], _J[f"{side}_ankle"]
        if np.isnan(out[0, toe, 0]):
            a = bvh.index(bone_map.joints[f"{side}_ankle"])
            tip = bvh.end_sites.get(a)
            if tip is None:
                children = [j for j, p in enumerate(bvh.parents) if p == a]
                if not children:
                    raise PrepareError(f"no toe joint or End Site below {bvh.names[a]}")
                out[:, toe] = pos[:, children[0]]
            else:
                out[:, toe] = out[:, ankle] + np.einsum("fab,b->fa", rot[:, a], tip)
    fill_missing_joints(out)
    return out


def fill_missing_joints(out: np.ndarray) -> None:
    """In place on (F, 22, 3) with NaN rows for unmapped joints: spine joints evenly between known ones, a neck
    between the shoulders, collars halfway from spine3 to the shoulders (the toes must be there already)."""
    _fill_spine(out)
    for side in ("left", "right"):
        collar, shoulder = _J[f"{side}_collar"], _J[f"{side}_shoulder"]
        if np.isnan(out[0, collar, 0]):
            out[:, collar] = 0.5 * (out[:, _J["spine3"]] + out[:, shoulder])


def _fill_spine(out: np.ndarray) -> None:
    """Missing spine joints between known ones, evenly; a missing neck between the shoulders."""
    if np.isnan(out[0, _J["neck"], 0]):
        out[:, _J["neck"]] = 0.5 * (out[:, _J["left_shoulder"]] + out[:, _J["right_shoulder"]])
    known = [k for k, name in enumerate(_SPINE) if not np.isnan(out[0, _J[name], 0])]
    for k, name in enumerate(_SPINE):
        if k in known:
            continue
        lo = max(i for i in known if i < k)
        hi = min(i for i in known if i > k)
        w = (k - lo) / (hi - lo)
        out[:, _J[name]] = (1 - w) * out[:, _J[_SPINE[lo]]] + w * out[:, _J[_SPINE[hi]]]


def detect_up(joints: np.ndarray) -> str:
    """'y' or 'z': the axis along which the head is farthest above the ankles on the first frame."""
    rise = joints[0, _J["head"]] - 0.5 * (joints[0, _J["left_ankle"]] + joints[0, _J["right_ankle"]])
    axis = int(np.argmax(np.abs(rise)))
    if axis == 0 or rise[axis] < 0:
        raise PrepareError("cannot tell the up axis: the head is not above the feet on the first frame "
                           "(pass --up y or --up z)")
    return "y" if axis == 1 else "z"


def to_y_up(joints: np.ndarray, up: str) -> np.ndarray:
    """Z-up (right-handed) -> Y-up by a rotation about X: (x, y, z) -> (x, z, -y)."""
    if up == "y":
        return joints
    return np.stack([joints[..., 0], joints[..., 2], -joints[..., 1]], axis=-1)


def leg_length(joints: np.ndarray) -> float:
    legs = [(_J[f"{s}_hip"], _J[f"{s}_knee"], _J[f"{s}_ankle"]) for s in ("left", "right")]
    return float(np.mean([np.linalg.norm(joints[:, k] - joints[:, h], axis=-1).mean()
                          + np.linalg.norm(joints[:, a] - joints[:, k], axis=-1).mean() for h, k, a in legs]))


def detect_units(joints: np.ndarray) -> tuple[str, float]:
    """The unit (name, metres per unit) that makes the legs most human (hip to ankle about 0.85 m); when no named
    unit comes within a factor 1.4 (CMU's ASF units are 1/0.45 inch), the scale that makes them exactly that."""
    leg = leg_length(joints)
    if not leg > 0:
        raise PrepareError("the legs have zero length")
    name = min(UNITS, key=lambda u: abs(np.log(leg * UNITS[u] / LEG_M)))
    if abs(np.log(leg * UNITS[name] / LEG_M)) <= np.log(1.4):
        return name, UNITS[name]
    scale = LEG_M / leg
    return f"{scale:.4g} m (from the leg length)", scale


def is_tpose(frame: np.ndarray) -> bool:
    """Both arms straight out sideways: wrists at shoulder height, far from the body (a Y-up frame (22, 3))."""
    leg = np.linalg.norm(frame[_J["left_hip"]] - frame[_J["left_knee"]]) + \
        np.linalg.norm(frame[_J["left_knee"]] - frame[_J["left_ankle"]])
    for side in ("left", "right"):
        shoulder, wrist = frame[_J[f"{side}_shoulder"]], frame[_J[f"{side}_wrist"]]
        arm = wrist - shoulder
        if abs(arm[1]) > 0.15 * leg or np.hypot(arm[0], arm[2]) < 0.5 * leg:
            return False
    return True


def leading_tpose_frames(joints: np.ndarray, max_frames: int) -> int:
    """How many first frames are a T-pose the take then leaves (a calibration frame, not motion)."""
    n = 0
    while n < min(max_frames, len(joints)) and is_tpose(joints[n]):
        n += 1
    return n if n < len(joints) and not all(is_tpose(f) for f in joints[n:n + 5]) else 0


def segments(frames: int, caption: Caption, fps: float, min_s: float, max_s: float) -> list[tuple[int, int]]:
    """The caption's span of a clip of ``frames`` cut into equal pieces of at most max_s (each at least min_s)."""
    start = int(round(caption.start_s * fps))
    end = frames if not caption.end_s else min(frames, int(round(caption.end_s * fps)))
    length = end - start
    if length < min_s * fps:
        return []
    pieces = int(np.ceil(length / (max_s * fps)))
    edges = np.linspace(start, end, pieces + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b - a >= min_s * fps]


# --------------------------------------------------------------------------------------------------------------
# one file


def clip_id(path: Path, src: Path) -> str:
    rel = path.relative_to(src).with_suffix("").as_posix()
    return re.sub(r"[^A-Za-z0-9_-]+", "_", rel.replace("/", "__"))


def skeleton_map(bvh, given=None):
    """The bone map for a parsed BVH: ``given`` (checked against its joints), else the detected one."""
    from mld_core.rig.bone_maps import detect_bone_map

    if given is not None:
        given.validate(bvh.names)
        return given
    detection = detect_bone_map(bvh.names, list(bvh.parents))
    if detection.missing:
        raise PrepareError(f"cannot map the skeleton: no {', '.join(detection.missing)} found "
                           "(save a bone map and pass --bone-map)")
    return detection.bone_map


def library_joints(bvh, bone_map, options: LibraryOptions) -> tuple[np.ndarray, dict]:
    """A parsed BVH as the 22 joints (T, 22, 3) in metres, Y up, at 20 fps without its leading T-pose frames, and
    what was found on the way (units, up axis, source frame rate, trimmed frames)."""
    joints = mapped_joints(bvh, bone_map)
    up = options.up or detect_up(joints)
    joints = to_y_up(joints, up)
    if options.units in UNITS:
        units, scale = options.units, UNITS[options.units]
    elif options.units:
        units, scale = f"{float(options.units):g} m", float(options.units)
    else:
        units, scale = detect_units(joints)
    joints = joints * scale
    fps = source_fps(bvh.frame_time)
    tpose = leading_tpose_frames(joints, int(fps))
    jumps = leading_jump_frames(joints[tpose:], fps)
    info = {"units": units, "up": up, "fps": round(fps, 3), "tpose_frames_trimmed": tpose,
            "leading_frames_trimmed": tpose + jumps}
    return resample_joints(joints[tpose + jumps:], fps, TARGET_FPS), info


def process_file(path: Path, src: Path, options: LibraryOptions, table: dict | None, root: Path,
                 bone_map=None) -> dict:
    """One BVH -> its segments' files under ``root``; returns a report entry (``error`` when skipped)."""
    from mld_core.motion import features as F

    entry = {"file": path.relative_to(src).as_posix()}
    try:
        texts = file_captions(path, src, table, options.caption_template)
        if not texts:
            raise PrepareError("no caption (none in --captions, no .txt beside it, no --caption-template)")
        bvh = read_bvh(path)
        bmap = skeleton_map(bvh, bone_map)
        joints, info = library_joints(bvh, bmap, options)
        entry.update(skeleton=bmap.source, root=bvh.names[0], **info,
                     seconds=round(len(joints) / TARGET_FPS, 2))
    except (BVHError, PrepareError, KeyError, ValueError, OSError) as exc:
        return {**entry, "error": str(exc).splitlines()[0] if str(exc) else type(exc).__name__}
    base = clip_id(path, src)
    by_span: dict[str, dict] = {}  # two captions of one span make one segment
    for c in texts:
        for a, b in segments(len(joints), c, TARGET_FPS, options.min_seconds, options.max_seconds):
            cid = f"{base}_{a:05d}_{b:05d}"
            by_span.setdefault(cid, {"id": cid, "start": a, "end": b, "captions": []})["captions"].append(c.text)
    entry["segments"] = list(by_span.values())
    if not entry["segments"]:
        return {**entry, "error": f"shorter than {options.min_seconds:g} s after trimming"}
    try:
        for seg in entry["segments"]:
            piece = joints[seg["start"]:seg["end"] + 1]
            why = implausible(piece, TARGET_FPS)
            if why:
                seg["error"] = why
                continue
            seg["frames"] = _write_clip(root, seg["id"], piece, [cap.caption_line(t) for t in seg["captions"]])
            if options.mirror:
                _write_clip(root, "M" + seg["id"], F.mirror_joints(piece),
                            [cap.caption_line(F.mirror_text(t)) for t in seg["captions"]])
    except ValueError as exc:
        return {**entry, "error": f"feature extraction failed: {exc}"}
    if all("error" in seg for seg in entry["segments"]):
        return {**entry, "error": f"implausible: {entry['segments'][0]['error']}"}
    return entry


# --------------------------------------------------------------------------------------------------------------
# the folder


def find_bvh(src: Path) -> list[Path]:
    return sorted(p for p in src.rglob("*") if p.suffix.lower() == ".bvh" and p.is_file())


def prepare_bvh(src, out, options: LibraryOptions | None = None) -> dict:
    """Build the HumanML3D-format folder ``out`` from the BVH files under ``src``; returns the summary."""

    options = options or LibraryOptions()
    src, out = Path(src).expanduser(), Path(out).expanduser().absolute()
    if not src.is_dir():
        raise PrepareError(f"{src} is not a folder")
    if options.up not in (None, "y", "z"):
        raise PrepareError("--up must be y or z")
    if not isinstance(options.licence, str) or not options.licence.strip():
        raise PrepareError("--licence: say the library's terms in words (e.g. \"Studio X, all rights reserved\")")
    if options.commercial is not None and not isinstance(options.commercial, bool):
        raise PrepareError("commercial must be true, false or unsaid (None)")
    if options.units is not None and options.units not in UNITS:
        try:
            if not 0 < float(options.units) < float("inf"):
                raise ValueError
        except ValueError:
            raise PrepareError(f"--units must be one of {', '.join(UNITS)} or metres per unit (> 0)") from None
    table = read_caption_table(options.captions) if options.captions else None
    bone_map = None
    if options.bone_map is not None:
        from mld_core.rig.bone_maps import BoneMap, BoneMapError

        try:
            bone_map = BoneMap.load(options.bone_map)
        except (OSError, ValueError, BoneMapError) as exc:
            raise PrepareError(f"cannot use --bone-map {options.bone_map}: "
                               f"{getattr(exc, 'strerror', None) or str(exc).splitlines()[0]}") from None
    files = find_bvh(src)
    if not files:
        raise PrepareError(f"no .bvh files under {src}")
    found = check_out(out)
    if out.resolve().is_relative_to(src.resolve()):
        raise PrepareError(f"--out {out} must not be inside {src}")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        for sub in ("new_joint_vecs", "new_joints", "texts"):
            (tmp / sub).mkdir()
        report = [process_file(p, src, options, table, tmp, bone_map) for p in files]
        ok = [r for r in report if "error" not in r]
        if not ok:
            raise PrepareError(f"no usable clips in {src}: e.g. {report[0]['file']}: {report[0]['error']}")
        folder_of = {r["file"]: Path(r["file"]).parent.as_posix() for r in ok}
        by_file = assign_splits({f: (folder, "") for f, folder in folder_of.items()})
        splits, content = {"train": [], "val": [], "test": []}, {}
        for r in ok:  # a file's segments (and mirrors) share its split and are labelled with its folder
            for s in _written(r):
                ids = [s["id"]] + (["M" + s["id"]] if options.mirror else [])
                splits[by_file[r["file"]]] += ids
                content.update(dict.fromkeys(ids, folder_of[r["file"]]))
        all_ids = write_splits(tmp, splits)
        actions = {"classes": sorted(set(content.values())), "clips": content, "styles": {i: "" for i in all_ids}}
        (tmp / "actions.json").write_text(json.dumps(actions, indent=1) + "\n", encoding="utf-8")
        segs = [s for r in ok for s in _written(r)]
        frames = int(sum(s["frames"] for s in segs)) * (2 if options.mirror else 1)
        skipped = {r["file"]: r["error"] for r in report if "error" in r}
        summary = {"written_by": "mld_core data prepare", "dataset": "bvh", "format_version": FORMAT_VERSION,
                   "fps": TARGET_FPS, "files": len(files), "mapped": len(ok), "clips": len(segs),
                   "mirrored": len(segs) if options.mirror else 0, "frames": frames,
                   "splits": {k: len(v) for k, v in splits.items()}, "classes": actions["classes"],
                   "skipped": skipped,
                   "rejected_segments": {s["id"]: s["error"] for r in ok for s in r["segments"] if "error" in s},
                   "leading_frames_trimmed": {r["file"]: r.get("leading_frames_trimmed", 0) for r in report
                                              if r.get("leading_frames_trimmed")}}
        (tmp / REPORT).write_text(json.dumps({"summary": summary, "files": report}, indent=1) + "\n",
                                  encoding="utf-8")
        (tmp / "README.md").write_text(_readme(src, summary), encoding="utf-8")
        terms.write(tmp, [{"name": f"BVH folder {Path(src).name}", "licence": options.licence,
                           "commercial": options.commercial}])
        (tmp / MANIFEST).write_text(json.dumps({**summary, "files": written_files(tmp) + [MANIFEST]}, indent=1) +
                                    "\n", encoding="utf-8")
        swap_into_place(tmp, out, found)
        for file, why in sorted(skipped.items()):
            print(f"warning: skipped {file}: {why}", file=sys.stderr)
        return {**summary, "out": str(out)}
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _written(entry: dict) -> list[dict]:
    """A file's segments that were written (not rejected as implausible)."""
    return [s for s in entry["segments"] if "error" not in s]


def _readme(src: Path, s: dict) -> str:
    return f"""# A BVH library in HumanML3D format

Written by `python -m mld_core data prepare bvh` (format version {FORMAT_VERSION}) from `{src}`.

- {s['mapped']} of {s['files']} BVH files mapped onto the 22 joints; {len(s['skipped'])} skipped (reasons in
  `{REPORT}`, with each file's skeleton, units, up axis, frame rate and trimmed T-pose frames).
- {s['clips']} segments of at most {MAX_SECONDS} s + {s['mirrored']} mirrored copies (`M` + id), {s['frames']} frames
  at {TARGET_FPS} fps. Splits by file (a file's segments stay together): train {s['splits']['train']},
  val {s['splits']['val']}, test {s['splits']['test']}.
- `actions.json` labels each segment with its file's folder.
- The motion keeps the licence of its source files.
"""
