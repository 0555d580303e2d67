"""Prometheus metrics of the API process (``GET /metrics``).

Counted in the service: HTTP requests by route template and status, request latency,
render cache hits and misses. Computed on each scrape from the RQ registries in Redis
(so they are right whichever process ran the jobs): jobs per queue and state, and
durations of the recently finished jobs per kind (the jobs RQ still keeps in its
finished registry, at most ``RECENT_JOBS`` per queue) as gauges: ``max``, ``mean`` and
``p50``/``p90`` over that window. Durations are window statistics, not a monotonic
histogram: an honest view of "how long do jobs take now" without a metrics pipeline
from the workers.
"""

from __future__ import annotations

import logging
import statistics
import time
from collections.abc import Callable, Iterable

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from redis import Redis
from rq.job import Job
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from producer.queue import get_queue, queue_depths

__all__ = ["RECENT_JOBS", "MetricsMiddleware", "ServiceMetrics"]

RECENT_JOBS = 200

log = logging.getLogger("ibr.metrics")


class _QueueCollector(Collector):
    def __init__(self, redis_getter: Callable[[], Redis | None]) -> None:
        self._redis_getter = redis_getter

    def collect(self) -> Iterable[Metric]:
        up = GaugeMetricFamily("ibr_redis_up", "1 when Redis answered this scrape")
        depth = GaugeMetricFamily(
            "ibr_queue_jobs", "Jobs per queue and state (RQ queue and registries)", labels=["queue", "state"]
        )
        workers = GaugeMetricFamily("ibr_queue_workers", "Workers listening on each queue", labels=["queue"])
        dur = GaugeMetricFamily(
            "ibr_job_duration_seconds",
            f"Duration of the most recent finished jobs (up to {RECENT_JOBS} per queue): count, mean, p50, p90, max",
            labels=["kind", "stat"],
        )
        conn = self._redis_getter()
        if conn is None:
            up.add_metric([], 0.0)
            return [up]
        try:
            for name, counts in queue_depths(conn).items():
                for state, n in counts.items():
                    if state == "workers":
                        workers.add_metric([name], float(n))
                    else:
                        depth.add_metric([name, state], float(n))
                q = get_queue(conn, name)  # type: ignore[arg-type]
                ids = q.finished_job_registry.get_job_ids(0, RECENT_JOBS - 1, desc=True, cleanup=False)
                seconds = sorted(
                    (job.ended_at - job.started_at).total_seconds()
                    for job in Job.fetch_many(ids, connection=conn, serializer=q.serializer)
                    if job is not None and job.started_at is not None and job.ended_at is not None
                )
                if seconds:
                    dur.add_metric([name, "count"], float(len(seconds)))
                    dur.add_metric([name, "mean"], statistics.fmean(seconds))
                    dur.add_metric([name, "p50"], seconds[len(seconds) // 2])
                    dur.add_metric([name, "p90"], seconds[min(len(seconds) - 1, int(0.9 * len(seconds)))])
                    dur.add_metric([name, "max"], seconds[-1])
        except Exception as exc:  # a scrape must not fail because Redis is down
            log.warning("metrics: redis unavailable: %s", exc)
            up.add_metric([], 0.0)
            return [up]
        up.add_metric([], 1.0)
        return [up, depth, workers, dur]


class ServiceMetrics:
    """One registry per app (tests build many apps in one process)."""

    def __init__(self, redis_getter: Callable[[], Redis | None]) -> None:
        self.registry = CollectorRegistry(auto_describe=False)
        self.requests = Counter(
            "ibr_http_requests", "HTTP requests", ["method", "route", "status"], registry=self.registry
        )
        self.latency = Histogram(
            "ibr_http_request_duration_seconds",
            "HTTP request latency",
            ["method", "route"],
            registry=self.registry,
            buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60),
        )
        self.render_cache = Counter(
            "ibr_render_cache", "Render requests answered from the artifact cache (hit) or by a job (miss)",
            ["result"], registry=self.registry,
        )
        self.registry.register(_QueueCollector(redis_getter))


class MetricsMiddleware:
    """Counts requests and latency by route template (not raw path: bounded label values)."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = 500
        start = time.perf_counter()

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "<unmatched>"
            method = str(scope.get("method", ""))
            self.metrics.requests.labels(method, template, str(status)).inc()
            self.metrics.latency.labels(method, template).observe(time.perf_counter() - start)
