"""The service on five hosts (network namespaces, tests/fixtures/netns.py): Redis, an S3 server, the
API and two worker hosts, nothing on disk shared but the code and numba's kernel cache
(tests/deployment/cluster.py). Through the API:

(a) a bake spread over both worker hosts, then an LDC render of it;
(b) a worker host taken away mid-bake (its link cut, its processes SIGKILLed) while its scheduler
    holds the bake queue's scheduler lock: the bake finishes on the other host, which takes the
    silent lock over and reruns the lost part once its heartbeat expires;
(c) Redis SIGKILLed and started again mid-job: the job (a render waiting for its bake) completes.

Liveness timings are the fast test ones (heartbeat every 1 s, 2 s grace, maintenance every 1 s), so
a lost host is noticed in ~3-4 s instead of ~30-60 s; scenes are tiny and direct-lit only.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest
from redis import Redis
from rq.scheduler import SCHEDULER_KEY_TEMPLATE, RQScheduler

from producer.queue import redis_from_url
from service.client import ApiError, Client
from tests.deployment.cluster import Cluster, wait_until
from tests.fixtures.netns import Hosts

pytestmark = pytest.mark.slow

SCENE = {
    "name": "hosts",
    "camera": {"type": "perspective", "eye": [0, 1.5, 4], "look_at": [0, 0.5, 0], "width": 48, "height": 32},
    "materials": [{"name": "m", "kd": [0.6, 0.5, 0.4]}, {"name": "floor", "kd": [0.5, 0.5, 0.5]}],
    "objects": [{"type": "sphere", "center": [0, 0.6, 0], "radius": 0.6, "material": "m", "subdivisions": 3},
                {"type": "plane", "material": "floor", "size": [4.0, 4.0]}],
    "lights": [{"type": "point", "position": [1, 3, 2], "intensity": [3.0, 3.0, 3.0]}],
}

FIRST_JOB_S = 600.0
"""The first bake and the first render: with an empty numba cache (a fresh CI machine) their
job processes compile the kernels (minutes); afterwards they load them in seconds."""
RECOVERY_S = 120.0


def bake_params(seed: int) -> dict[str, Any]:
    return {"ldc_resolution": 48, "max_layers": 8, "area_light_samples": 1, "seed": seed, "indirect": {"mode": "off"}}


@pytest.fixture
def cluster(netns_hosts: Hosts) -> Iterator[Cluster]:
    h = netns_hosts
    c = Cluster(h, h.add("redis"), h.add("s3"), h.add("api"), {"w1": h.add("w1"), "w2": h.add("w2")})
    c.start_redis()
    c.start_s3()
    c.wait_redis()
    c.make_bucket()
    c.start_api()
    # w1 first: its bake worker's scheduler holds the bake queue's scheduler lock, which the retry
    # of the part lost with w1 in (b) needs: w2 must take over the lock of the lost host
    c.start_worker("w1", "bake")
    redis = redis_from_url(c.redis_url)
    try:
        wait_until(lambda: scheduler_host(redis, "bake") == "w1", 60, "w1's bake scheduler", c.logs)
        c.start_worker("w2", "bake")
        c.start_worker("w2", "render")
        wait_until(lambda: len(workers_of(redis, "bake")) == 2, 60, "both bake workers", c.logs)
        c.wait_api()
    finally:
        redis.close()
    yield c  # torn down by netns_hosts: every process killed, namespaces deleted


def workers_of(redis: Redis, queue: str) -> set[str]:
    from rq import Worker

    from producer.queue import get_queue

    return {w.name for w in Worker.all(connection=redis, queue=get_queue(redis, queue))}  # type: ignore[arg-type]


def scheduler_host(redis: Redis, queue: str) -> str | None:
    """The hostname of the scheduler holding ``queue``'s scheduler lock (it enqueues due retries)."""
    name = redis.get(RQScheduler.get_locking_key(queue))
    host = redis.hget(SCHEDULER_KEY_TEMPLATE % name.decode(), "hostname") if name else None
    return host.decode() if host else None


def worker_of(redis: Redis, job_id: str) -> str | None:
    name = redis.hget(f"rq:job:{job_id}", "worker_name")
    return name.decode() if name else None


def status_of(redis: Redis, job_id: str) -> str | None:
    s = redis.hget(f"rq:job:{job_id}", "status")
    return s.decode() if s else None


def follow_bake(api: Client, sid: str, key: str, timeout: float, c: Cluster) -> tuple[Any, int]:
    """The bake once it ended (any end state), and how many polls the API answered 503 (Redis away)."""
    deadline = time.monotonic() + timeout
    unavailable = 0
    while True:
        try:
            b = api.get_bake(sid, key)
            if b.state in ("finished", "failed", "canceled", "missing"):
                return b, unavailable
        except ApiError as e:
            if e.status != 503:
                raise
            unavailable += 1
        assert time.monotonic() < deadline, f"bake {key} not done after {timeout} s\n{c.logs()}"
        time.sleep(0.2)


