"""The meshing thread: runs the mapper's mesh jobs beside mapping and publishes their chunks, at most
`rate_hz()` times a second. A job submitted while another one waits replaces it (covering both jobs'
dirty voxels), and a waiting job makes the running one stop after its current pass: the newer job meshes
from a newer field and picks up every chunk the older one left."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

log = logging.getLogger("h2viz.worker")


@dataclass(frozen=True)
class PassRecord:
    """One pass of a mesh job (for measurements and the status panel)."""

    job_version: int  # the job's version (stamped on its chunks)
    field_version: int  # frames integrated into the field it meshed
    submitted: float  # time.time() the job was submitted
    started: float  # time.time() the job started (after the one before it ended)
    finished: float  # time.time() the pass ended
    chunks: tuple[tuple[int, int, int], ...]  # chunks re-meshed by this pass
    required: bool  # part of the job's required chunks (changed or dirty), not the optional refresh


@dataclass(frozen=True)
class JobRecord:
    """One job the thread ran (for measurements). A job that ran no pass and was not cut short had no chunk to
    re-mesh: its frames allocated no voxel, and refresh passes of later jobs show how they changed the field."""

    version: int  # the job's version
    field_version: int  # frames integrated into the field it meshed
    submitted: float  # time.time() the job was submitted
    finished: float  # time.time() it ended
    passes: int  # passes it ran
    cut_short: bool  # a newer job was waiting when it ended: what it left undone is that job's


class MeshThread:
    """Runs jobs (objects with `run(stop, on_pass, hurry)`, `after(older)`, `version`, `field_version`, like
    `h2viz.mapping.meshing.job.MeshJob`) one at a time; `publish()` is called after passes, no more often than
    `rate_hz()` (<= 0: no limit)."""

    def __init__(
        self,
        publish: Callable[[], None],
        rate_hz: Callable[[], float],
        background: Callable[[], None] | None = None,
        hurry: Callable[[], bool] | None = None,
    ) -> None:
        """`background()` runs first on the thread (e.g. `Backend.serial_thread`: kernels on one core); while
        `hurry()` is true, jobs skip their optional refresh passes (mapping needs the cores)."""
        self._publish, self._rate_hz = publish, rate_hz
        self._background, self._hurry = background, hurry
        self._cond = threading.Condition()
        self._pending: tuple[Any, float] | None = None  # (job, submitted at)
        self._running = False
        self._stopping = False
        self._unpublished = False
        self._unpublished_required = False  # among the unpublished results are a job's required chunks
        self._hold_until = 0.0  # time.monotonic() until which refresh-only results wait for a required pass
        self._required_since: float | None = None  # submission (monotonic) of the running job while on required passes
        self._next_publish = 0.0  # time.monotonic() from which publishing is allowed again
        self.passes: deque[PassRecord] = deque(maxlen=10_000)
        self.jobs: deque[JobRecord] = deque(maxlen=10_000)
        self.published: deque[float] = deque(maxlen=10_000)  # time.time() each publish began (for measurements)
        self.errors: list[str] = []
        self.busy_s = 0.0  # seconds spent running jobs
        self._thread = threading.Thread(target=self._run, name="h2viz-meshing", daemon=True)

    def start(self) -> MeshThread:
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 30.0) -> None:
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout_s)

    def submit(self, job: Any) -> None:
        """Queue `job`; a job still waiting is replaced by `job.after(waiting)`."""
        with self._cond:
            if self._pending is not None:
                job = job.after(self._pending[0])
            self._pending = (job, time.time())
            self._cond.notify_all()

    @property
    def busy(self) -> bool:
        """A job is running or waiting."""
        with self._cond:
            return self._running or self._pending is not None

    def wait_idle(self, timeout_s: float | None = None) -> bool:
        """Block until no job runs or waits and the last results are published; False on timeout."""
        with self._cond:
            done = self._cond.wait_for(
                lambda: not (self._running or self._pending or self._unpublished) or self._stopping, timeout_s
            )
            return bool(done) and not self._stopping

    def catch_up(self, deadline_s: float, timeout_s: float) -> float:
        """Block while the running job has been on its required passes for more than `deadline_s` since it was
        submitted (at most `timeout_s`), so that the caller stops competing for the cores; the seconds waited."""
        with self._cond:
            since = self._required_since
            if since is None or time.monotonic() - since <= deadline_s:
                return 0.0
            start = time.monotonic()
            self._cond.wait_for(lambda: self._required_since is None or self._stopping, timeout_s)
            return time.monotonic() - start

    # -- the thread ----------------------------------------------------------------------------
    def _run(self) -> None:
        if self._background is not None:
            self._background()
        while True:
            with self._cond:
                while self._pending is None and not self._stopping:
                    if self._unpublished and self._publish_allowed():
                        break
                    wait = max(0.0, self._publish_at() - time.monotonic()) if self._unpublished else None
                    self._cond.wait(wait)
                if self._stopping:
                    return
                pending, self._pending = self._pending, None
                self._running = pending is not None
            self._flush()
            if pending is not None:
                self._execute(*pending)

    def _execute(self, job: Any, submitted: float) -> None:
        start, started = time.perf_counter(), time.time()
        with self._cond:
            self._required_since = time.monotonic() - (time.time() - submitted)

        n_passes = 0

        def on_pass(chunks: list[tuple[int, int, int]], required: bool) -> None:
            nonlocal n_passes
            n_passes += 1
            now = time.time()
            record = PassRecord(job.version, job.field_version, submitted, started, now, tuple(chunks), required)
            self.passes.append(record)
            with self._cond:
                if required:
                    self._unpublished_required = True
                else:  # the required passes are done: callers waiting in catch_up go on
                    if not self._unpublished:
                        self._hold_until = time.monotonic() + self._period()
                    self._required_since = None
                    self._cond.notify_all()
                self._unpublished = True
            self._flush()

        try:
            job.run(stop=self._has_pending, on_pass=on_pass, hurry=self._hurry)
        except Exception as e:  # keep meshing later jobs; the failed chunks are retried when next dirty
            log.exception("mesh extraction failed")
            self.errors.append(f"mesh extraction failed: {type(e).__name__}: {e}")
        finally:
            self.busy_s += time.perf_counter() - start
            cut = self._has_pending()
            self.jobs.append(JobRecord(job.version, job.field_version, submitted, time.time(), n_passes, cut))
            with self._cond:
                self._running, self._required_since = False, None
                self._cond.notify_all()
        self._flush()

    def _has_pending(self) -> bool:
        with self._cond:
            return self._pending is not None or self._stopping

    def _period(self) -> float:
        rate = self._rate_hz()
        return 1.0 / rate if rate > 0 else 0.0

    def _publish_at(self) -> float:
        """When the unpublished results may go out: one update period after the last one; results of refresh
        passes alone also wait up to a period for the next job's required chunks, so that they do not start a
        period those would then have to wait out (updates come about one a job instead of two)."""
        if self._unpublished_required:
            return self._next_publish
        return max(self._next_publish, self._hold_until)

    def _publish_allowed(self) -> bool:
        return time.monotonic() >= self._publish_at()

    def _flush(self) -> None:
        """Publish unpublished results when the rate allows."""
        with self._cond:
            if not self._unpublished or not self._publish_allowed():
                return
            self._unpublished = self._unpublished_required = False
            self._next_publish = time.monotonic() + self._period()
        try:
            started = time.time()
            self._publish()
            self.published.append(started)
        except Exception:
            log.exception("publishing the mesh failed")
        with self._cond:
            self._cond.notify_all()
