"""What a HumanML3D-format training folder holds: hours per source, per checked verb and per split, as a table for
its README (``data merge`` writes one; ``python -m mld_core data summary DIR`` prints it for any folder)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mld_core.data.verbs import VERBS, verbs_in

SPLITS = ("train", "val", "test")


def _ids(root: Path, split: str) -> list[str]:
    path = root / f"{split}.txt"
    if not path.is_file():
        return []
    return [line.strip() for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def _frames(path: Path) -> int:
    return int(np.load(path, mmap_mode="r").shape[0])


def _captions(path: Path) -> list[str]:
    if not path.is_file():
        return []
    return [line.split("#")[0].strip() for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def folder_summary(root, fps: float = 20.0) -> dict:
    """{"hours": {split: {source: h}}, "verbs": {verb: {split: h}}, "captioned": {split: h}} for the folder ``root``;
    the source of a clip is read from ``provenance.json`` (a merged folder), else it is the folder's name."""
    root = Path(root)
    provenance_path = root / "provenance.json"
    provenance = json.loads(provenance_path.read_text(encoding="utf-8")) if provenance_path.is_file() else {}
    hours = {sp: {} for sp in SPLITS}
    verbs = {v: {sp: 0.0 for sp in SPLITS} for v in VERBS}
    captioned = {sp: 0.0 for sp in SPLITS}
    for split in SPLITS:
        for cid in _ids(root, split):
            feats = root / "new_joint_vecs" / f"{cid}.npy"
            if not feats.is_file():
                continue
            h = _frames(feats) / fps / 3600.0
            source = Path(provenance.get(cid, {}).get("source", root.name)).name
            hours[split][source] = hours[split].get(source, 0.0) + h
            texts = _captions(root / "texts" / f"{cid}.txt")
            if texts:
                captioned[split] += h
            for verb in set(v for t in texts for v in verbs_in(t)):
                verbs[verb][split] += h
    return {"hours": hours, "verbs": verbs, "captioned": captioned}


def summary_table(summary: dict) -> str:
    """The summary as Markdown tables (hours, mirrored copies included)."""
    sources = sorted({s for per in summary["hours"].values() for s in per})
    lines = ["| split | " + " | ".join(sources) + " | all | captioned |", "|---|" + "---|" * (len(sources) + 2)]
    for split in SPLITS:
        per = summary["hours"][split]
        lines.append(f"| {split} | " + " | ".join(f"{per.get(s, 0.0):.2f}" for s in sources)
                     + f" | {sum(per.values()):.2f} | {summary['captioned'][split]:.2f} |")
    lines += ["", "| verb (captions that ask for it) | " + " | ".join(SPLITS) + " |", "|---|---|---|---|"]
    for verb, per in summary["verbs"].items():
        lines.append(f"| {verb} | " + " | ".join(f"{per[sp]:.2f}" for sp in SPLITS) + " |")
    return "\n".join(lines) + "\n"
