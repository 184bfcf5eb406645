"""Which model Generate uses: the Preferences' model folder (or ``MLD_MODEL_DIR``) when one is set, else the bundled
model chosen in the panel (mld_core.bundled), or under Auto the bundled model the prompt goes to
(mld_core.model_route). No bpy here: the panel, the operators, the worker and the coverage watcher read it."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from mld_core import bundled
from mld_core.bundled import DEFAULT_NAME, UnknownModel, bundled_models, model_folder, model_id_in, weights_use
from mld_core.inputs import model_limits
from mld_core.model_route import AUTO, is_auto, route_line, routed

AUTO_TIP = ("Auto: the default model, and for a prompt it has not learned that asks for a jump, a crawl, a fall, ... "
            "the bundled model trained to make it")


def model_items() -> list[tuple[str, str, str]]:
    """The panel's Model choices, (name, label, tooltip) per bundled model, the default first."""
    items = [(AUTO, "Auto", AUTO_TIP)] if len(bundled_models()) > 1 else []
    for name, model_id in bundled_models().items():
        tip = f"The bundled model {model_id} (mld_core/weights/{name}; its MODEL_CARD.md says what it makes)"
        use = f". Its weights: {weights_use(bundled.WEIGHTS_DIR / name)}"
        items.append((name, model_id, tip + (", the default" if name == DEFAULT_NAME else "") + use))
    return items or [(DEFAULT_NAME, "default", "The bundled default model")]


def folder_override(prefs_dir: str | None, env_dir: str | None) -> str | None:
    """The model folder set outside the panel (the Preferences' folder, else ``MLD_MODEL_DIR``), or None."""
    for value in (prefs_dir, env_dir):
        if value and str(value).strip():
            return str(value).strip()
    return None


def chosen_model_dir(choice: str | None, override: str | None = None) -> str | None:
    """The model folder for a request: ``override``, a folder set outside the panel (folder_override), wins; else
    the panel's bundled ``choice``'s folder (None for the default, or for a name no longer bundled, which loads the
    default); AUTO under Auto (pipe_for_request routes each request)."""
    if override is not None:
        return override
    if choice == AUTO:
        return AUTO
    if not choice or choice == DEFAULT_NAME:
        return None
    return str(bundled.WEIGHTS_DIR / choice) if choice in bundled_models() else None


def folder_override_for(prefs) -> str | None:
    """folder_override of the add-on's preferences ``prefs`` (None: none set) and ``MLD_MODEL_DIR``."""
    from ..env import model_dir_override

    return folder_override(getattr(prefs, "model_dir", "") if prefs else "", model_dir_override())


def model_dir_for(settings, prefs) -> str | None:
    """The model folder Generate uses for the panel's ``settings`` and the add-on's preferences ``prefs`` (None:
    none set)."""
    return chosen_model_dir(getattr(settings, "model", None), folder_override_for(prefs))


def has_draft(model_dir: str | None) -> bool:
    """Whether a model folder (None: the bundled default) has a Draft denoiser (Draft mode, Live Preview)."""
    return model_limits(model_dir).draft_guidance is not None


def pipe_for_request(cache, request):
    """The pipeline a request runs on (``cache`` a model_cache.PipelineCache): route_request's."""
    return route_request(cache, request)[0]


def route_request(cache, request) -> tuple[object, list[str]]:
    """(the pipeline a request runs on, the lines saying why Auto left the default): its model folder's; under Auto
    the bundled model its prompt (a sequence: its segments, together) goes to. A Draft asked of a model without one
    raises ValueError naming the model Auto chose."""
    if not is_auto(request.model_dir):
        return cache.get(request.model_dir, request.device, request.threads), []
    sequence = request.extra.get("sequence") if isinstance(request.extra, dict) else None
    prompts = [p for p, _ in sequence] if sequence else [request.prompt]
    default = cache.get(None, request.device, request.threads)
    name, said = routed(default.coverage(prompts), one_motion=True)
    pipe = default if name == DEFAULT_NAME else cache.get(name, request.device, request.threads)
    if request.draft and getattr(pipe, "draft_denoiser", None) is None:
        raise ValueError(f"Auto chose {name} for this prompt and it has no Draft: use Final")
    return pipe, said


@lru_cache(maxsize=64)
def auto_line(prompt: str, verdict: str, known_contents: tuple) -> str:
    """The panel's line under a prompt under Auto ('' when it stays with the default), from the default's
    coverage verdict and contents; cached, as the panel draws it on every redraw."""
    from mld_core.condition.coverage import Coverage

    line = route_line(Coverage(prompt, 0.0, verdict, [], list(known_contents)))
    return line[:1].upper() + line[1:]


@lru_cache(maxsize=64)
def other_model_line(prompt: str, verdict: str, model_dir: str | None, overridden: bool) -> str:
    """The panel's line under an ``unknown`` verdict when another bundled model is trained on the prompt's verbs
    ('' otherwise); ``overridden``: a Preferences folder is in use, which must be cleared first."""
    from mld_core.condition.coverage import Coverage
    from mld_core.take_report import PANEL_PICK, other_model_note

    if is_auto(model_dir):  # Auto already goes to that model (mld_core.model_route.route_line says so)
        return ""
    pick = ("clear the Preferences' model folder, then " if overridden else "") + PANEL_PICK
    return other_model_note(Coverage(prompt, 0.0, verdict), model_id_of(model_dir), pick)


def folder_weights_line(folder: str) -> str:
    """The panel's line under a model folder set in the Preferences: what its weights may be used for (the
    bundled models say it in the Model choice's tooltip); cached per folder and config.json change, as the panel
    draws it on every redraw."""
    config = Path(folder).expanduser() / "config.json"
    try:
        stat = config.stat()
        stamp = (stat.st_mtime_ns, stat.st_size)
    except OSError:
        stamp = (0, 0)
    return _weights_line(str(Path(folder).expanduser()), stamp)


@lru_cache(maxsize=16)
def _weights_line(folder: str, stamp: tuple) -> str:
    return f"Its weights: {weights_use(Path(folder))}" if model_id_in(Path(folder)) is not None else ""


def model_id_of(model_dir: str | None) -> str:
    """The model id in a model folder's config.json (None: the bundled default); '' when it cannot be read."""
    try:
        return model_id_in(model_folder(model_dir)) or ""
    except UnknownModel:
        return ""
