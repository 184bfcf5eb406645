"""A worker thread that runs generation jobs one at a time (bpy-free).

The main thread (Blender's UI) submits a job and then polls: :meth:`JobRunner.finished` hands back the
jobs that ended since the last call, so bpy is only ever touched by the caller on the main thread (from a
``bpy.app.timers`` callback). The work function runs on the worker thread and receives the job; it reports
progress through ``job.step(step, total)``, whose return value is the pipeline callback's answer: False once
cancel was requested, so the pipeline stops within one diffusion step.

Job states: queued -> running -> done | failed | cancelled. A failed job carries ``error`` (one sentence
for the user) and ``details`` (the traceback, for the console only).
"""

from __future__ import annotations

import itertools
import queue
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

QUEUED, RUNNING, DONE, FAILED, CANCELLED = "queued", "running", "done", "failed", "cancelled"
ENDED = (DONE, FAILED, CANCELLED)


class JobCancelled(Exception):
    """Raised inside the work function when the job was cancelled (any pipeline 'Cancelled' works too)."""


def user_message(exc: BaseException) -> str:
    """One readable sentence for an exception (no traceback)."""
    from .dependencies import dependency_message

    if isinstance(exc, ModuleNotFoundError) and exc.name:
        root = exc.name.split(".")[0]
        if root in {"torch", "safetensors", "tqdm", "numpy"}:
            return dependency_message([root])
        return f"Missing Python module {exc.name!r}"
    text = str(exc).strip() or exc.__class__.__name__
    if exc.__class__.__module__.startswith("mld_core") and str(exc).strip():
        return text  # mld_core's errors (CheckpointError, TextEncoderError ...) are written for users
    if isinstance(exc, (ValueError, FileNotFoundError, PermissionError, RuntimeError)) and str(exc).strip():
        # Messages of these are written for users (RequestError, BVHError, missing files ...).
        if isinstance(exc, FileNotFoundError) and exc.filename and str(exc.filename) not in text:
            text = f"{text}: {exc.filename}"
        return text.splitlines()[0] if len(text) > 400 else text
    return f"{exc.__class__.__name__}: {text}"


def _is_cancellation(exc: BaseException) -> bool:
    return isinstance(exc, JobCancelled) or exc.__class__.__name__ == "Cancelled"


@dataclass(eq=False)
class Job:
    id: int
    request: Any
    state: str = QUEUED
    step_done: int = 0
    step_total: int = 0
    stage: str = "queued"  # a word for the panel: queued, loading model, denoising, posing ...
    result: Any = None
    error: str = ""
    details: str = ""
    submitted_at: float = field(default_factory=time.perf_counter)
    started_at: float | None = None
    ended_at: float | None = None
    _cancel: threading.Event = field(default_factory=threading.Event, repr=False)
    _ended: threading.Event = field(default_factory=threading.Event, repr=False)

    # -- main thread -------------------------------------------------------------------------------------
    def cancel(self) -> None:
        """Ask the job to stop; a running pipeline stops at its next step callback."""
        self._cancel.set()

    @property
    def cancel_requested(self) -> bool:
        return self._cancel.is_set()

    @property
    def ended(self) -> bool:
        return self.state in ENDED

    @property
    def progress(self) -> float:
        """0..1 over the diffusion steps."""
        if self.state == DONE:
            return 1.0
        if self.step_total <= 0:
            return 0.0
        return min(1.0, max(0.0, self.step_done / self.step_total))

    @property
    def elapsed(self) -> float:
        start = self.started_at if self.started_at is not None else self.submitted_at
        end = self.ended_at if self.ended_at is not None else time.perf_counter()
        return end - start

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the job ended (for headless use and tests); True if it did."""
        return self._ended.wait(timeout)

    # -- worker thread -----------------------------------------------------------------------------------
    def step(self, step: int, total: int) -> bool:
        """Progress callback for the pipeline; False tells it to stop (cancel requested)."""
        self.step_done, self.step_total = int(step), int(total)
        self.stage = "denoising"
        return not self._cancel.is_set()

    def check_cancel(self) -> None:
        """Raise :class:`JobCancelled` if cancel was requested (between stages of the work)."""
        if self._cancel.is_set():
            raise JobCancelled()


WorkFn = Callable[[Job], Any]


class JobRunner:
    """Runs ``work(job) -> result`` for each submitted job on one daemon worker thread, in order."""

    def __init__(self, work: WorkFn, *, name: str = "mld-generate"):
        self._work = work
        self._name = name
        self._queue: queue.Queue[Job | None] = queue.Queue()
        self._finished: queue.Queue[Job] = queue.Queue()
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._jobs: list[Job] = []  # not yet handed back by finished()

    # -- main thread -------------------------------------------------------------------------------------
    def submit(self, request: Any) -> Job:
        job = Job(id=next(self._ids), request=request)
        with self._lock:
            self._jobs.append(job)
            self._ensure_thread()
        self._queue.put(job)
        return job

    def run_now(self, request: Any) -> Job:
        """Run a job on the calling thread (headless/batch use); returns it ended."""
        job = Job(id=next(self._ids), request=request)
        self._run(job, report=False)
        return job

    @property
    def busy(self) -> bool:
        """True while a submitted job has not ended."""
        with self._lock:
            return any(not job.ended for job in self._jobs)

    @property
    def current(self) -> Job | None:
        """The first submitted job that has not ended yet."""
        with self._lock:
            for job in self._jobs:
                if not job.ended:
                    return job
        return None

    def cancel_all(self) -> None:
        with self._lock:
            for job in self._jobs:
                job.cancel()

    def finished(self) -> list[Job]:
        """Jobs that ended since the last call, in the order they ended (call from the main thread)."""
        done = []
        while True:
            try:
                job = self._finished.get_nowait()
            except queue.Empty:
                break
            done.append(job)
        if done:
            with self._lock:
                self._jobs = [job for job in self._jobs if job not in done]
        return done

    def shutdown(self, *, cancel: bool = True, timeout: float | None = 5.0) -> None:
        """Stop the worker (cancelling jobs unless told not to); waits up to ``timeout`` seconds."""
        if cancel:
            self.cancel_all()
        with self._lock:
            thread, self._thread = self._thread, None
        if thread is not None:
            self._queue.put(None)
            thread.join(timeout)

    # -- worker thread -----------------------------------------------------------------------------------
    def _ensure_thread(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            self._thread = threading.Thread(target=self._loop, name=self._name, daemon=True)
            self._thread.start()

    def _loop(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            self._run(job)

    def _run(self, job: Job, report: bool = True) -> None:
        job.started_at = time.perf_counter()
        interrupt: BaseException | None = None
        try:
            if job.cancel_requested:
                raise JobCancelled()
            job.state, job.stage = RUNNING, "starting"
            job.result = self._work(job)
            if job.cancel_requested:
                # Cancel arrived after the last diffusion step: the user asked for nothing, give nothing.
                job.result = None
                raise JobCancelled()
            end = DONE
        except BaseException as exc:  # noqa: BLE001 - every failure must end the job, never the thread
            if _is_cancellation(exc):
                end = CANCELLED
            else:
                end = FAILED
                job.error = user_message(exc)
                job.details = traceback.format_exc()
                if not isinstance(exc, Exception):
                    interrupt = exc  # KeyboardInterrupt / SystemExit: record, then let it through
        job.ended_at = time.perf_counter()
        # The state goes last: another thread that sees the job ended must also see its error, details and end time.
        job.state, job.stage = end, end
        if report:
            self._finished.put(job)  # before wait() returns: a waiter's next finished() call sees the job
        job._ended.set()
        if interrupt is not None:
            raise interrupt
