"""Prompt coverage while the user types, and the words the panel uses for coverage and badges (bpy-free).

:class:`CoverageWatcher` debounces prompt edits and checks the newest prompt on its own thread, so typing never
waits on torch: the check (given by the caller; the add-on's loads the model through its model cache once and runs
only the text encoder against the model's coverage index, ``MLDPipeline.coverage``) never runs on the main thread.
:func:`coverage_line` and :func:`badge_lines` are the panel's text. The bpy side is ``quality_ui``.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

DEBOUNCE_S = 0.3
VERDICT_TEXT = {
    "known": ("CHECKMARK", "Known to this model"),
    "near": ("INFO", "Near what this model learned"),
    "unknown": ("ERROR", "Not learned by this model"),
}
# (custom property, label, format, one-line explanation), in the order drawn
BADGE_LINES = (
    ("mld_adherence", "Adherence", "{:.0f}", "match to the prompt: percentile of real clips"),
    ("mld_skating", "Foot skating", "{:.2f}", "planted toes sliding (real walks: 0.2)"),
    ("mld_foot_float", "Foot float", "{:.2f}", "no foot on the floor, not jumping (real: 0)"),
    ("mld_penetration_cm", "Penetration", "{:.1f} cm", "deepest joint below the floor (real: 0)"),
    ("mld_jitter", "Jitter", "{:.2f}", "jerk relative to motion capture (real: 1)"),
    ("mld_side", "Side", "{}", "the side the prompt names: used (named), only the other (opposite), or neither"),
    ("mld_verb", "Verb", "{}", "the jump, crawl, kick, ... the prompt names: all shown by their checks, or missed"),
)


class CoverageWatcher:
    """Checks the newest prompt ``DEBOUNCE_S`` after the last edit, on a worker thread.

    ``check(text, key)`` does the work (runs on the worker); ``key`` says which model (results are cached per
    (text, key)). ``result`` returns the Coverage, or None while it is pending or was never asked."""

    def __init__(self, check, debounce_s: float = DEBOUNCE_S, keep: int = 64):
        self._check, self._debounce = check, debounce_s
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._wanted: tuple | None = None  # (text, key, time of the edit)
        self._results: OrderedDict = OrderedDict()
        self._keep = keep
        self._thread: threading.Thread | None = None
        self.seconds: list = []  # time of each check (the text encoder and the index lookup)

    def request(self, text: str, key=None) -> None:
        with self._lock:
            if (text, key) in self._results:
                return
            self._wanted = (text, key, time.monotonic())
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="mld-coverage", daemon=True)
                self._thread.start()
        self._wake.set()

    def result(self, text: str, key=None):
        with self._lock:
            return self._results.get((text, key))

    @property
    def pending(self) -> bool:
        with self._lock:
            return self._wanted is not None

    def _run(self) -> None:
        while True:
            if not self._wake.wait(timeout=30.0):
                with self._lock:
                    if self._wanted is None:
                        self._thread = None
                        return
            self._wake.clear()
            with self._lock:
                wanted = self._wanted
            if wanted is None:
                continue
            quiet = wanted[2] + self._debounce - time.monotonic()
            if quiet > 0:  # still typing: look again when the prompt has been still for the debounce time
                time.sleep(quiet)
                self._wake.set()
                continue
            text, key, _ = wanted
            t0 = time.perf_counter()
            try:
                found = self._check(text, key)
            except Exception:  # noqa: BLE001 - no model, no index: the panel shows nothing rather than an error
                found = None
            self.seconds.append(time.perf_counter() - t0)
            with self._lock:
                self._results[(text, key)] = found if found is not None else _UNAVAILABLE
                while len(self._results) > self._keep:
                    self._results.popitem(last=False)
                if self._wanted is wanted:
                    self._wanted = None


class _Unavailable:
    verdict = "unavailable"
    score = 0.0
    nearest: list = []
    known_contents: list = []


_UNAVAILABLE = _Unavailable()


def coverage_line(cov) -> tuple[str, str] | None:
    """(icon, text) of the line under the prompt; None when coverage is unavailable."""
    if cov is None or cov.verdict not in VERDICT_TEXT:
        return None
    icon, words = VERDICT_TEXT[cov.verdict]
    text = f"{words} ({cov.score:.2f})"
    if cov.verdict != "known" and cov.nearest:
        text += f": closest '{cov.nearest[0][0].rstrip('.')}'"
    return icon, text


def badge_lines(props) -> list[tuple[str, str]]:
    """[(value line, explanation)] from an Action's custom properties (a mapping); empty when it has none."""
    lines = []
    for key, label, fmt, why in BADGE_LINES:
        if key in props:
            value = props[key]
            lines.append((f"{label}: {fmt.format(value if isinstance(value, str) else float(value))}", why))
    return lines
