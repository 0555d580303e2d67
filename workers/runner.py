"""Worker processes: ``python -m workers.runner --queue render|bake [--burst] [--name NAME]``.

- ``--queue render`` -> :class:`RenderWorker` (an ``rq.SimpleWorker``): jobs run in the worker
  process itself, so compiled numba kernels, Embree scenes and the scene LRU
  (workers/cache.py) stay warm from one job to the next.
- ``--queue bake`` -> :class:`BakeWorker` (an ``rq.Worker``): a work horse is forked per job,
  so a crash in a job cannot take the worker down. The parent imports the bake job module (and
  with it the engine, mesh loading and Embree's bindings) once at start-up, so every forked horse
  starts with the modules loaded (measured ~2 s per job otherwise, docs/performance.md "Bake
  scaling"), but it never RUNS a numba kernel or creates an Embree device: no thread pool exists
  before a fork (GNU OpenMP / TBB pools are not fork-safe, ARCHITECTURE "Known traps"; the engine
  selects the workqueue layer). Each horse runs its kernels itself, and numba's on-disk cache
  (``cache=True``) saves the compiles.

Both run RQ's scheduler (retries with intervals need it) and install RQ's signal handlers:
SIGTERM / SIGINT -> warm shutdown (finish the current job, then exit); a second signal -> cold
shutdown.

Liveness and abandoned jobs (docs/hard-cases.md #20). RQ marks a running job's execution in the queue's
StartedJobRegistry with an expiry; the busy worker refreshes it every
``job_monitoring_interval`` seconds. When a worker dies (SIGKILL, OOM, machine loss) the
refreshes stop, and the next maintenance pass of ANY worker on that queue (every
``maintenance_interval`` seconds) retries the job (if it has retries left) or moves it to
failed. Stock RQ 3.0 makes that slow: the expiry is ``interval + 60`` s, an idle worker only
wakes for maintenance when its blocking dequeue times out (``worker_ttl - 15`` = 405 s by
default), and a ``SimpleWorker`` never refreshes during a job (expiry = job timeout + 60 s).
So here:

- expiry = ``job_monitoring_interval + heartbeat_grace`` (defaults 10 + 20 s, settings
  ``IBR_JOB_MONITORING_INTERVAL_S`` / ``IBR_HEARTBEAT_GRACE_S``);
- the blocking dequeue waits at most ``maintenance_interval`` (default 30 s,
  ``IBR_MAINTENANCE_INTERVAL_S``), so idle workers do run maintenance on time;
- :class:`RenderWorker` refreshes the heartbeat from a small thread while its job runs, and
  stops refreshing once the job is ``heartbeat_grace`` past its timeout (a job stuck in native
  code then counts as abandoned instead of 'started' forever);
- a bake work horse asks the kernel (``PR_SET_PDEATHSIG``) to be killed with its parent, so a
  SIGKILLed worker leaves no unsupervised horse behind that could publish late.

A dead worker's job is therefore noticed within about
``job_monitoring_interval + heartbeat_grace + maintenance_interval`` (~60 s by default), as
long as one worker of that queue is alive. Worker registration TTL: ``worker_ttl`` (RQ's 420 s),
refreshed while the worker lives.

Redis outages (docs/reliability.md). RQ records a job's start and end with Redis calls outside
its own error handling, so stock, a worker busy when Redis goes away exits ("unhandled
exception") and its job stays 'started' until another worker's maintenance finds it. Here a Redis
error while a job runs or records its end (in the render worker, the bake worker's parent or its
horse) waits for Redis with backoff (0.5 s doubling to 5 s), then :meth:`settle_after_outage`
puts the job back at the front of its queue unless its end was recorded or another worker runs
it; no retry is spent. The loop's own Redis calls (heartbeats, maintenance, the suspension check,
the shutdown bookkeeping) log and back off instead of ending the loop; the idle dequeue
reconnects with RQ's backoff, capped at 5 s. :class:`DyingScheduler` (RQ's forked scheduler) dies
with its worker and waits out outages instead of exiting. On each maintenance pass a worker also
releases what a dead worker of the same host still holds (:meth:`reap_dead_local_peers`), so a
SIGKILLed worker's job is retried at the next pass rather than after its heartbeat expiry and the
dead scheduler's lock (up to 30 + 61 s). A scheduler lock whose holder, on any host, has not
refreshed it for its 1 s period plus ``heartbeat_grace`` is released for a live worker's scheduler
(:meth:`take_over_silent_scheduler_locks`): a lost host's lock is free ~21 s after the loss instead
of 61 s, so the retries of its abandoned jobs run on time. ``--healthcheck`` answers 0 when a live worker of the
queue on this host has beaten recently (the compose health check).

Warm-up (render workers only). As the worker starts taking jobs, :func:`start_background_warm_up`
starts ``python -m workers.warmup --publish <worker name>`` in a process of its own: every engine
path of the render queue's jobs on tiny built-in data, in the order a user is likely to need them
(reference, LDC methods, relighting, walkthroughs), so numba compiles the kernels (empty disk
cache: minutes) or loads them (a few seconds) into its disk cache; the worker's jobs then load
them from there. It publishes per-method readiness in Redis (``producer.readiness``, shown by
``GET /v1/methods`` and the preview). A job whose kernels are not ready yet compiles them itself,
as without a warm-up. On by default (``IBR_WORKER_WARMUP``), off with ``--no-warmup``; it dies
with the worker. A failed step is logged with its traceback (docs/service-design.md, "Worker
start-up and warm-up"). The bake worker's parent never warms up: it must not run a kernel before
forking (above); its horses load the kernels from the disk cache, which a render worker's warm-up
on the same machine (or the image build) fills for the bake kernels too.

Retries: jobs are enqueued with ``Retry(max=2, interval=[5, 30])``; the exception handler
:func:`retry_policy` keeps the retries only for transient failures (store unavailable, Redis
connection trouble, a dead worker); anything else -- invalid payload or scene, NaN output,
time limit exceeded, cancellation -- fails the job at once.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import faulthandler
import functools
import inspect
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from types import TracebackType
from typing import Any, Literal
from uuid import uuid4

from pydantic import ValidationError
from redis import Redis
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import RedisError
from redis.exceptions import TimeoutError as RedisTimeoutError
from rq import SimpleWorker, Worker
from rq.defaults import DEFAULT_LOGGING_DATE_FORMAT, DEFAULT_LOGGING_FORMAT
from rq.exceptions import AbandonedJobError, NoSuchJobError
from rq.job import Job, JobStatus
from rq.job_lifecycle import call_exception_handlers
from rq.queue import Queue
from rq.scheduler import SCHEDULER_KEY_TEMPLATE, RQScheduler
from rq.scripts import release_lock
from rq.serializers import JSONSerializer
from rq.utils import current_timestamp
from rq.worker import WorkerStatus

from engine.memory import keep_freed_memory
from producer.queue import QUEUE_NAMES, QueueName, get_queue, redis_from_url
from producer.settings import Settings
from producer.store import StoreUnavailable
from workers.warmup_steps import lanes_for

__all__ = [
    "TRANSIENT_ERRORS",
    "BakeWorker",
    "RenderWorker",
    "build_worker",
    "main",
    "retry_policy",
    "start_background_warm_up",
    "stop_background_warm_up",
]

log = logging.getLogger("workers.runner")

TRANSIENT_ERRORS: tuple[type[BaseException], ...] = (
    StoreUnavailable,
    RedisConnectionError,
    RedisTimeoutError,
    AbandonedJobError,
)
"""Failures worth a retry; every other exception fails the job at once."""

REDIS_DOWN: tuple[type[BaseException], ...] = (RedisConnectionError, RedisTimeoutError)
"""What redis-py raises while the server is unreachable, restarting or still loading its AOF
(``BusyLoadingError`` is a ``ConnectionError``), after its own short retries."""

OUTAGE_BACKOFF_FIRST_S = 0.5
OUTAGE_BACKOFF_CAP_S = 5.0

EXIT_DEADLINE_S = 30.0
"""Seconds a worker may take from the end of its work loop to its exit: the scheduler's stop (its
1 s loop), the warm-up's stop (at most 15 s) and the interpreter's clean-up. Past it, the worker
logs every thread's stack and exits anyway (:func:`exit_within`)."""

