"""``python -m mld_core data merge A B ... --out C``: several HumanML3D-format folders as one (numpy only).

Every folder is checked before anything is written: its split files (UTF-8, plain ids, none listed twice, a train
split that names a clip), every clip's features (a readable (frames, 263) array of finite numbers), joints and
captions (UTF-8) and its ``actions.json``. Each clip keeps its split and its id; an id that two folders share gets
its folder's name as a prefix in both (the shortest tail of the folders' paths that tells them apart: ``x_data``
and ``y_data`` for ``x/data`` and ``y/data``), so nothing is overwritten, and ids that would still meet are refused.
Mean/Std are recomputed over the merged train split (HumanML3D's per-group std); ``provenance.json`` says where
every clip came from; ``actions.json`` is merged when the folders have one. The folder is built beside ``--out``
under a temporary name and renamed at the end only if ``--out`` is still new or empty: a failure leaves nothing, and
of two runs writing the same ``--out`` one wins and the other is refused.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..fileio import build_new_folder
from ..inputs import InputError, check_output_folder, read_utf8
from ..motion import features as F
from ..motion.skeleton import FEATURE_DIM
from . import terms

SPLITS = ("train", "val", "test")
MANIFEST = ".mld_merge.json"


@dataclass(eq=False)
class Source:
    """One folder to merge: its clip ids per split, its clip labels (actions.json) and the prefix its clashing ids
    get."""

    path: Path
    ids: dict[str, list[str]]
    actions: dict[str, str] | None = None
    prefix: str = ""
    train: list = field(default_factory=list)  # the train clips' features, read when checked


# -- reading and checking the folders -------------------------------------------------------------------------------
def check_sources(sources: list[Path]) -> None:
    if len(sources) < 2:
        raise InputError("data merge needs at least two folders")
    if len({s.resolve() for s in sources}) != len(sources):
        raise InputError("data merge got the same folder twice")
    for s in sources:
        missing = [n for n in ("new_joint_vecs", "texts", "train.txt") if not (s / n).exists()]
        if missing:
            raise InputError(f"{s} is not a HumanML3D-format folder (missing {', '.join(missing)})")


def _text(path: Path) -> str:
    """A UTF-8 text file's contents; InputError naming the file (and the line) otherwise."""
    return read_utf8(path, str(path))


def _split_ids(folder: Path, split: str, seen: dict[str, str]) -> list[str]:
    """The ids ``{split}.txt`` lists (none when it is absent); each a plain file name, listed once in the folder."""
    path = folder / f"{split}.txt"
    if not path.exists():
        return []
    ids = []
    for number, line in enumerate(_text(path).splitlines(), start=1):
        cid = line.strip()
        if not cid:
            continue
        if cid in (".", "..") or any(c in cid for c in "/\\\0"):
            raise InputError(f"{path}, line {number}: {cid!r} is not a clip id (the name of a new_joint_vecs file "
                             "without .npy)")
        if cid in seen:
            raise InputError(f"{path}, line {number}: clip {cid} is listed twice (also in {seen[cid]}.txt); list "
                             "each clip once")
        seen[cid] = split
        ids.append(cid)
    return ids


def _actions(folder: Path) -> dict[str, str] | None:
    """``actions.json``'s clip labels (None when the folder has none)."""
    path = folder / "actions.json"
    if not path.exists():
        return None
    try:
        data = json.loads(_text(path))
    except (ValueError, RecursionError) as exc:
        raise InputError(f"{path} is not valid JSON: {str(exc).splitlines()[0][:120]}") from None
    clips = data.get("clips", {}) if isinstance(data, dict) else None
    if not isinstance(clips, dict) or not all(isinstance(v, str) for v in clips.values()):
        raise InputError(f'{path}: expected {{"classes": [...], "clips": {{"<clip id>": "<label>", ...}}}}')
    return clips


def read_source(folder: Path) -> Source:
    """A folder's split files and actions.json, checked (the clips themselves: :func:`check_clips`)."""
    seen: dict[str, str] = {}
    ids = {split: _split_ids(folder, split, seen) for split in SPLITS}
    if not ids["train"]:
        raise InputError(f"{folder / 'train.txt'} names no clip: a folder to merge needs a train split")
    return Source(folder, ids, _actions(folder))


