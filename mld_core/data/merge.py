"""``python -m mld_core data merge A B ... --out C``: several HumanML3D-format folders as one (numpy only).

Each clip keeps its split; its id gets its source folder's name as a prefix when two folders share an id (so nothing
is overwritten); Mean/Std are recomputed over the merged train split (HumanML3D's per-group std); ``provenance.json``
says where every clip came from; ``actions.json`` is merged when the folders have one. The folder is built beside
``--out`` under a temporary name and renamed at the end: a failure leaves nothing, an existing folder is refused.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..inputs import InputError, check_output_folder
from ..motion import features as F

SPLITS = ("train", "val", "test")
MANIFEST = ".mld_merge.json"


def _ids(folder: Path, split: str) -> list[str]:
    path = folder / f"{split}.txt"
    return [line.strip() for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []


def check_sources(sources: list[Path]) -> None:
    if len(sources) < 2:
        raise InputError("data merge needs at least two folders")
    if len({s.resolve() for s in sources}) != len(sources):
        raise InputError("data merge got the same folder twice")
    for s in sources:
        missing = [n for n in ("new_joint_vecs", "texts", "train.txt") if not (s / n).exists()]
        if missing:
            raise InputError(f"{s} is not a HumanML3D-format folder (missing {', '.join(missing)})")


def merged_ids(sources: list[Path]) -> list[tuple[Path, str, str, str]]:
    """(source, split, original id, merged id) for every clip; ids that two sources share get a prefix."""
    seen: dict[str, int] = {}
    rows = [(s, split, cid) for s in sources for split in SPLITS for cid in _ids(s, split)]
    for _, _, cid in rows:
        seen[cid] = seen.get(cid, 0) + 1
    return [(s, split, cid, f"{s.name}_{cid}" if seen[cid] > 1 else cid) for s, split, cid in rows]


def merge(sources, out) -> dict:
    """Write the merged folder ``out``; returns a summary (clips per split, per source)."""
    sources = [Path(s).expanduser() for s in sources]
    out = Path(out).expanduser().absolute()
    check_sources(sources)
    check_output_folder(out, "--out")
    if out.exists() and any(out.iterdir()):
        raise InputError(f"--out {out} is not empty; choose a new or empty folder - nothing was changed")
    rows = merged_ids(sources)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        _write(tmp, rows, sources)
        if out.exists():
            out.rmdir()  # empty (checked above)
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return {"out": str(out), "splits": {sp: sum(1 for r in rows if r[1] == sp) for sp in SPLITS},
            "sources": {str(s): sum(1 for r in rows if r[0] == s) for s in sources}}


def _write(tmp: Path, rows, sources: list[Path]) -> None:
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (tmp / sub).mkdir()
    train_feats = []
    for source, split, cid, new in rows:
        feats = source / "new_joint_vecs" / f"{cid}.npy"
        if not feats.is_file():
            raise InputError(f"{source}: {split}.txt names {cid}, which has no new_joint_vecs/{cid}.npy")
        shutil.copyfile(feats, tmp / "new_joint_vecs" / f"{new}.npy")
        for sub, ext in (("new_joints", "npy"), ("texts", "txt")):
            src = source / sub / f"{cid}.{ext}"
            if src.is_file():
                shutil.copyfile(src, tmp / sub / f"{new}.{ext}")
        if split == "train":
            train_feats.append(np.load(feats))
    for split in SPLITS:
        (tmp / f"{split}.txt").write_text("".join(f"{r[3]}\n" for r in rows if r[1] == split))
    (tmp / "all.txt").write_text("".join(f"{r[3]}\n" for r in rows))
    mean, std = F.mean_std(train_feats)
    np.save(tmp / "Mean.npy", mean)
    np.save(tmp / "Std.npy", std)
    provenance = {r[3]: {"source": str(r[0]), "id": r[2], "split": r[1]} for r in rows}
    (tmp / "provenance.json").write_text(json.dumps(provenance, indent=1) + "\n")
    actions = _merged_actions(rows, sources)
    if actions is not None:
        (tmp / "actions.json").write_text(json.dumps(actions, indent=1) + "\n")
    (tmp / MANIFEST).write_text(json.dumps({"written_by": "mld_core data merge",
                                            "sources": [str(s) for s in sources]}, indent=1) + "\n")


def _merged_actions(rows, sources: list[Path]) -> dict | None:
    """The sources' actions.json merged (clip labels under their merged ids), or None when none has one."""
    loaded = {s: json.loads((s / "actions.json").read_text()) for s in sources if (s / "actions.json").is_file()}
    if not loaded:
        return None
    clips = {new: loaded[s]["clips"][cid] for s, _, cid, new in rows if s in loaded and cid in loaded[s].get("clips", {})}
    return {"classes": sorted(set(clips.values())), "clips": clips}
