"""Live Preview's scheduling (bpy-free): wait until the edits pause, then run only the newest request.

:class:`LivePreview` is told of every edit (``edited``) and asked by a main-thread timer when to look again
(``seconds_to_wait``). Once the settings have been still for ``debounce_s`` it hands the newest request to
``submit`` and cancels the job of the one before, so jobs never pile up: at most one runs and one waits.
"""

from __future__ import annotations

import time

DEBOUNCE_S = 0.3


class LivePreview:
    def __init__(self, submit, debounce_s: float = DEBOUNCE_S, clock=time.monotonic):
        self._submit, self.debounce_s, self._clock = submit, debounce_s, clock
        self._last_edit: float | None = None
        self.job = None  # the newest submitted job
        self.submitted = 0
        self.cancelled = 0

    def edited(self) -> None:
        """An edit of the prompt, seconds or seed (call on every change)."""
        self._last_edit = self._clock()

    @property
    def waiting(self) -> bool:
        """An edit has not been submitted yet."""
        return self._last_edit is not None

    def seconds_to_wait(self) -> float:
        """0 when the edits have paused for the debounce time (then call ``fire``), else how long to wait."""
        if self._last_edit is None:
            return 0.0
        return max(0.0, self._last_edit + self.debounce_s - self._clock())

    def fire(self, request) -> object:
        """Submit ``request`` (the settings as they are now), cancelling the previous job; returns the new job."""
        self._last_edit = None
        self.cancel()
        self.job = self._submit(request)
        self.submitted += 1
        return self.job

    def cancel(self) -> None:
        """Cancel the newest job if it has not ended (turning Live Preview off, Keep)."""
        job = self.job
        if job is not None and not getattr(job, "ended", True):
            job.cancel()
            self.cancelled += 1
        self.job = None

    def stop(self) -> None:
        self._last_edit = None
        self.cancel()