def _array(path: Path, what: str, mmap: bool = False) -> np.ndarray:
    try:
        array = np.load(path, allow_pickle=False, mmap_mode="r" if mmap else None)
    except (OSError, ValueError, EOFError):
        raise InputError(f"{path} is not a readable numpy array file; {what}") from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "fiu":
        raise InputError(f"{path} is not an array of numbers; {what}")
    return array


def _features(source: Source, split: str, cid: str) -> np.ndarray:
    """A clip's features, checked: a readable (frames, 263) array of finite numbers."""
    folder = source.path
    path = folder / "new_joint_vecs" / f"{cid}.npy"
    if not path.is_file():
        raise InputError(f"{folder}: {split}.txt names {cid}, which has no new_joint_vecs/{cid}.npy")
    fix = f"prepare {folder} again or drop {cid} from {split}.txt"
    feats = _array(path, fix)
    if feats.ndim != 2 or len(feats) < 1:
        raise InputError(f"{path} has shape {feats.shape}, not (frames, {FEATURE_DIM}); {fix}")
    if feats.shape[1] != FEATURE_DIM:
        raise InputError(f"{path} has {feats.shape[1]} features per frame, not HumanML3D's {FEATURE_DIM}: every "
                         "folder to merge must hold the same features")
    if not np.isfinite(feats).all():
        raise InputError(f"{path} holds NaN or infinite values; {fix}")
    return feats


def check_clips(source: Source) -> None:
    """Every clip of ``source``: features (:func:`_features`), joints readable, captions UTF-8; keeps the train
    clips' features for the statistics."""
    source.train = []
    for split, ids in source.ids.items():
        for cid in ids:
            feats = _features(source, split, cid)
            if split == "train":
                source.train.append(feats)
            joints = source.path / "new_joints" / f"{cid}.npy"
            if joints.is_file():
                _array(joints, f"prepare {source.path} again or remove it", mmap=True)
            text = source.path / "texts" / f"{cid}.txt"
            if text.is_file():
                _text(text)


# -- ids ---------------------------------------------------------------------------------------------------------
def prefixes(paths: list[Path]) -> list[str]:
    """Per folder, the shortest tail of its path (parts joined by ``_``) that no other folder's tail of the same
    length equals: its name, unless two folders share that."""
    parts = [p.resolve().parts[1:] or (p.resolve().anchor,) for p in paths]
    out = []
    for i, mine in enumerate(parts):
        for k in range(1, len(mine) + 1):
            name = "_".join(mine[-k:])
            if all("_".join(other[-k:]) != name for j, other in enumerate(parts) if j != i):
                break
        out.append(name)
    return out


def merged_ids(sources: list[Source]) -> list[tuple[Source, str, str, str]]:
    """(source, split, original id, merged id) for every clip: an id that two folders share gets each folder's
    prefix; refused where two clips would still get one id."""
    holders: dict[str, list[Source]] = {}
    for s in sources:
        for ids in s.ids.values():
            for cid in ids:
                holders.setdefault(cid, []).append(s)
    clashing = [s for s in sources if any(len(holders[c]) > 1 for ids in s.ids.values() for c in ids)]
    names = [s.prefix for s in clashing]
    for s in clashing:
        if names.count(s.prefix) > 1:
            other = next(o for o in clashing if o is not s and o.prefix == s.prefix)
            raise InputError(f"{s.path} and {other.path} share clip ids and would both prefix them with "
                             f"'{s.prefix}_'; rename one folder - nothing was written")
    rows = [(s, split, cid, f"{s.prefix}_{cid}" if len(holders[cid]) > 1 else cid)
            for s in sources for split in SPLITS for cid in s.ids[split]]
    first: dict[str, tuple[Source, str]] = {}
    for s, _, cid, new in rows:
        if new in first:
            o, ocid = first[new]
            raise InputError(f"the merged id {new} would name two clips ({o.path}: {ocid}, {s.path}: {cid}); rename "
                             "a folder or a clip - nothing was written")
        first[new] = (s, cid)
    return rows