LISTENER_STOP_S = 1.0
"""How long a stopping worker waits for RQ's pub/sub listener (a daemon thread) to end."""


def wait_for_redis(redis: Redis, should_stop: Callable[[], bool], what: str,
                   first: float = OUTAGE_BACKOFF_FIRST_S, cap: float = OUTAGE_BACKOFF_CAP_S) -> bool:
    """Block until ``redis`` answers PING again (exponential backoff from ``first`` to ``cap``
    seconds between attempts); False when ``should_stop()`` turned true first."""
    delay, t0, attempts = first, time.monotonic(), 0
    while not should_stop():
        try:
            redis.ping()
        except REDIS_DOWN as exc:
            attempts += 1
            if attempts == 1 or attempts % 10 == 0:
                log.warning("%s: Redis unreachable for %.0f s (%s); retrying every %.1f s at most",
                            what, time.monotonic() - t0, exc, cap)
            time.sleep(delay)
            delay = min(cap, delay * 2)
            continue
        if attempts:
            log.info("%s: Redis reachable again after %.1f s", what, time.monotonic() - t0)
        return True
    return False


def retry_policy(job: Job, exc_type: type[BaseException] | None, exc_value: BaseException | None,
                 tb: TracebackType | None) -> bool:
    """RQ exception handler: drop the job's remaining retries unless the failure is transient.

    RQ calls the worker's exception handlers before it decides between retry and failure, with
    the same ``Job`` object it then inspects (``job.retries_left``), both for exceptions raised by
    the job and for jobs found abandoned by maintenance. Returns True: later handlers still run.
    """
    transient = exc_type is not None and issubclass(exc_type, TRANSIENT_ERRORS)
    if not transient and job.retries_left:
        log.info("job %s: %s is not transient, not retrying", job.id, exc_type.__name__ if exc_type else "failure")
        job.retries_left = 0
    return True


class _DemoteToInfo(logging.Filter):
    """Logs records whose message template contains ``text`` at INFO (RQ logs a deliberate stop at
    WARNING; here a stop is a cancel on request, not a problem)."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.text = text

    def filter(self, record: logging.LogRecord) -> bool:
        if self.text in str(record.msg) and record.levelno > logging.INFO:
            record.levelno, record.levelname = logging.INFO, "INFO"
        return True


def _was_canceled(job: Job, exc_type: type[BaseException] | None) -> bool:
    # deferred (api_schemas, numba, the engine: seconds of imports): loaded by the job modules by then, and
    # ``--healthcheck`` (a container health check, run every few seconds) never needs them
    from producer.status import cancel_requested
    from workers.jobs.common import JobCanceled

    if exc_type is not None and issubclass(exc_type, JobCanceled):
        return True
    try:
        return bool(job.meta.get("cancel_requested")) or cancel_requested(job.connection, job.id)
    except RedisError:
        return False


def _observe(job: Job, queue: str, outcome: Literal["finished", "failed", "canceled"], seconds: float) -> None:
    """The job's run time into the shared duration histogram; a metrics write never fails a job."""
    from producer.status import job_method, record_job_duration  # deferred, as in ``_was_canceled``

    try:
        record_job_duration(job.connection, queue, job_method(job), outcome, seconds)
    except RedisError as exc:
        log.warning("job %s: duration not recorded: %s", job.id, exc)


def exit_within(seconds: float, status: Callable[[], int]) -> threading.Timer:
    """Make sure this process ends within ``seconds``: if it is still alive then, log it, write
    every thread's stack to stderr (to find what held it) and leave with ``os._exit(status())``.

    A worker whose work is done and whose registration is withdrawn must not stay alive: its
    supervisor (``ibr up``, the container runtime, a rollout) waits for the exit before it starts
    the next one. A daemon thread, so a normal exit does not wait for it."""
    def expire() -> None:
        code = status()
        log.warning("still running %.0f s after the work loop ended; every thread's stack follows, "
                    "then the process exits with status %d", seconds, code)
        for handler in logging.getLogger().handlers:
            handler.flush()
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        os._exit(code)

    timer = threading.Timer(seconds, expire)
    timer.name = "ibr-exit-deadline"
    timer.daemon = True
    timer.start()
    return timer


