"""``data prepare cmu-joints``: the CMU motion capture database as joint positions -> a HumanML3D-format folder.

The source (``cmu-mocap-joints.tar.xz`` or its extracted folder) holds ``joints/SS_TT.npy`` (frames, 20, 3) in CMU
length units at 12 fps (6 fps for 60 Hz captures) and ``labels.tsv`` (CMU's one-line description, Action2Motion's
class and KIT Motion-Language sentences per trial). Per trial: the 20 joints onto the 22 (spine1/spine2 between the
pelvis and the upper spine, collars halfway to the shoulders, as ``data prepare bvh`` fills them), units to metres,
leading frames that jump impossibly dropped, resampled to 20 fps by linear interpolation (no overshoot), cut into
windows of at most 9.8 s whose captions are true of them (``mld_core.data.cmu_captions``), each window checked for
plausibility (``mld_core.data.take_checks``) and mirrored. Calibration, range-of-motion and T-pose trials,
two-subject trials whose description does not say what this subject does, and the second copy of a capture the
database holds twice (under two subjects) are listed with their reason in ``prepare_report.json``; uncaptioned
windows are written and listed in ``uncaptioned.txt`` (they train the VAE, not the denoiser). Splits are by subject:
the test split holds subjects no other split has. ``--captions cmu`` leaves the KIT sentences out.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import re
import shutil
import sys
import tarfile
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mld_core.data import captions as cap
from mld_core.data import terms
from mld_core.data import cmu_captions as cc
from mld_core.data.bandai import (FORMAT_VERSION, MANIFEST, TARGET_FPS, PrepareError, _hash, _write_clip,
                                  check_out, iter_tar, resample_joints, swap_into_place, write_splits, written_files)
from mld_core.data.bvh_library import fill_missing_joints
from mld_core.data.take_checks import implausible, leading_jump_frames
from mld_core.motion.skeleton import JOINT_NAMES

REPORT = "prepare_report.json"
UNCAPTIONED = "uncaptioned.txt"
CMU_UNIT_M = 0.0564  # CMU length units -> metres (the walk 02_01 travels 3.3 m in 2.9 s)
DEFAULT_FPS = 12.0  # trials whose rate is not given: their lengths match 12 fps
MAX_SECONDS = 9.8
MIN_SECONDS = 2.0
LABEL_COLUMNS = ("trial", "frames", "src_fps", "a2p_fps", "cmu_description", "a2p_class", "kitml_captions")
_TRIAL = re.compile(r"^(\d+)_(\d+)$")

# CMU's 20 joints (0 pelvis, 1 upper spine, 2 neck, 3 head, 4-7 left shoulder/elbow/wrist/hand, 8-11 right arm,
# 12-15 left hip/knee/ankle/toe, 16-19 right leg) -> the SMPL-22 joints they are; the rest are filled in.
CMU_TO_SMPL = {
    "pelvis": 0, "spine3": 1, "neck": 2, "head": 3,
    "left_shoulder": 4, "left_elbow": 5, "left_wrist": 6,
    "right_shoulder": 8, "right_elbow": 9, "right_wrist": 10,
    "left_hip": 12, "left_knee": 13, "left_ankle": 14, "left_foot": 15,
    "right_hip": 16, "right_knee": 17, "right_ankle": 18, "right_foot": 19,
}
# Subjects in the test and validation splits: every 10th subject by a fixed hash order (about 10% each).
TEST_EVERY, VAL_OFFSET = 10, 5


@dataclass
class Trial:
    trial: str  # "SS_TT"
    fps: float
    description: str = ""
    a2p_class: str = ""
    kit: list[str] = field(default_factory=list)

    @property
    def subject(self) -> str:
        return self.trial.split("_")[0]


# --------------------------------------------------------------------------------------------------------------
# the source


def read_labels(text: str, where: str = "labels.tsv") -> dict[str, Trial]:
    """``labels.tsv`` -> trial id -> Trial. A header without the expected columns is refused in one line."""
    rows = list(csv.reader(io.StringIO(text), dialect="excel-tab"))
    if not rows or [c.strip() for c in rows[0]][: len(LABEL_COLUMNS)] != list(LABEL_COLUMNS):
        got = ", ".join(rows[0][:8]) if rows else "nothing"
        raise PrepareError(f"{where}: expected the columns {', '.join(LABEL_COLUMNS)}; found {got}")
    trials = {}
    for n, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        if len(row) < len(LABEL_COLUMNS) or not _TRIAL.match(row[0].strip()):
            raise PrepareError(f"{where}, line {n}: expected {len(LABEL_COLUMNS)} tab-separated fields starting "
                               f"with a trial id such as 02_01")
        rate = row[3].strip()
        try:
            fps = float(rate) if rate else DEFAULT_FPS
        except ValueError:
            raise PrepareError(f"{where}, line {n}: a2p_fps {rate!r} is not a number") from None
        if not 1 <= fps <= 240:
            raise PrepareError(f"{where}, line {n}: a2p_fps {rate!r} is not a frame rate")
        kit = [s.strip() for s in row[6].split(" | ") if s.strip()]
        trials[row[0].strip()] = Trial(row[0].strip(), fps, row[4].strip(), row[5].strip(), kit)
    if not trials:
        raise PrepareError(f"{where} lists no trials")
    return trials


def _archive_members(src: Path) -> tuple[str, dict[str, bytes]]:
    """(labels text, trial id -> .npy bytes) read from the .tar(.xz) archive in one pass."""
    labels, arrays = None, {}
    for name, data in iter_tar(src, lambda n: n.endswith("/labels.tsv") or n == "labels.tsv"
                               or (n.endswith(".npy") and "/joints/" in f"/{n}")):
        if name.endswith(".npy"):
            arrays[name.rsplit("/", 1)[-1][:-4]] = data
        else:
            try:
                labels = data.decode("utf-8")
            except UnicodeDecodeError as exc:
                raise PrepareError(f"{src}: labels.tsv is not UTF-8 text ({exc.reason})") from None
    if labels is None:
        raise PrepareError(f"{src} holds no labels.tsv (expected the CMU joints archive)")
    return labels, arrays


def read_source(src: Path) -> tuple[dict[str, Trial], dict[str, object]]:
    """(trials, trial id -> a path or the bytes of its .npy) from the archive or its extracted folder."""
    if not src.exists():
        raise PrepareError(f"SRC {src} does not exist (expected cmu-mocap-joints.tar.xz or its extracted folder)")
    if src.is_dir():
        found = sorted(src.rglob("labels.tsv"))
        if not found:
            raise PrepareError(f"SRC folder {src} holds no labels.tsv (expected the extracted CMU joints archive)")
        root = found[0].parent
        try:
            labels = (root / "labels.tsv").read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise PrepareError(f"cannot read {root / 'labels.tsv'}: {exc}") from None
        arrays = {p.stem: p for p in sorted((root / "joints").glob("*.npy"))}
        where = str(root / "labels.tsv")
    else:
        if not tarfile.is_tarfile(src):
            raise PrepareError(f"SRC {src} is neither a folder nor a readable tar archive (.tar.xz)")
        labels, arrays = _archive_members(src)
        where = f"{src}: labels.tsv"
    return read_labels(labels, where), arrays


def deduplicate(trials: dict[str, Trial], arrays: dict[str, object]) -> dict[str, str]:
    """The CMU database holds some captures twice under two subjects (subject 121's trials are subject 90's, 122's
    are 83's, ...). Keep one trial per identical capture (the lowest subject and trial number), give it the others'
    labels where its own are missing or cryptic, drop the others from ``trials``; returns dropped -> kept."""
    groups: dict[str, list[str]] = {}
    for name in sorted(arrays, key=_trial_order):
        if name in trials:
            data = arrays[name]
            digest = hashlib.sha1(data.read_bytes() if isinstance(data, Path) else data).hexdigest()
            groups.setdefault(digest, []).append(name)
    dropped = {}
    for names in groups.values():
        keep = trials[names[0]]
        for other in names[1:]:
            twin = trials.pop(other)
            if not cc.trial_plan(keep.description).sentences and cc.trial_plan(twin.description).sentences:
                keep.description = twin.description
            keep.kit = list(dict.fromkeys(keep.kit + twin.kit))
            keep.a2p_class = keep.a2p_class or twin.a2p_class
            dropped[other] = keep.trial
    return dropped


def load_trial_array(data) -> np.ndarray:
    """One trial's (frames, 20, 3) positions from a path or .npy bytes; ValueError with the reason otherwise."""
    try:
        raw = np.load(data if isinstance(data, Path) else io.BytesIO(data), allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"not a readable .npy file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})")
    if raw.ndim != 3 or raw.shape[1:] != (20, 3):
        raise ValueError(f"positions of shape {raw.shape}, expected (frames, 20, 3)")
    if not np.issubdtype(raw.dtype, np.number):
        raise ValueError(f"positions of type {raw.dtype}, expected numbers")
    raw = raw.astype(np.float64)
    if not np.isfinite(raw).all():
        raise ValueError("NaN or infinite positions")
    return raw


# --------------------------------------------------------------------------------------------------------------
# one trial


def to_smpl22(raw: np.ndarray) -> np.ndarray:
    """CMU's 20 joints (F, 20, 3) in CMU units -> the 22 SMPL-order joints (F, 22, 3) in metres."""
    out = np.full((len(raw), len(JOINT_NAMES), 3), np.nan)
    for name, k in CMU_TO_SMPL.items():
        out[:, JOINT_NAMES.index(name)] = raw[:, k]
    fill_missing_joints(out)
    return out * CMU_UNIT_M


def trial_joints(raw: np.ndarray, fps: float) -> tuple[np.ndarray, int]:
    """A trial's joints at 20 fps (T, 22, 3) in metres, without its leading impossible frames, and how many source
    frames were dropped."""
    joints = to_smpl22(raw)
    trimmed = leading_jump_frames(joints, fps)
    return resample_joints(joints[trimmed:], fps, TARGET_FPS), trimmed


def windows(frames: int, fps: float = TARGET_FPS, max_s: float = MAX_SECONDS,
            min_s: float = MIN_SECONDS) -> list[tuple[int, int]]:
    """A take of ``frames`` cut into equal windows of at most max_s (each at least min_s), [start, end) frames."""
    if frames < min_s * fps:
        return []
    pieces = int(np.ceil(frames / (max_s * fps)))
    edges = np.linspace(0, frames, pieces + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b - a >= min_s * fps]


def prepare_trial(trial: Trial, data, root: Path, mirror: bool = True, kit: bool = True) -> dict:
    """One trial -> its windows' files under ``root``; returns its report entry (``error`` when skipped).
    ``kit`` False: the trial's KIT sentences are left out, its captions come from CMU's description only."""
    entry = {"trial": trial.trial, "fps": trial.fps, "description": trial.description}
    plan = cc.trial_plan(trial.description, trial.kit if kit else [])
    if plan.skip:
        return {**entry, "error": plan.skip}
    try:
        raw = load_trial_array(data)
        joints, trimmed = trial_joints(raw, trial.fps)
    except ValueError as exc:
        return {**entry, "error": str(exc)}
    entry.update(leading_frames_trimmed=trimmed, seconds=round(len(joints) / TARGET_FPS, 2), windows=[])
    spans = windows(len(joints))
    if not spans:
        return {**entry, "error": f"shorter than {MIN_SECONDS:g} s"}
    for a, b in spans:
        piece = joints[a:b]
        wid = f"{trial.trial}_{a:05d}_{b:05d}"
        why = implausible(piece, TARGET_FPS)
        if why:
            entry["windows"].append({"id": wid, "error": why})
            continue
        texts = cc.window_captions(plan, piece, whole=len(spans) == 1)
        win = {"id": wid, "start": a, "end": b, "captions": texts}
        try:
            win["frames"] = _write_clip(root, wid, piece, [cap.caption_line(t) for t in texts])
            if mirror:
                _write_clip(root, "M" + wid, _mirror(piece), [cap.caption_line(_mirror_text(t)) for t in texts])
        except ValueError as exc:
            win = {"id": wid, "error": f"feature extraction failed: {exc}"}
        entry["windows"].append(win)
    if not any("error" not in w for w in entry["windows"]):
        entry["error"] = "no plausible window: " + entry["windows"][0]["error"]
    return entry


def _mirror(joints: np.ndarray) -> np.ndarray:
    from mld_core.motion.features import mirror_joints

    return mirror_joints(joints)


def _mirror_text(text: str) -> str:
    from mld_core.motion.features import mirror_text

    return mirror_text(text)


def whole_trial_windows(data: Path) -> list[str]:
    """Ids (and their mirrors) of a prepared folder's windows whose captions were written from the whole trial, not
    found by the detectors in a long trial that lists several actions: the windows to calibrate and score on."""
    report = json.loads((Path(data) / REPORT).read_text(encoding="utf-8"))
    ids = []
    for trial in report["trials"]:
        if len(trial.get("windows", [])) > 1 and cc.trial_plan(trial.get("description", ""), []).several_actions:
            continue
        for w in trial.get("windows", []):
            if "error" not in w and w["captions"]:
                ids += [w["id"], "M" + w["id"]]
    return [i for i in ids if (Path(data) / "new_joints" / f"{i}.npy").is_file()]


# --------------------------------------------------------------------------------------------------------------
# splits


def subject_splits(subjects) -> dict[str, str]:
    """subject -> "train" / "val" / "test": subjects ordered by a fixed hash; every TEST_EVERY-th is test, the one
    VAL_OFFSET after it val. Depends only on the subject ids."""
    order = sorted(set(subjects), key=lambda s: (_hash(f"cmu-subject-{s}"), s))
    out = {}
    for k, s in enumerate(order):
        out[s] = "test" if k % TEST_EVERY == 0 else "val" if k % TEST_EVERY == VAL_OFFSET else "train"
    return out


# --------------------------------------------------------------------------------------------------------------
# the folder


CAPTION_SOURCES = {"all": "CMU's descriptions and KIT Motion-Language sentences",
                   "cmu": "CMU's descriptions only"}


def prepare_cmu_joints(src, out, *, mirror: bool = True, limit: int | None = None, progress: bool = True,
                       captions: str = "all") -> dict:
    """Build the HumanML3D-format folder ``out`` from the CMU joints source ``src``; returns the summary.
    ``captions`` "cmu" leaves out the KIT sentences (a folder for weights whose use CMU's terms alone govern)."""
    if captions not in CAPTION_SOURCES:
        raise PrepareError(f"captions must be one of {', '.join(CAPTION_SOURCES)}, not {captions!r}")
    from tqdm import tqdm

    from mld_core.data.verbs import verbs_in

    src, out = Path(src).expanduser(), Path(out).expanduser().absolute()
    found = check_out(out)
    trials, arrays = read_source(src)
    if src.is_dir() and out.resolve().is_relative_to(src.resolve()):
        raise PrepareError(f"--out {out} must not be inside SRC {src}")
    duplicates = deduplicate(trials, arrays)
    names = sorted(trials, key=_trial_order)[:limit]
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        for sub in ("new_joint_vecs", "new_joints", "texts"):
            (tmp / sub).mkdir()
        report = []
        for name in tqdm(names, unit="trial", desc="cmu", disable=not progress, dynamic_ncols=True):
            if name not in arrays:
                report.append({"trial": name, "error": "no joints/<trial>.npy in the source"})
                continue
            report.append(prepare_trial(trials[name], arrays.pop(name), tmp, mirror, kit=captions == "all"))
        report += [{"trial": d, "error": f"the same capture as {k} (kept under {k})"}
                   for d, k in sorted(duplicates.items()) if limit is None]
        ok = [r for r in report if "error" not in r]
        if not ok:
            raise PrepareError(f"no usable trials in {src}: e.g. {report[0]['trial']}: {report[0]['error']}")
        split_of = subject_splits(trials[r["trial"]].subject for r in ok)
        splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
        labels, uncaptioned = {}, []
        for r in ok:
            for w in r["windows"]:
                if "error" in w:
                    continue
                ids = [w["id"]] + (["M" + w["id"]] if mirror else [])
                splits[split_of[trials[r["trial"]].subject]] += ids
                verbs = verbs_in(" ".join(w["captions"]))
                for cid in ids:
                    labels[cid] = verbs[0] if verbs else ("other" if w["captions"] else "uncaptioned")
                if not w["captions"]:
                    uncaptioned += ids
        all_ids = write_splits(tmp, splits)
        (tmp / UNCAPTIONED).write_text("".join(f"{i}\n" for i in sorted(uncaptioned)), encoding="utf-8")
        actions = {"classes": sorted(set(labels.values())), "clips": labels,
                   "styles": {i: "" for i in all_ids}}
        (tmp / "actions.json").write_text(json.dumps(actions, indent=1) + "\n", encoding="utf-8")
        summary = {**_summary(report, splits, uncaptioned, mirror, len(report)), "captions": captions}
        (tmp / REPORT).write_text(json.dumps({"summary": summary, "trials": report}, indent=1) + "\n",
                                  encoding="utf-8")
        (tmp / "README.md").write_text(_readme(summary), encoding="utf-8")
        (tmp / "LICENSE").write_text(license_text(captions), encoding="utf-8")
        terms.write(tmp, [terms.CMU, terms.KIT] if captions == "all" else [terms.CMU])
        (tmp / MANIFEST).write_text(json.dumps({**summary, "files": written_files(tmp) + [MANIFEST]}, indent=1)
                                    + "\n", encoding="utf-8")
        swap_into_place(tmp, out, found)
        for r in report:
            if "error" in r:
                print(f"warning: skipped {r['trial']}: {r['error']}", file=sys.stderr)
        return {**summary, "out": str(out)}
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _trial_order(name: str) -> tuple[int, int]:
    subject, take = name.split("_")
    return int(subject), int(take)


def _summary(report: list[dict], splits: dict, uncaptioned: list[str], mirror: bool, trials: int) -> dict:
    wins = [w for r in report if "error" not in r for w in r["windows"] if "error" not in w]
    factor = 2 if mirror else 1
    frames = int(sum(w["frames"] for w in wins)) * factor
    return {"written_by": "mld_core data prepare", "dataset": "cmu-joints", "format_version": FORMAT_VERSION,
            "fps": TARGET_FPS, "trials": trials, "prepared": sum(1 for r in report if "error" not in r),
            "windows": len(wins), "mirrored": len(wins) if mirror else 0, "frames": frames,
            "hours": round(frames / TARGET_FPS / 3600, 3), "uncaptioned": len(uncaptioned),
            "rejected_windows": sum(1 for r in report for w in r.get("windows", []) if "error" in w),
            "leading_frames_trimmed": int(sum(r.get("leading_frames_trimmed", 0) for r in report)),
            "splits": {k: len(v) for k, v in splits.items()},
            "skipped": {r["trial"]: r["error"] for r in report if "error" in r}}


_LICENSE_MOTION = """The motion in this folder comes from the CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu).

CMU's terms: "This data is free for use in research projects. You may include this data in commercially-sold
products, but you may not resell this data directly, even in converted form."
Acknowledgement: "The data used in this project was obtained from mocap.cs.cmu.edu. The database was created with
funding from NSF EIA-0196217."
"""

_LICENSE_KIT = """
Captions that are KIT Motion-Language sentences come from: Plappert, Mandery and Asfour, "The KIT Motion-Language
Dataset", Big Data 4(4), 2016 (an open research dataset whose licence is not stated). The other captions are written
from CMU's own trial descriptions by `python -m mld_core data prepare cmu-joints`.
"""

_LICENSE_CMU_ONLY = """
Every caption is written from CMU's own trial descriptions by `python -m mld_core data prepare cmu-joints --captions
cmu`; no KIT Motion-Language sentences are used.
"""


def license_text(captions: str = "all") -> str:
    """The folder's LICENSE: CMU's terms and acknowledgement, and where its captions come from."""
    return _LICENSE_MOTION + (_LICENSE_KIT if captions == "all" else _LICENSE_CMU_ONLY)


def _readme(s: dict) -> str:
    kit_citation = "; the KIT Motion-Language citation" if s["captions"] == "all" else ""
    return f"""# The CMU motion capture database in HumanML3D format

Written by `python -m mld_core data prepare cmu-joints --captions {s['captions']}` (format version {FORMAT_VERSION}).

- {s['prepared']} of {s['trials']} trials prepared; {len(s['skipped'])} skipped (each with its reason in `{REPORT}`).
- {s['windows']} windows of at most {MAX_SECONDS} s + {s['mirrored']} mirrored copies (`M` + id), {s['frames']} frames
  ({s['hours']} h) at {TARGET_FPS} fps; {s['rejected_windows']} windows failed the plausibility check and were not
  written; {s['leading_frames_trimmed']} leading source frames trimmed in all.
- Captions: {CAPTION_SOURCES[s['captions']]}.
- {s['uncaptioned']} windows (mirrors included) have no caption (`{UNCAPTIONED}`): they train the VAE only.
- Splits by subject: train {s['splits']['train']}, val {s['splits']['val']}, test {s['splits']['test']}.
- `actions.json` labels each window with the first checked verb its captions ask for (`other`, `uncaptioned`).
- Licences: see `LICENSE` (CMU's terms and acknowledgement{kit_citation}).
"""
