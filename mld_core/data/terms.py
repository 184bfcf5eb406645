"""Whose terms a prepared folder's motion and captions carry, and so the weights trained on them.

``data prepare`` writes ``terms.json`` (one entry per source) into its folder and ``data merge`` joins its sources'
entries. Every training stage and every tool that puts trained weights into a model folder adds the entries of what
it read (data folders, the models it started from) to config.json's ``training_data``, so a model says whose terms
its weights carry (``commercial_use``), its card and the add-on's licence notice say it, and a model that owes
nothing to non-commercial data can be told from one that does.

An entry: ``{"name": ..., "licence": ..., "commercial": true | false | null}``, where ``commercial`` says whether
weights trained on that source may go into commercial products: false for any source that forbids it, null where
its terms are not known (a user's own BVH folder, a model from before these records), true only where they allow it.
"""

from __future__ import annotations

import json
from pathlib import Path

TERMS_FILE = "terms.json"

BANDAI = {"name": "Bandai-Namco-Research-Motiondataset (Bandai Namco Research Inc.)", "licence": "CC BY-NC 4.0",
          "commercial": False}
CMU = {"name": "CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu)",
       "licence": "CMU's terms: free for research, may be included in commercially-sold products, not resold as data",
       "commercial": True}
KIT = {"name": "KIT Motion-Language Dataset sentences (Plappert et al. 2016)", "licence": "not stated",
       "commercial": None}

_RANK = {False: 0, None: 1, True: 2}  # the more restrictive of two entries of one name wins


def unrecorded(name: str) -> dict:
    """The entry of something whose data is not recorded: its terms are unknown."""
    return {"name": str(name), "licence": "not recorded", "commercial": None}


def checked(sources) -> list[dict]:
    """``sources`` as a list of well-formed entries (ValueError, one line, otherwise)."""
    if not isinstance(sources, list) or not sources:
        raise ValueError(f"training data terms must be a non-empty list of entries, got {sources!r}")
    out = []
    for entry in sources:
        if not (isinstance(entry, dict) and isinstance(entry.get("name"), str) and entry["name"].strip()
                and isinstance(entry.get("licence"), str) and entry["licence"].strip() and "commercial" in entry
                and (entry["commercial"] is None or isinstance(entry["commercial"], bool))):
            raise ValueError(f"a training data entry needs a name, a licence and commercial true/false/null, "
                             f"got {entry!r}")
        out.append({"name": entry["name"], "licence": entry["licence"], "commercial": entry["commercial"]})
    return out


def union(*lists) -> list[dict]:
    """The entries of every list, each name once (first place kept; of two differing entries the more restrictive)."""
    by_name: dict[str, dict] = {}
    for sources in lists:
        for entry in checked(sources):
            kept = by_name.get(entry["name"])
            if kept is None or _RANK[entry["commercial"]] < _RANK[kept["commercial"]]:
                by_name[entry["name"]] = entry
    return list(by_name.values())


def write(folder: Path, sources: list[dict]) -> None:
    """``terms.json`` in ``folder`` (a folder being written: callers write into their staging folder)."""
    (Path(folder) / TERMS_FILE).write_text(json.dumps({"sources": checked(sources)}, indent=1) + "\n",
                                           encoding="utf-8")


def of_folder(folder: Path) -> list[dict]:
    """A data folder's entries; a folder without a readable ``terms.json`` (HumanML3D, KIT-ML, one prepared before
    these records) is one entry of unknown terms named by the folder."""
    try:
        return checked(json.loads((Path(folder) / TERMS_FILE).read_text(encoding="utf-8"))["sources"])
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        return [unrecorded(f"data folder {Path(folder).name}")]


def of_model(config) -> list[dict]:
    """A model config's entries (``training_data``); a model without them is one entry of unknown terms."""
    recorded = getattr(config, "training_data", None)
    return checked(recorded) if recorded else [unrecorded(f"model {config.model_id}")]


def add_to(config, *lists) -> None:
    """Add entries to a model config's ``training_data`` (its own first, unknown when it has none)."""
    config.training_data = union(of_model(config), *lists)


def commercial_use(sources) -> bool | None:
    """May weights trained on ``sources`` go into commercial products: False when any source forbids it, True when
    every source allows it, None when some source's terms are unknown."""
    values = [entry["commercial"] for entry in checked(sources)]
    if False in values:
        return False
    return True if all(values) else None


def _forbidding(sources) -> str:
    """The licences of the sources that forbid commercial use, joined."""
    return ", ".join(e["licence"] for e in checked(sources) if e["commercial"] is False)


def use_label(sources) -> str:
    """A few words on what the weights may be used for, for the add-on's model choices."""
    use = commercial_use(sources)
    if use is False:
        return f"non-commercial ({_forbidding(sources)})"
    return "may be used in commercial products" if use else "use as its training data's terms allow"


def licence_summary(sources) -> str:
    """One line for a model card's licence row and the add-on's model notice."""
    use = commercial_use(sources)
    names = "; ".join(f"{e['name']}: {e['licence']}" for e in checked(sources))
    if use is False:
        return f"**non-commercial** ({_forbidding(sources)}), inherited from the training data ({names})"
    if use is True:
        return f"**may be used in commercial products**: every source of its training data allows it ({names})"
    return f"**as the licences of its training data allow**: some are not recorded or not stated ({names})"
