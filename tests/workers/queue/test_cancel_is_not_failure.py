"""A job canceled on request is not a failure: ``/metrics`` counts it as canceled (as ``/v1/jobs``
shows it), the worker logs it at INFO without a traceback, and the workers observe every job's run
time into the duration histogram that ``/metrics`` exposes (per queue, method and outcome)."""

from __future__ import annotations

import logging
import re

import pytest
from prometheus_client import generate_latest
from redis import Redis

from producer.queue import get_queue
from producer.status import job_public
from service.core.metrics import ServiceMetrics
from workers import runner

JOBS = "tests.workers.queue.jobs_for_tests"


def _metric(text: str, name: str, **labels: str) -> float:
    for line in text.splitlines():
        if line.startswith(name + "{") and all(f'{k}="{v}"' in line for k, v in labels.items()):
            return float(line.rsplit(" ", 1)[1])
    raise AssertionError(f"no {name} {labels} in\n{text}")


def test_cancel_is_counted_and_logged_as_a_cancel(redis_conn: Redis, caplog: pytest.LogCaptureFixture) -> None:
    q = get_queue(redis_conn, "render")
    canceled = [q.enqueue(f"{JOBS}.canceled_while_running", {"seconds": 0.2}, meta={"kind": "render"},
                          job_id=f"render-cancel-{i}") for i in range(2)]
    broken = q.enqueue(f"{JOBS}.broken", {"x": 1}, job_id="render-broken")
    done = q.enqueue(f"{JOBS}.quick", {"request": {"method": "ldc+llf"}}, meta={"kind": "render"},
                     job_id="render-done")
    worker = runner.build_worker("render", redis_conn, name="cancel-test")
    with caplog.at_level(logging.INFO):
        worker.work(burst=True, with_scheduler=False)

    for j in (*canceled, broken, done):
        j.refresh()
    states = {j.id: job_public(j).state for j in (*canceled, broken, done)}
    assert states == {"render-cancel-0": "canceled", "render-cancel-1": "canceled", "render-broken": "failed",
                      "render-done": "finished"}

    # logs: the cancels one INFO line each, no traceback; a real failure still an ERROR with its traceback
    for j in canceled:
        mine = [r for r in caplog.records if j.id in r.getMessage()]
        assert any(r.levelno == logging.INFO and "canceled on request" in r.getMessage() for r in mine), mine
        assert all(r.levelno < logging.WARNING for r in mine), [(r.levelname, r.getMessage()) for r in mine]
        assert not any("Traceback" in r.getMessage() or r.exc_info for r in mine)
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR and "render-broken" in r.getMessage()]
    assert errors and "ValueError: broken on purpose" in errors[0].getMessage()

    text = generate_latest(ServiceMetrics(lambda: redis_conn).registry).decode()
    assert _metric(text, "ibr_queue_jobs", queue="render", state="canceled") == 2
    assert _metric(text, "ibr_queue_jobs", queue="render", state="failed") == 1
    assert _metric(text, "ibr_queue_jobs", queue="render", state="finished") == 1
    # durations: observed by the worker, per queue, method and outcome; cumulative buckets
    assert _metric(text, "ibr_job_duration_seconds_count", queue="render", method="reference",
                   outcome="canceled") == 2
    assert _metric(text, "ibr_job_duration_seconds_sum", queue="render", method="reference",
                   outcome="canceled") >= 0.4
    assert _metric(text, "ibr_job_duration_seconds_bucket", queue="render", method="reference", outcome="canceled",
                   le="0.1") == 0
    assert _metric(text, "ibr_job_duration_seconds_count", queue="render", method="ldc+llf",
                   outcome="finished") == 1
    assert _metric(text, "ibr_job_duration_seconds_count", queue="render", method="broken", outcome="failed") == 1
    buckets = [float(m.group(1)) for m in re.finditer(
        r'ibr_job_duration_seconds_bucket\{le="[^"]+",method="reference",outcome="canceled",queue="render"\} (\S+)',
        text)]
    assert len(buckets) == 15 and buckets == sorted(buckets) and buckets[-1] == 2, buckets

    # a second run adds to the same counters (monotonic, not recomputed from a window)
    q.enqueue(f"{JOBS}.quick", {"request": {"method": "ldc+llf"}}, meta={"kind": "render"}, job_id="render-done-2")
    runner.build_worker("render", redis_conn, name="cancel-test-2").work(burst=True, with_scheduler=False)
    text = generate_latest(ServiceMetrics(lambda: redis_conn).registry).decode()
    assert _metric(text, "ibr_job_duration_seconds_count", queue="render", method="ldc+llf",
                   outcome="finished") == 2