class _TunedWorkerMixin:
    """Shorter liveness timings (module docstring), cancels logged at INFO, job durations observed
    where the job runs; shared by both worker classes."""

    heartbeat_grace: int = 20
    max_connection_wait_time = OUTAGE_BACKOFF_CAP_S  # the idle dequeue's reconnect backoff (RQ: 60 s)
    maintenance_interval: int
    worker_ttl: int
    job_monitoring_interval: int
    log: logging.Logger
    name: str
    _exc_handlers: list[Any]

    connection: Redis
    serializer: Any
    scheduler: RQScheduler | None
    _stop_requested: bool
    pubsub: Any
    pubsub_thread: Any
    pubsub_channel_name: str

    def perform_job(self, job: Job, queue: Queue, execution: Any) -> bool:
        # Runs where the job runs (the render worker itself, a bake worker's forked horse).
        t0 = time.monotonic()
        try:
            ok: bool = super().perform_job(job, queue, execution)  # type: ignore[misc]
        except REDIS_DOWN as exc:
            # RQ records a job's end with Redis calls outside its own error handling: an outage
            # while the job runs or ends escapes here (and would end the worker's loop).
            self.settle_after_outage(job, queue, execution, exc)
            return False
        outcome: Literal["finished", "failed", "canceled"] = "finished"
        if not ok:
            # RQ logs (does not raise) a failure it could not write: the job would stay 'started'.
            if self._end_not_recorded(job, execution):
                self.settle_after_outage(job, queue, execution, None)
                return False
            outcome = "canceled" if _was_canceled(job, None) else "failed"
        _observe(job, queue.name, outcome, time.monotonic() - t0)
        return ok

    def execute_job(self, job: Job, queue: Queue) -> None:
        # Runs in the worker process. A Redis outage anywhere in it (creating the execution,
        # the bake worker's heartbeats and its reading of the horse's outcome, the state change
        # to idle) settles the job instead of ending the work loop.
        self._current_execution: Any = None
        try:
            super().execute_job(job, queue)  # type: ignore[misc]
        except REDIS_DOWN as exc:
            self.settle_after_outage(job, queue, self._current_execution, exc)

    def prepare_execution(self, job: Job) -> Any:
        # remembered for settle_after_outage: RQ forgets it once the horse has ended
        self._current_execution = None
        executions: dict[str, Any] = self.executions  # type: ignore[attr-defined]
        before = set(executions)
        try:
            self._current_execution = super().prepare_execution(job)  # type: ignore[misc]
        except REDIS_DOWN:
            # RQ registers the execution in memory before writing it: settle cleans it up
            added = [e for k, e in executions.items() if k not in before]
            self._current_execution = added[0] if added else None
            raise
        return self._current_execution

    def _end_not_recorded(self, job: Job, execution: Any) -> bool:
        """True when Redis still lists this execution of ``job`` as running (its end was lost)."""
        if execution is None:
            return False
        try:
            entries = job.started_job_registry.get_job_and_execution_ids(cleanup=False)
        except REDIS_DOWN:
            return True
        return (job.id, execution.id) in entries

    def settle_after_outage(self, job: Job, queue: Queue, execution: Any, exc: BaseException | None) -> None:
        """Once Redis answers again, put a job whose end was never recorded back at the front
        of its queue (no retry is spent: the outage is not the job's fault). A job that did end
        (finished, failed, retried, canceled) or that another worker runs by now is left alone.

        A job that already stored its artifact finds it on the rerun and ends at once. Gives up
        when the worker is asked to stop first: maintenance then treats the job as abandoned
        (retried or failed) once its heartbeat expires."""
        self.log.warning("Worker %s: job %s: Redis went away while it ran or recorded its end (%s); "
                         "settling it once Redis is back", self.name, job.id, exc or "failure not recorded")
        if not wait_for_redis(self.connection, lambda: bool(getattr(self, "_stop_requested", False)),
                              f"job {job.id}"):
            self.log.warning("Worker %s: stopping before Redis came back; job %s is left to maintenance "
                             "(abandoned-job handling)", self.name, job.id)
            return
        for attempt in range(5):
            try:
                self._requeue_if_unrecorded(job, queue, execution)
                return
            except REDIS_DOWN as again:  # Redis went away again in between: wait once more
                if not wait_for_redis(self.connection, lambda: bool(getattr(self, "_stop_requested", False)),
                                      f"job {job.id} (attempt {attempt + 2})"):
                    return
                exc = again
        self.log.error("Worker %s: job %s could not be settled (%s); maintenance will treat it as abandoned",
                       self.name, job.id, exc)

    def _requeue_if_unrecorded(self, job: Job, queue: Queue, execution: Any) -> None:
        conn = self.connection
        try:
            fresh = Job.fetch(job.id, connection=conn, serializer=self.serializer)
        except NoSuchJobError:
            fresh = None
        entries = job.started_job_registry.get_job_and_execution_ids(cleanup=False)
        mine = execution.id if execution is not None else None
        others = [eid for jid, eid in entries if jid == job.id and eid != mine]
        with conn.pipeline() as p:
            if execution is not None:
                self.cleanup_execution(fresh or job, pipeline=p, execution=execution)  # type: ignore[attr-defined]
            p.execute()
        if fresh is None:
            self.log.info("Worker %s: job %s was deleted meanwhile; nothing to settle", self.name, job.id)
            return
        status = fresh.get_status(refresh=False)
        in_queue = conn.lpos(queue.key, job.id) is not None
        if others or not (status == JobStatus.STARTED or (status == JobStatus.QUEUED and not in_queue)):
            self.log.info("Worker %s: job %s needs nothing after the outage (status %s%s)", self.name, job.id,
                          status, ", run by another worker" if others else "")
            return
        conn.lrem(queue.intermediate_queue_key, 0, job.id)
        queue.enqueue_job(fresh, at_front=True)
        self.log.warning("Worker %s: job %s was %s when Redis went away; queued again at the front",
                         self.name, job.id, status)

    # -- Redis outages outside a job: the loop keeps running, with backoff ----------------------

    def heartbeat(self, timeout: int | None = None, pipeline: Any = None) -> None:
        if pipeline is not None:
            super().heartbeat(timeout, pipeline=pipeline)  # type: ignore[misc]
            return
        try:
            super().heartbeat(timeout)  # type: ignore[misc]
        except REDIS_DOWN as exc:
            # the dequeue that follows backs off until Redis is back; the registration's TTL is
            # refreshed by the next heartbeat
            self.log.warning("Worker %s: heartbeat failed: %s", self.name, exc)

    def maintain_heartbeats(self, job: Job, execution: Any) -> None:
        try:
            super().maintain_heartbeats(job, execution)  # type: ignore[misc]
        except REDIS_DOWN as exc:
            self.log.warning("Worker %s: heartbeat of job %s failed: %s", self.name, job.id, exc)

    def check_for_suspension(self, burst: bool) -> None:
        while True:
            try:
                super().check_for_suspension(burst)  # type: ignore[misc]
                return
            except REDIS_DOWN:
                if not wait_for_redis(self.connection, lambda: bool(getattr(self, "_stop_requested", False)),
                                      f"worker {self.name}"):
                    return

    def set_shutdown_requested_date(self) -> None:
        # called from the signal handler: an outage must not turn a warm shutdown into a crash
        try:
            super().set_shutdown_requested_date()  # type: ignore[misc]
        except REDIS_DOWN as exc:
            self.log.warning("Worker %s: shutdown request not recorded in Redis: %s", self.name, exc)

    ends_by_itself = False
    """True for ``--burst`` / ``--max-jobs``: the loop's end is then a normal exit (status 0)."""

    def exit_status(self) -> int:
        """0 when the loop ended as asked (burst, job limit, a stop request), else 1."""
        asked = getattr(self, "_shutdown_requested_date", None) is not None or self._stop_requested
        return 0 if self.ends_by_itself or asked else 1

    exit_deadline_s: float | None = None
    """Set by :func:`main` (the worker owns its process): the process then ends within this many
    seconds of the loop's end (:func:`exit_within`). None for a worker run inside another program."""

    def unsubscribe(self) -> None:
        # RQ's unsubscribe stops its pub/sub listener with PubSubWorkerThread.stop(), which from
        # redis-py 8.2 waits for the listener to end; a listener that has read the UNSUBSCRIBE
        # reply waits a whole poll interval (60 s) for a new subscription first, so workers took
        # a minute to exit. The listener is a daemon thread: stop it, wait a second, move on.
        listener = self.pubsub_thread
        if listener is None:
            return
        self.log.info("Worker %s: unsubscribing from channel %s", self.name, self.pubsub_channel_name)
        self.pubsub.unsubscribe()
        if "timeout" in inspect.signature(listener.stop).parameters:
            listener.stop(timeout=LISTENER_STOP_S)
        else:
            listener.stop()
            listener.join(timeout=LISTENER_STOP_S)
        self.pubsub.close()

    def teardown(self) -> None:
        if self.exit_deadline_s is not None and not getattr(self, "is_horse", False):
            exit_within(self.exit_deadline_s, self.exit_status)
        try:
            super().teardown()  # type: ignore[misc]
        except REDIS_DOWN as exc:
            self.log.warning("Worker %s: Redis unreachable at shutdown (%s); the registration expires "
                             "by its TTL", self.name, exc)

    def handle_exception(self, job: Job, *exc_info: Any) -> None:
        # RQ logs every exception at ERROR with its traceback; a job that stops because it was
        # canceled on request is not an error: one INFO line, then the usual handlers.
        if not _was_canceled(job, exc_info[0] if exc_info else None):
            super().handle_exception(job, *exc_info)  # type: ignore[misc]
            return
        self.log.info("Worker %s: job %s canceled on request", self.name, job.id,
                      extra={"queue": job.origin, "job_id": job.id})
        call_exception_handlers(self._exc_handlers, job, *exc_info)

    @property
    def dequeue_timeout(self) -> int:
        # Wake up for maintenance on time even when idle (stock RQ blocks worker_ttl - 15 s).
        return max(1, min(self.worker_ttl - 15, int(self.maintenance_interval)))

    def dequeue_job_and_maintain_ttl(self, timeout: int | None, max_idle_time: int | None = None) -> Any:
        # RQ blocks in its dequeue ``timeout`` s per round, and runs maintenance between rounds only
        # once ``maintenance_interval`` has passed. Here a round also ends when something in this
        # worker's queues falls due (:meth:`_seconds_to_due`), so a lost worker's job is retried
        # within a second of its heartbeat expiry instead of up to ``maintenance_interval`` later.
        # A round lasts at most the heartbeat expiry (interval + grace), so a job that starts
        # elsewhere during a round expires after that round ends, and the next round sees it.
        if timeout is None or max_idle_time is not None:
            return super().dequeue_job_and_maintain_ttl(timeout, max_idle_time)  # type: ignore[misc]
        timeout = max(1, min(timeout, int(self.job_monitoring_interval) + int(self.heartbeat_grace)))
        while True:
            due = self._seconds_to_due()
            t = timeout if due is None else max(1, min(timeout, math.ceil(due)))
            try:
                result = super().dequeue_job_and_maintain_ttl(t, max_idle_time=t)  # type: ignore[misc]
            except REDIS_DOWN as exc:
                # RQ records the idle state before its reconnecting loop: an outage between rounds
                # lands here; wait for Redis as that loop would
                self.log.warning("Worker %s: Redis unreachable between dequeues: %s", self.name, exc)
                if not wait_for_redis(self.connection, lambda: bool(getattr(self, "_stop_requested", False)),
                                      f"worker {self.name}"):
                    return None
                continue
            if result is not None:
                return result

    @property
    def should_run_maintenance_tasks(self) -> bool:
        if super().should_run_maintenance_tasks:  # type: ignore[misc]
            return True
        due = self._seconds_to_due()
        return due is not None and due <= 0

    def _seconds_to_due(self) -> float | None:
        """Seconds until maintenance has something to do in this worker's queues (<= 0: now): the
        earliest heartbeat expiry of a running execution, or the moment a scheduler lock that is no
        longer refreshed becomes free to take (:meth:`take_over_silent_scheduler_locks`). None when
        nothing is pending or Redis does not answer."""
        conn = self.connection
        full_ms = (SCHEDULER_INTERVAL_S + 60) * 1000
        silent_ms = (SCHEDULER_INTERVAL_S + self.heartbeat_grace) * 1000
        mine = self.scheduler.name if self.scheduler is not None else None
        dues: list[float] = []
        try:
            clock = current_timestamp()  # the clock RQ's registry clean-up compares expiries with
            for queue in self.queues:  # type: ignore[attr-defined]
                first = conn.zrange(queue.started_job_registry.key, 0, 0, withscores=True)
                score = float(first[0][1]) if first else math.inf
                if math.isfinite(score):
                    dues.append(score - clock)
                lock_key = RQScheduler.get_locking_key(queue.name)
                with conn.pipeline(transaction=False) as p:
                    p.get(lock_key)
                    p.pttl(lock_key)
                    holder, left_ms = p.execute()
                if holder is not None and _text(holder) != mine and left_ms >= 0 and \
                        full_ms - left_ms > 2000 * SCHEDULER_INTERVAL_S:  # a live holder refreshes every second
                    dues.append((silent_ms - (full_ms - left_ms)) / 1000)
        except RedisError:
            return None
        return min(dues) if dues else None

    def run_maintenance_tasks(self) -> None:
        # RQ 3.0 restarts a stopped scheduler here even after a warm shutdown was requested
        # (SIGTERM stops the scheduler, the running job ends, maintenance starts a new one),
        # and the worker then hangs joining it. Once stopping, only clean the registries.
        try:
            if getattr(self, "_stop_requested", False):
                self.clean_registries()  # type: ignore[attr-defined]
                self.clean_group_registries()  # type: ignore[attr-defined]
                return
            self.reap_dead_local_peers()
            self.take_over_silent_scheduler_locks()
            self.requeue_stranded_jobs()
            super().run_maintenance_tasks()  # type: ignore[misc]
        except REDIS_DOWN as exc:
            # not marked as done: the next pass (inside the dequeue's backoff loop) tries again
            self.log.warning("Worker %s: maintenance skipped, Redis unreachable: %s", self.name, exc)

    def requeue_stranded_jobs(self) -> None:
        """Put back at the front of its queue a job that a worker took and never started.

        A worker's blocking dequeue moves a job into RQ's intermediate queue; the worker then
        records it as started within milliseconds. A worker whose host went away (machine lost,
        link cut) leaves its dequeue open in Redis until the connection times out, and Redis
        hands it the next job, which nobody starts: RQ's own clean-up fails it as stuck only
        after a minute or more and spends a retry (measured 92 s across hosts). Here a job that
        is still 'queued', in no started registry, and seen in the intermediate queue on two
        passes at least :data:`STRANDED_AFTER_S` apart never ran: it is queued again at the
        front, no retry spent."""
        conn = self.connection
        now = time.time()
        for queue in self.queues:  # type: ignore[attr-defined]
            for raw in conn.lrange(queue.intermediate_queue_key, 0, -1):
                job_id = _text(raw)
                if not job_id or job_id in queue.started_job_registry:
                    continue
                seen_key = f"ibr:stranded-seen:{job_id}"
                if conn.set(seen_key, now, nx=True, ex=int(10 * STRANDED_AFTER_S + 600)):
                    continue  # first sighting: a live worker may be about to start it
                if now - float(_text(conn.get(seen_key)) or now) < STRANDED_AFTER_S:
                    continue
                try:
                    job = Job.fetch(job_id, connection=conn, serializer=self.serializer)
                except NoSuchJobError:
                    conn.lrem(queue.intermediate_queue_key, 0, job_id)
                    continue
                if job.get_status(refresh=False) != JobStatus.QUEUED:
                    continue
                if conn.lrem(queue.intermediate_queue_key, 0, job_id):  # one worker wins the race
                    conn.delete(seen_key)
                    if conn.lpos(queue.key, job_id) is None:
                        queue.enqueue_job(job, at_front=True)
                    self.log.warning("Worker %s: job %s was taken from the %s queue but never started (its "
                                     "worker's host is gone?); queued again at the front", self.name, job_id,
                                     queue.name)

    def take_over_silent_scheduler_locks(self) -> None:
        """Release a queue's scheduler lock whose holder stopped refreshing it, wherever it ran; RQ's
        maintenance that follows in the same pass starts this worker's scheduler on it (at start-up,
        :meth:`_start_scheduler` takes it).

        A live scheduler refreshes its lock every :data:`SCHEDULER_INTERVAL_S` (RQ sets its TTL to
        ``interval + 60`` s each time), so the lock's remaining TTL tells how long its holder has
        been silent, on Redis's clock alone (no clock skew between hosts). The rule is the one for
        abandoned jobs: silent for its refresh period plus ``heartbeat_grace``. A lost host's
        scheduler lock is thus free ~21 s after the loss instead of 61 s, and the retries of the
        jobs it lost (found abandoned ~20-30 s after the loss) are enqueued on time. The check
        and the release are one Lua script, so a holder that refreshes meanwhile keeps its lock; a
        holder that was only silent (a Redis outage longer than the grace) finds its lock taken
        at its next refresh and exits (:class:`DyingScheduler`)."""
        conn = self.connection
        silent_ms = int((SCHEDULER_INTERVAL_S + self.heartbeat_grace) * 1000)
        full_ms = int((SCHEDULER_INTERVAL_S + 60) * 1000)
        script = conn.register_script(_RELEASE_SILENT_LOCK)
        for queue in self.queues:  # type: ignore[attr-defined]
            lock_key = RQScheduler.get_locking_key(queue.name)
            holder = _text(conn.get(lock_key))
            if not holder or (self.scheduler is not None and holder == self.scheduler.name):
                continue
            left_ms = int(script(keys=[lock_key], args=[holder, full_ms, silent_ms]))
            if left_ms != _RELEASED:
                continue
            where = _text(conn.hget(SCHEDULER_KEY_TEMPLATE % holder, "hostname")) or "an unknown host"
            self.log.warning("Worker %s: released the %s scheduler lock of scheduler %s on %s, silent for more "
                             "than %.0f s (host lost?), for a live scheduler to take", self.name, queue.name,
                             holder, where, silent_ms / 1000)

    def reap_dead_local_peers(self) -> None:
        """Release what a worker of this host that no longer exists (SIGKILL, OOM) still holds,
        instead of waiting for it to expire: its scheduler's lock (RQ: up to 61 s, during which
        no scheduler enqueues the retries it scheduled) and its running executions (expiry
        ``job_monitoring_interval + heartbeat_grace``). An execution is only marked expired:
        RQ's own abandoned-job handling of the same maintenance pass then retries or fails it.

        "No longer exists" is decided by its registered hostname being this one and its pid
        being gone, so it holds only where pids are this host's (one machine, one container):
        a registration from elsewhere, or a pid now reused, is left to the expiry."""
        conn = self.connection
        host = socket.gethostname()
        for queue in self.queues:  # type: ignore[attr-defined]
            lock_key = RQScheduler.get_locking_key(queue.name)
            name = _text(conn.get(lock_key))
            if name and _gone_here(conn.hmget(SCHEDULER_KEY_TEMPLATE % name, ["hostname", "pid"]), host) and \
                    release_lock(conn, lock_key, name):
                self.log.warning("Worker %s: released the %s scheduler lock of scheduler %s, whose process on "
                                 "this host is gone", self.name, queue.name, name)
            registry = queue.started_job_registry
            for job_id, execution_id in registry.get_job_and_execution_ids(cleanup=False):
                peer_name = _text(conn.hget(f"rq:execution:{job_id}:{execution_id}", "worker_name"))
                if not peer_name or peer_name == self.name:
                    continue
                peer = conn.hmget(Worker.redis_worker_namespace_prefix + peer_name, ["hostname", "pid"])
                if not _gone_here(peer, host):
                    continue
                entry = f"{job_id}:{execution_id}"
                try:
                    job = Job.fetch(job_id, connection=conn, serializer=self.serializer)
                except NoSuchJobError:
                    conn.zrem(registry.key, entry)
                    continue
                if job.get_status(refresh=False) == JobStatus.QUEUED:
                    # killed between taking the job and starting it: RQ's abandoned-job handling
                    # skips a job that is not 'started' (it would wait in RQ's intermediate queue
                    # for a minute); it never ran, so it goes back to the front, no retry spent
                    if conn.zrem(registry.key, entry):
                        conn.lrem(queue.intermediate_queue_key, 0, job_id)
                        if conn.lpos(queue.key, job_id) is None:
                            queue.enqueue_job(job, at_front=True)
                        self.log.warning("Worker %s: job %s was taken by worker %s, whose process on this host is "
                                         "gone, before it started; queued again at the front", self.name, job_id,
                                         peer_name)
                elif conn.zadd(registry.key, {entry: 1}, xx=True, ch=True):
                    self.log.warning("Worker %s: job %s was run by worker %s, whose process on this host is gone; "
                                     "handled as abandoned now", self.name, job_id, peer_name)

    def _start_scheduler(self, burst: bool = False, logging_level: str | None = "INFO",
                         date_format: str = DEFAULT_LOGGING_DATE_FORMAT,
                         log_format: str = DEFAULT_LOGGING_FORMAT) -> None:
        # RQ's own start-up of its scheduler, with DyingScheduler in place of RQScheduler.
        scheduler = DyingScheduler(
            self.queues,  # type: ignore[attr-defined]
            connection=self.connection,
            logging_level=logging_level if logging_level is not None else self.log.level,
            date_format=date_format,
            log_format=log_format,
            serializer=self.serializer,
        )
        self.scheduler = scheduler
        try:
            self.reap_dead_local_peers()  # a killed predecessor's lock would keep this one idle
            self.take_over_silent_scheduler_locks()  # and so would a lost host's
        except REDIS_DOWN as exc:
            self.log.warning("Worker %s: could not check for dead peers: %s", self.name, exc)
        scheduler.acquire_locks()  # type: ignore[no-untyped-call]
        if not scheduler.acquired_locks:
            return
        if burst:
            try:
                scheduler.register_birth()
                scheduler.enqueue_scheduled_jobs()  # type: ignore[no-untyped-call]
            finally:
                scheduler.release_locks()  # type: ignore[no-untyped-call]
                scheduler.register_death()
        else:
            scheduler.start()

    def get_heartbeat_ttl(self, job: Job, working_time: float = 0.0) -> int:
        interval = int(self.job_monitoring_interval)
        if job.timeout and job.timeout > 0:
            remaining = int(job.timeout - working_time)
            interval = max(1, min(remaining, interval))
        return interval + int(self.heartbeat_grace)