# -- the merge -----------------------------------------------------------------------------------------------------
def merge(sources, out) -> dict:
    """Write the merged folder ``out``; returns a summary (clips per split, per source)."""
    paths = [Path(s).expanduser() for s in sources]
    out = Path(out).expanduser().absolute()
    check_sources(paths)
    check_output_folder(out, "--out", staged_beside=True)
    if out.exists() and any(out.iterdir()):
        raise InputError(f"--out {out} is not empty; choose a new or empty folder - nothing was changed")
    folders = [read_source(p) for p in paths]
    for folder, prefix in zip(folders, prefixes(paths)):
        folder.prefix = prefix
    rows = merged_ids(folders)
    for folder in folders:
        check_clips(folder)
    mean, std = F.mean_std([f for folder in folders for f in folder.train])
    for folder in folders:
        folder.train = []
    build_new_folder(out, lambda tmp: _write(tmp, rows, folders, mean, std))
    return {"out": str(out), "splits": {sp: sum(1 for r in rows if r[1] == sp) for sp in SPLITS},
            "sources": {str(s.path): sum(1 for r in rows if r[0] is s) for s in folders}}


def _write(tmp: Path, rows, folders: list[Source], mean, std) -> None:
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (tmp / sub).mkdir()
    for source, _, cid, new in rows:
        for sub, ext in (("new_joint_vecs", "npy"), ("new_joints", "npy"), ("texts", "txt")):
            src = source.path / sub / f"{cid}.{ext}"
            if src.is_file():
                shutil.copyfile(src, tmp / sub / f"{new}.{ext}")
    for split in SPLITS:
        (tmp / f"{split}.txt").write_text("".join(f"{r[3]}\n" for r in rows if r[1] == split), encoding="utf-8")
    (tmp / "all.txt").write_text("".join(f"{r[3]}\n" for r in rows), encoding="utf-8")
    np.save(tmp / "Mean.npy", mean)
    np.save(tmp / "Std.npy", std)
    provenance = {r[3]: {"source": str(r[0].path), "id": r[2], "split": r[1]} for r in rows}
    (tmp / "provenance.json").write_text(json.dumps(provenance, indent=1) + "\n", encoding="utf-8")
    actions = _merged_actions(rows, folders)
    if actions is not None:
        (tmp / "actions.json").write_text(json.dumps(actions, indent=1) + "\n", encoding="utf-8")
    (tmp / MANIFEST).write_text(json.dumps({"written_by": "mld_core data merge",
                                            "sources": [str(s.path) for s in folders]}, indent=1) + "\n",
                                encoding="utf-8")
    terms.write(tmp, terms.union(*(terms.of_folder(folder.path) for folder in folders)))
    licences = _licences(folders)
    if licences:
        (tmp / "LICENSE").write_text(licences, encoding="utf-8")
    (tmp / "README.md").write_text(_readme(tmp, folders, bool(licences)), encoding="utf-8")


def _licences(folders: list[Source]) -> str:
    """The sources' LICENSE files, one after the other under their folder's name ("" when none has one)."""
    parts = []
    for folder in folders:
        path = folder.path / "LICENSE"
        if path.is_file():
            text = path.read_text(encoding="utf-8", errors="replace").strip()
            parts.append(f"## {folder.prefix or folder.path.name}\n\n{text}\n")
    return ("# Licences of the merged folders\n\n" + "\n".join(parts)) if parts else ""


def _readme(tmp: Path, folders: list[Source], licences: bool) -> str:
    from .summary import folder_summary, summary_table

    names = ", ".join(f"`{f.path.name}`" for f in folders)
    return (f"# A merged HumanML3D-format folder\n\nWritten by `python -m mld_core data merge` from {names}: splits "
            f"kept, Mean/Std over the merged train split, each clip's source in `provenance.json`."
            + (" Each source's licence in `LICENSE`." if licences else "")
            + "\n\nHours (mirrored copies included) per source and split, and per checked verb (the captions that ask "
            "for it):\n\n" + summary_table(folder_summary(tmp)))


def _merged_actions(rows, folders: list[Source]) -> dict | None:
    """The folders' actions.json merged (clip labels under their merged ids), or None when none has one."""
    if all(s.actions is None for s in folders):
        return None
    clips = {new: s.actions[cid] for s, _, cid, new in rows if s.actions is not None and cid in s.actions}
    return {"classes": sorted(set(clips.values())), "clips": clips}
