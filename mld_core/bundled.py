"""The model folders that ship with mld_core (``mld_core/weights/<name>``), and a model named by folder or by name.

    model_folder(None)           # the bundled default, mld_core/weights/default
    model_folder("v4_preview")   # a bundled model by its name
    model_folder("runs/mine")    # any model folder by its path

A folder wins over a bundled name: with a folder called ``default`` in the working directory, ``default`` names that
folder (the bundled default is then named by None or "").
"""

from __future__ import annotations

import json
from pathlib import Path

from mld_core.data import terms

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_NAME = "default"
MODEL_FORMAT = "mld-core-model"  # config.json's "format" (mld_core.checkpoint.FORMAT is this)


class UnknownModel(ValueError):
    """A model named by neither a folder nor a bundled model's name."""


def _generation_config(folder: Path) -> dict | None:
    """A folder's config.json when it is a generation model's; None otherwise (missing, unreadable, an evaluator's)."""
    try:
        data = json.loads((folder / "config.json").read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return None
    return data if isinstance(data, dict) and data.get("format") == MODEL_FORMAT else None


def model_id_in(folder: Path) -> str | None:
    """The model id in a model folder's config.json; None when it is not a generation model's."""
    data = _generation_config(folder)
    return None if data is None else str(data.get("model_id") or folder.name)


def training_data_in(folder: Path) -> list[dict] | None:
    """A model folder's ``training_data`` (config.json; mld_core.data.terms), checked; None when it records none
    or is not a readable generation model's."""
    try:
        return terms.checked((_generation_config(Path(folder)) or {}).get("training_data"))
    except ValueError:
        return None


def weights_use(folder: Path) -> str:
    """What a model folder's weights may be used for, in a few words: a folder that records no training data is of
    unknown terms."""
    return terms.use_label(training_data_in(folder) or [terms.unrecorded(Path(folder).name)])


def bundled_models() -> dict[str, str]:
    """{name: model id} of every bundled generation model, the default first, the rest by name (the evaluator,
    which generates nothing, is not one)."""
    found = {}
    folders = sorted(WEIGHTS_DIR.iterdir(), key=lambda p: (p.name != DEFAULT_NAME, p.name)) if WEIGHTS_DIR.is_dir() \
        else []
    for folder in folders:
        model_id = model_id_in(folder) if folder.is_dir() else None
        if model_id is not None:
            found[folder.name] = model_id
    return found


def model_folder(value: str | Path | None) -> Path:
    """The folder of a model given as None or "" (the bundled default), a path (returned as it is: loading it says
    what is wrong with it), or a bundled model's name; ``UnknownModel`` (one line, naming the bundled models) for a
    bare name that is neither a folder nor a bundled model."""
    if value is None or str(value).strip() == "":
        return WEIGHTS_DIR / DEFAULT_NAME
    path = Path(value)
    if path.is_dir() or len(path.parts) > 1 or path.is_absolute():
        return path
    name = str(value).strip()
    if name in bundled_models():
        return WEIGHTS_DIR / name
    names = ", ".join(bundled_models()) or "none"
    raise UnknownModel(f"model folder not found: {value} (bundled models: {names})")


def verb_labels(name: str) -> set[str]:
    """The labels a bundled model's verb guidance was trained on (config.json's ``verb_guide.actions``; empty when
    it has none)."""
    guide = (_generation_config(WEIGHTS_DIR / name) or {}).get("verb_guide")
    actions = guide.get("actions") if isinstance(guide, dict) else None
    return {str(a) for a in actions} if isinstance(actions, list) else set()


def model_for_verbs(verbs, current_model_id: str) -> str | None:
    """The first bundled model other than the one whose id is ``current_model_id`` that is trained on every one of
    the checked ``verbs`` (mld_core.data.verbs), by its verb guidance; None when there is none or no verb."""
    wanted = set(verbs)
    if not wanted:
        return None
    for name, model_id in bundled_models().items():
        if model_id != current_model_id and wanted <= verb_labels(name):
            return name
    return None