def test_bake_render_host_loss_and_redis_restart_across_hosts(cluster: Cluster, capsys: Any) -> None:
    c = cluster
    redis = redis_from_url(c.redis_url)  # the operator's view of the queue, from outside the hosts
    report: dict[str, Any] = {}
    with Client(c.api_url, timeout=30) as api:
        sid = api.create_scene(SCENE).id

        # (a) a bake over both worker hosts, then a render from it ------------------------------------
        t0 = time.monotonic()
        a = api.bake(sid, bake_params(1))
        done, _ = follow_bake(api, sid, a.key, FIRST_JOB_S, c)
        assert done.state == "finished", (done.error, c.logs())
        report["a_bake_s"] = time.monotonic() - t0
        ran_on = {p.name: worker_of(redis, p.job_id) for p in done.parts}  # type: ignore[arg-type]
        assert set(ran_on.values()) <= {"bake-w1", "bake-w2"}, ran_on
        t0 = time.monotonic()
        r = api.render(sid, method="ldc", bake=bake_params(1), params={"spp": 1})
        man = api.wait_render(r, timeout=FIRST_JOB_S)
        report["a_render_s"] = time.monotonic() - t0
        png = api.download(man.key, "png")
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and worker_of(redis, r.job.id) == "render-w2"  # type: ignore[union-attr]
        report["a_parts_by_worker"] = ran_on

        # (b) w1's host lost while it runs a part of the next bake ------------------------------------
        b = api.bake(sid, bake_params(2))

        def part_on_w1() -> Any:
            st = api.get_bake(sid, b.key)
            return next((p for p in st.parts if p.job_id and status_of(redis, p.job_id) == "started"
                         and worker_of(redis, p.job_id) == "bake-w1"), None)

        victim = wait_until(part_on_w1, 120, "a part of the bake to run on w1", c.logs, interval=0.02)
        t_loss = time.monotonic()
        killed = c.hosts.take_down(c.worker_hosts["w1"])
        done_b, _ = follow_bake(api, sid, b.key, RECOVERY_S, c)
        report["b_recovery_s"] = time.monotonic() - t_loss
        report["b_processes_killed"] = killed
        assert done_b.state == "finished", (done_b.error, c.logs())
        assert worker_of(redis, victim.job_id) == "bake-w2", c.logs()  # the lost part reran on w2
        job = redis.hgetall(f"rq:job:{victim.job_id}")
        report["b_victim"] = victim.name
        report["b_victim_retries_left"] = int(job.get(b"retries_left", b"-1"))
        assert not c.hosts.pids(c.worker_hosts["w1"])
        w2_log = c.procs["bake-w2"].log_path.read_text(errors="replace")
        assert f"Job {victim.job_id}: scheduled for retry" in w2_log  # w2's abandoned-job handling
        assert "on this host is gone" not in w2_log  # w1 is another host: no same-host shortcut
        # w1's scheduler held the bake queue's lock: w2 released it once silent 1 + 2 s and holds it now
        assert "scheduler lock of scheduler" in w2_log and "on w1, silent for more than 3 s" in w2_log, w2_log
        assert scheduler_host(redis, "bake") == "w2"
        assert workers_of(redis, "bake") >= {"bake-w2"}

        # (c) Redis restarted while a render waits for its bake ---------------------------------------
        r3 = api.render(sid, method="ldc", bake=bake_params(3), params={"spp": 1}, missing_bake="bake")
        assert r3.job is not None and r3.bake is not None

        def part_running() -> bool:
            st = api.get_bake(sid, r3.bake.key)  # type: ignore[union-attr]
            return any(p.job_id and status_of(redis, p.job_id) == "started" for p in st.parts)

        wait_until(part_running, 120, "a part of the third bake to run", c.logs, interval=0.02)
        t_fault = time.monotonic()
        report["c_redis_away_s"] = c.restart_redis()
        redis.close()
        redis = redis_from_url(c.redis_url)
        done_c, unavailable = follow_bake(api, sid, r3.bake.key, RECOVERY_S, c)  # type: ignore[union-attr]
        assert done_c.state == "finished", (done_c.error, c.logs())
        man3 = wait_until(lambda: _finished_render(api, r3.artifact_key), RECOVERY_S, "the render after the restart",
                          c.logs, interval=0.2)
        report["c_recovery_s"] = time.monotonic() - t_fault
        report["c_503_polls"] = unavailable
        assert api.download(man3.key, "png")[:8] == b"\x89PNG\r\n\x1a\n"
        assert all(p.alive() for name, p in c.procs.items() if not name.endswith("-w1")), c.logs()

    # nothing was written to a local disk that another host would have needed: no local store anywhere
    for host in c.hosts.hosts.values():
        assert not (host.tmp / "ibr-data" / "store").exists(), host.name
    redis.close()
    with capsys.disabled():
        print(f"\nseveral hosts: {report}")


def _finished_render(api: Client, key: str) -> Any:
    try:
        return api.artifact(key)
    except ApiError as e:
        if e.status in (404, 503):
            return None
        raise