SCHEDULER_INTERVAL_S = 1
"""RQ's scheduler loop period (``RQScheduler(interval=1)``, the default): it refreshes its locks
(TTL ``interval + 60`` s) and enqueues due jobs that often."""

_RELEASED = -1
_RELEASE_SILENT_LOCK = """
-- KEYS[1] = a scheduler lock; ARGV = holder, TTL when refreshed (ms), silence that frees it (ms)
-- returns -1 when released, else the lock's remaining TTL (ms; -2 gone or another holder)
if redis.call('GET', KEYS[1]) ~= ARGV[1] then return -2 end
local left = redis.call('PTTL', KEYS[1])
if left >= 0 and tonumber(ARGV[2]) - left >= tonumber(ARGV[3]) then
    redis.call('DEL', KEYS[1])
    return -1
end
return left
"""

STRANDED_AFTER_S = 5.0
"""How long a job may sit taken but not started before maintenance queues it again (a live worker
starts a job it took within milliseconds)."""


def _text(value: Any) -> str | None:
    return value.decode() if isinstance(value, bytes) else value


def _gone_here(registration: list[Any], host: str) -> bool:
    """True when a (hostname, pid) registration names this host and a pid that does not exist
    or is a zombie (a killed worker's scheduler is reparented, and stays a zombie until the
    host's init reaps it)."""
    hostname, pid = (_text(v) for v in registration)
    if hostname is None or pid is None or hostname != host:
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except (PermissionError, ValueError, OverflowError):
        return False
    try:
        stat = open(f"/proc/{int(pid)}/stat", "rb").read()  # noqa: SIM115 - read at once
    except OSError:
        return False
    return stat[stat.rfind(b")") + 2:stat.rfind(b")") + 3] == b"Z"


