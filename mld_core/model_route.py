"""Auto: which bundled model makes a prompt.

    model_for(coverage)                       # the default's coverage of a prompt -> a bundled model's name
    routed(coverages)                         # (the one model a call goes to, the lines saying why)
    ModelRouter(load).pipe_for(prompts)       # (name, pipeline) of the one model a call's prompts go to

The default makes what it has learned. A prompt it has not learned (its coverage ``unknown`` or only ``near``) that
names checked verbs (mld_core.data.verbs) none of its contents is, and that another bundled model is trained on
(its verb guidance's labels, mld_core.bundled.model_for_verbs), goes to that model: "a person jumps over a puddle"
goes to v4_preview, "a person kicks high" stays with the default, which has kicks among its contents. The route
reads only the prompt and the default's coverage index, so a prompt goes to the same model on every run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

from mld_core import bundled
from mld_core.bundled import DEFAULT_NAME, model_for_verbs, model_id_in

AUTO = "auto"


class MixedRoute(ValueError):
    """Prompts of one call that go to different models, where a call is made by one model."""


def is_auto(value) -> bool:
    """Whether a --model value asks for Auto (the word ``auto``, unless a folder of that name is in the working
    directory: a folder wins over a name, as in mld_core.bundled.model_folder)."""
    return isinstance(value, str) and value.strip() == AUTO and not Path(value.strip()).is_dir()


def verbs_to_route(coverage) -> list[str]:
    """The checked verbs a prompt names that the default has not learned (none when its coverage is ``known`` or
    unavailable, or when each verb is one of its contents)."""
    from mld_core.data.verbs import verbs_in_order

    if coverage.verdict not in ("unknown", "near"):
        return []
    known = set(getattr(coverage, "known_contents", None) or ())
    return [verb for verb in verbs_in_order(coverage.prompt) if verb not in known]


def model_for(coverage) -> str:
    """The bundled model's name Auto uses for a prompt, from the default's ``coverage`` of it."""
    verbs = verbs_to_route(coverage)
    if not verbs:
        return DEFAULT_NAME
    return model_for_verbs(verbs, model_id_in(bundled.WEIGHTS_DIR / DEFAULT_NAME) or "") or DEFAULT_NAME


def route_line(coverage) -> str:
    """'' when Auto keeps the default for a prompt; else which model makes it and why, for the user to read."""
    from mld_core.data.verbs import VERB_SHOWN

    name = model_for(coverage)
    if name == DEFAULT_NAME:
        return ""
    shown = " and ".join(VERB_SHOWN[v] for v in verbs_to_route(coverage))
    return f"auto: {name} makes this prompt (trained to make {shown}, which the default has not learned)"


def model_for_call(coverages: Sequence, one_motion: bool) -> str:
    """The one model a call goes to: its prompts' model when they agree. A call that makes one motion (a sequence's
    segments) goes to the model another segment needs, which makes the default's contents too; prompts made apart
    that need different models raise MixedRoute (one line, which prompts need which)."""
    names = [model_for(c) for c in coverages]
    others = sorted(set(names) - {DEFAULT_NAME})
    if not others:
        return DEFAULT_NAME
    if len(others) == 1 and (one_motion or set(names) == {others[0]}):
        return others[0]
    groups = {}
    for n, name in enumerate(names, start=1):
        groups.setdefault(name, []).append(str(n))
    listed = "; ".join(f"{name}: prompt{'s' if len(rows) > 1 else ''} {', '.join(rows)}"
                       for name, rows in groups.items())
    raise MixedRoute(f"auto: these prompts need different models ({listed}): generate them apart, or name one "
                     "with --model")


def routed(coverages: Sequence, one_motion: bool = False) -> tuple[str, list[str]]:
    """(model_for_call of the default's ``coverages``, the route_line of each prompt that leaves the default, once
    each; none when the call stays with the default)."""
    name = model_for_call(coverages, one_motion)
    if name == DEFAULT_NAME:
        return name, []
    lines = (route_line(c) for c in {c.prompt: c for c in coverages}.values())
    return name, [line for line in lines if line]


class ModelRouter:
    """The bundled models Auto chooses from, each loaded the first time a call goes to it by ``load(name)`` (each
    with its own text encoder, so a model's Draft keeps its own distilled one)."""

    def __init__(self, load: Callable):
        self._load = load
        self._pipes: dict = {}

    def pipe(self, name: str):
        """The loaded pipeline of a bundled model (loading it the first time)."""
        if name not in self._pipes:
            self._pipes[name] = self._load(name)
        return self._pipes[name]

    def pipe_for(self, prompts: Sequence[str], one_motion: bool = False) -> tuple[str, object]:
        """(name, pipeline) of the model the call's ``prompts`` go to (model_for_call; MixedRoute)."""
        name, pipe, _ = self.route(prompts, one_motion)
        return name, pipe

    def route(self, prompts: Sequence[str], one_motion: bool = False) -> tuple[str, object, list[str]]:
        """(name, pipeline, the lines saying why: routed) of the model the call's ``prompts`` go to."""
        name, lines = routed(self.pipe(DEFAULT_NAME).coverage(list(prompts)), one_motion)
        return name, self.pipe(name), lines
