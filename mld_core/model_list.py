"""``python -m mld_core models [MODEL ...]``: the bundled models (or the named ones), each with its id and whose terms
its weights carry (config.json's ``training_data``, mld_core.data.terms). Reads config files only: no torch."""

from __future__ import annotations

from pathlib import Path

from mld_core import bundled
from mld_core.data import terms


def register(groups) -> None:
    p = groups["root"].add_parser(
        "models", help="the bundled models and whose terms their weights carry",
        description="List the bundled models (or the named model folders or bundled names): name, model id, and "
                    "what their weights may be used for, from the data and models they were trained on.")
    p.add_argument("models", nargs="*", metavar="MODEL", help="a model folder or a bundled model's name "
                   "(default: every bundled model)")
    p.set_defaults(func=_run)


def model_lines(name: str, folder: Path) -> list[str]:
    """A model's lines: its name, id and use, then one line per source of its training data."""
    model_id = bundled.model_id_in(folder)
    sources = bundled.training_data_in(folder) or [terms.unrecorded(f"model {model_id}")]
    head = f"{name}: {model_id}, {terms.use_label(sources)}"
    return [head] + [f"  trained on {e['name']}: {e['licence']}" for e in sources]


def _run(args) -> int:
    from mld_core.cli import UsageError

    names = args.models or list(bundled.bundled_models())
    lines = []
    for name in names:
        try:
            folder = bundled.model_folder(name)
        except bundled.UnknownModel as exc:
            raise UsageError(str(exc)) from None
        if bundled.model_id_in(folder) is None:
            raise UsageError(f"{name} is not a model folder (no readable config.json of a generation model)")
        lines += model_lines(name, folder)
    print("\n".join(lines) if lines else "no bundled models")
    return 0