def _set_parent_death_signal(sig: int = signal.SIGKILL) -> None:
    """Linux: have the kernel send ``sig`` to this process when its parent dies."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, sig, 0, 0, 0)
    except (OSError, AttributeError):
        log.warning("prctl(PR_SET_PDEATHSIG) unavailable; a horse may outlive a killed worker")


class DyingScheduler(RQScheduler):
    """RQ's scheduler process, tied to its worker and tolerant of Redis outages.

    RQ forks the scheduler from the worker. Stock, a SIGKILLed worker leaves it running as an
    orphan that still holds the worker's scheduler lock and a copy of the worker's Redis
    sockets: Redis keeps the dead worker's blocking dequeue open and hands it the next job,
    which then waits in the intermediate queue until maintenance frees it (measured 88.5 s).
    Here the child asks the kernel to kill it with its parent (``PR_SET_PDEATHSIG``), and a
    Redis outage makes it wait and carry on (its lock is refreshed or re-taken by its next
    heartbeat) instead of exiting."""

    _parent_pid: int = 0

    def heartbeat(self) -> None:
        # RQ drops a lock another scheduler took over (ours was silent longer than the takeover
        # rule allows, e.g. through a long Redis outage) and keeps looping without it until its
        # 10-minute fallback; exiting instead lets the worker start a new scheduler as soon as
        # the lock is free again (RQ's maintenance restarts a scheduler that is not alive).
        had = bool(self._acquired_locks)
        super().heartbeat()  # type: ignore[no-untyped-call]
        if had and not self._acquired_locks:
            self.log.warning("Scheduler %s: its lock was taken over by another scheduler; exiting", self.name)
            self._stop_requested = True

    def start(self) -> Any:
        self._parent_pid = os.getpid()
        return super().start()  # type: ignore[no-untyped-call]

    def work(self) -> None:
        # in the forked child
        _set_parent_death_signal()
        if self._parent_pid and os.getppid() != self._parent_pid:  # the worker died before prctl
            os._exit(0)
        delay = OUTAGE_BACKOFF_FIRST_S
        while True:
            try:
                super().work()  # type: ignore[no-untyped-call]
                return
            except REDIS_DOWN as exc:
                if self._stop_requested:
                    return
                self.log.warning("Scheduler: Redis unreachable (%s); retrying in %.1f s", exc, delay)
                time.sleep(delay)
                delay = min(OUTAGE_BACKOFF_CAP_S, delay * 2)


class BakeWorker(_TunedWorkerMixin, Worker):
    """Forking worker (isolation per job) with the liveness timings above."""

    def _handle_stopped_job(self, job: Job, queue: Queue, execution: Any) -> None:
        # The horse was killed by the cancel's stop command (it never returns to perform_job):
        # observe its run time here, and log the stop at INFO instead of RQ's WARNING.
        started = job.started_at
        demote = _DemoteToInfo("stopped by user")
        self.log.addFilter(demote)
        try:
            super()._handle_stopped_job(job, queue, execution)
        finally:
            self.log.removeFilter(demote)
        if started is not None:
            _observe(job, queue.name, "canceled", max(0.0, (datetime.now(UTC) - started).total_seconds()))

    def main_work_horse(self, job: Job, queue: Queue) -> None:
        parent = os.getppid()
        _set_parent_death_signal()
        if os.getppid() != parent:  # the parent died before prctl took effect
            os._exit(1)
        super().main_work_horse(job, queue)


class RenderWorker(_TunedWorkerMixin, SimpleWorker):
    """In-process worker (warm caches) whose running job keeps a heartbeat from a thread."""

    def execute_job(self, job: Job, queue: Queue) -> None:
        self._current_execution = None
        try:
            execution = self.prepare_execution(job)
            stop = threading.Event()
            beat = threading.Thread(target=self._keep_alive, args=(job, execution, stop),
                                    name="ibr-job-heartbeat", daemon=True)
            beat.start()
            try:
                self.perform_job(job, queue, execution)
            finally:
                stop.set()
                beat.join(timeout=10)
            self.set_state(WorkerStatus.IDLE)
        except REDIS_DOWN as exc:
            self.settle_after_outage(job, queue, self._current_execution, exc)

    def _keep_alive(self, job: Job, execution: Any, stop: threading.Event) -> None:
        started = time.monotonic()
        while not stop.wait(self.job_monitoring_interval):
            elapsed = time.monotonic() - started
            if job.timeout and job.timeout > 0 and elapsed > job.timeout + self.heartbeat_grace:
                self.log.warning("job %s is %.0f s past its %s s timeout and still running (stuck in native "
                                 "code?); heartbeats stop so maintenance treats it as abandoned",
                                 job.id, elapsed - job.timeout, job.timeout)
                return
            try:
                self.maintain_heartbeats(job, execution)
            except RedisError as exc:
                self.log.warning("heartbeat for job %s failed: %s", job.id, exc)


def build_worker(
    queue: QueueName,
    redis: Redis,
    *,
    name: str | None = None,
    maintenance_interval: int = 30,
    job_monitoring_interval: int = 10,
    heartbeat_grace: int = 20,
    worker_ttl: int = 420,
) -> RenderWorker | BakeWorker:
    """The worker for ``queue`` ('render' -> RenderWorker, 'bake' -> BakeWorker), with the
    JSON serializer and :func:`retry_policy` installed."""
    if queue not in QUEUE_NAMES:
        raise ValueError(f"unknown queue {queue!r}; queues are {QUEUE_NAMES}")
    cls: type[RenderWorker | BakeWorker] = RenderWorker if queue == "render" else BakeWorker
    worker = cls(
        [get_queue(redis, queue)],
        name=name,
        connection=redis,
        serializer=JSONSerializer,
        exception_handlers=[retry_policy],
        maintenance_interval=maintenance_interval,
        job_monitoring_interval=job_monitoring_interval,
        worker_ttl=worker_ttl,
    )
    worker.heartbeat_grace = heartbeat_grace
    return worker


LATER_LANE_NICENESS = 10
"""Niceness of the warm-up lanes after the first: the first lane compiles the reference renderer
and then the LDC methods, the kinds a user is likely to ask for first; the others give it the CPU
when both want it (at start-up the API, the workers' imports and both lanes share the cores)."""


def _warm_up_lane_setup(lane: int) -> None:
    _set_parent_death_signal()
    if lane > 0:
        with contextlib.suppress(OSError):
            os.nice(LATER_LANE_NICENESS)


def start_background_warm_up(worker_name: str, redis: Redis) -> list[subprocess.Popen[bytes]]:
    """Start ``python -m workers.warmup --publish worker_name --lanes N --lane i``, one process per
    lane (module docstring, "Warm-up"; ``workers.warmup_steps.lanes_for``: two on two or more cores, as
    numba compiles on one core per process), so the worker takes jobs at once; they die with the
    worker (parent death signal) and share its log output. A lane that cannot be started is
    logged (its kinds compile in their first jobs). Publishes the readiness of a warm-up that has
    not started yet first: a process takes seconds to import the engine before it publishes."""
    from producer.readiness import publish_readiness  # deferred: not needed by ``--healthcheck``
    from workers.warmup_readiness import ReadinessTracker

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    lanes = lanes_for(cores)
    procs = []
    for i, steps in enumerate(lanes):
        with contextlib.suppress(RedisError, OSError):
            publish_readiness(redis, worker_name, ReadinessTracker(steps, worker_name).document(), lane=i)
        cmd = [sys.executable, "-m", "workers.warmup", "--publish", worker_name, "--lanes", str(len(lanes)),
               "--lane", str(i)]
        try:
            procs.append(subprocess.Popen(cmd, stdin=subprocess.DEVNULL,
                                          preexec_fn=functools.partial(_warm_up_lane_setup, i)))  # noqa: PLW1509
        except OSError as exc:
            log.error("warm-up: could not start %s: %s; those kinds compile in their first jobs", cmd, exc)
    log.info("warm-up: started in the background (%d processes, pids %s): compiles or loads the render jobs' "
             "numba kernels, reference and LDC methods in one, relighting and walkthroughs in the other; jobs "
             "are taken meanwhile (a job whose kernels are not ready yet compiles them itself)",
             len(procs), ", ".join(str(p.pid) for p in procs))
    return procs


def stop_background_warm_up(procs: list[subprocess.Popen[bytes]], redis: Redis, worker_name: str) -> None:
    """Stop the background warm-up's processes that still run and withdraw the worker's readiness."""
    from producer.readiness import clear_readiness  # deferred: not needed by ``--healthcheck``

    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
    with contextlib.suppress(RedisError, OSError):
        clear_readiness(redis, worker_name)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m workers.runner", description="Run an ibr-service RQ worker.")
    p.add_argument("--queue", required=True, choices=QUEUE_NAMES, help="queue to work on")
    p.add_argument("--burst", action="store_true", help="exit when the queue is empty")
    p.add_argument("--name", default=None, help="worker name (unique among live workers; default: random)")
    p.add_argument("--max-jobs", type=int, default=None, help="exit after this many jobs")
    p.add_argument("--exit-deadline", type=float, default=EXIT_DEADLINE_S, metavar="S",
                   help="seconds from the end of the work loop to the exit, past which the worker logs "
                        f"its threads' stacks and exits anyway (default {EXIT_DEADLINE_S:.0f})")
    p.add_argument("--maintenance-interval", type=int, default=None, metavar="S",
                   help="seconds between registry clean-ups (default: IBR_MAINTENANCE_INTERVAL_S or 30)")
    p.add_argument("--job-monitoring-interval", type=int, default=None, metavar="S",
                   help="seconds between heartbeats of a running job (default: IBR_JOB_MONITORING_INTERVAL_S or 10)")
    p.add_argument("--heartbeat-grace", type=int, default=None, metavar="S",
                   help="extra seconds before a silent job counts as abandoned (default: IBR_HEARTBEAT_GRACE_S or 20)")
    p.add_argument("--worker-ttl", type=int, default=None, metavar="S", help="worker registration TTL (default 420)")
    p.add_argument("--no-scheduler", action="store_true", help="do not run RQ's scheduler in this worker")
    p.add_argument("--no-warmup", action="store_true",
                   help="render worker: skip the background warm-up of the numba kernels "
                        "(default: IBR_WORKER_WARMUP, on)")
    p.add_argument("--healthcheck", action="store_true",
                   help="exit 0 when a worker of --queue on this host is registered in Redis with a recent "
                        "heartbeat, else 1 (a container health check); starts no worker")
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        settings = Settings()
    except ValidationError as exc:
        print(f"invalid worker settings (IBR_* environment variables):\n{exc}", file=sys.stderr)
        return 2
    redis = redis_from_url(settings.effective_redis_url)
    try:
        redis.ping()
    except (RedisError, OSError) as exc:
        print(f"cannot reach Redis at {settings.effective_redis_url}: {exc}", file=sys.stderr)
        return 3
    if args.healthcheck:
        return healthcheck(redis, args.queue, settings)
    # keep image-sized buffers mapped between jobs (engine/memory.py); inherited by forked horses
    if keep_freed_memory(settings.malloc_keep_mib << 20):
        log.info("malloc: blocks up to 32 MiB from the heap, up to %d MiB of freed memory kept for the next job",
                 settings.malloc_keep_mib)
    name = args.name or uuid4().hex  # RQ's default name, chosen here: the warm-up publishes under it
    warm: list[subprocess.Popen[bytes]] = []
    if args.queue == "render":
        # Compile / load the kernels in the background while taking jobs (module docstring, "Warm-up"),
        # started before this process imports the engine, so their own imports overlap it.
        if settings.worker_warmup and not args.no_warmup:
            warm = start_background_warm_up(name, redis)
        else:
            log.info("warm-up: off (%s); the first jobs compile or load their kernels",
                     "--no-warmup" if args.no_warmup else "IBR_WORKER_WARMUP=false")
        # Import the job module (and the engine) now, so a broken install fails at start-up.
        import workers.jobs.render  # noqa: F401  # deferred on purpose: this queue's jobs only

    else:
        # Import only (no kernel runs in the parent, see the module docstring): forked horses
        # inherit the loaded modules instead of importing numba, Embree and the engine per job.
        from workers.jobs.bake import preload_modules  # deferred on purpose: this queue's jobs only

        preload_modules()
    worker = build_worker(
        args.queue,
        redis,
        name=name,
        maintenance_interval=args.maintenance_interval or settings.maintenance_interval_s,
        job_monitoring_interval=args.job_monitoring_interval or settings.job_monitoring_interval_s,
        heartbeat_grace=args.heartbeat_grace or settings.heartbeat_grace_s,
        worker_ttl=args.worker_ttl or settings.worker_ttl_s,
    )
    worker.ends_by_itself = args.burst or args.max_jobs is not None
    worker.exit_deadline_s = args.exit_deadline
    try:
        worker.work(burst=args.burst, with_scheduler=not args.no_scheduler, logging_level=args.log_level,
                    max_jobs=args.max_jobs)
    finally:
        if args.queue == "render":
            stop_background_warm_up(warm, redis, worker.name)
    if worker.exit_status() != 0:
        # RQ's loop ends on an exception it does not handle (logged above with its traceback):
        # a non-zero status, so the supervisor (ibr up, the container's restart policy) starts
        # a fresh worker instead of taking the exit for a requested stop.
        log.error("worker %s: the work loop ended without a stop request; exiting with status 1", worker.name)
        return 1
    return 0


def healthcheck(redis: Redis, queue: QueueName, settings: Settings) -> int:
    """0 when a live worker of ``queue`` registered from this host has sent a heartbeat within
    ``2 x maintenance_interval + job_monitoring_interval + 30`` seconds (an idle worker beats at
    every dequeue timeout, a busy one with every job heartbeat), else 1 with the reason."""
    import socket

    from rq.utils import now

    limit = 2 * settings.maintenance_interval_s + settings.job_monitoring_interval_s + 30
    host = socket.gethostname()
    ages = []
    for w in Worker.all(connection=redis, queue=get_queue(redis, queue)):
        if w.hostname == host and w.last_heartbeat is not None and not _gone_here([w.hostname, str(w.pid)], host):
            ages.append((now() - w.last_heartbeat).total_seconds())
    if ages and min(ages) <= limit:
        print(f"ok: {queue} worker on {host}, last heartbeat {min(ages):.0f} s ago")
        return 0
    print(f"unhealthy: no {queue} worker on {host} with a heartbeat in the last {limit} s "
          f"({len(ages)} registered)", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
