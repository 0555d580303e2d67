"""Prometheus metrics of the API process (``GET /metrics``).

Counted in the service: HTTP requests by route template and status, request latency,
render cache hits and misses. Read from Redis on each scrape (so they are right whichever
process ran the jobs): jobs per queue and state (RQ's queue and registries, with the jobs
that were canceled on request counted as ``canceled``, not ``failed``, as ``/v1/jobs`` shows
them), and the job-duration histograms ``ibr_job_duration_seconds{queue,method,outcome}``
that the workers observe where each job runs (``producer.status.record_job_duration``):
monotonic counters, so rates and quantiles come from ``histogram_quantile`` as usual.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from typing import cast

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector
from redis import Redis
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from producer.queue import QueueName, queue_depths
from producer.status import failed_and_canceled, job_duration_histograms

__all__ = ["MetricsMiddleware", "ServiceMetrics"]

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
        dur = HistogramMetricFamily(
            "ibr_job_duration_seconds",
            "Run time of jobs, observed by the worker that ran each one (outcome: finished, failed or canceled)",
            labels=["queue", "method", "outcome"],
        )
        conn = self._redis_getter()
        if conn is None:
            up.add_metric([], 0.0)
            return [up]
        try:
            for name, counts in queue_depths(conn).items():
                if counts.get("failed"):
                    failed, canceled = failed_and_canceled(conn, cast(QueueName, name))
                    counts = {**counts, "failed": failed, "canceled": counts.get("canceled", 0) + canceled}
                for state, n in counts.items():
                    if state == "workers":
                        workers.add_metric([name], float(n))
                    else:
                        depth.add_metric([name, state], float(n))
            for labels, (buckets, total) in sorted(job_duration_histograms(conn).items()):
                dur.add_metric(list(labels), buckets, total)
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
