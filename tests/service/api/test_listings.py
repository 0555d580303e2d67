"""Scene and job listings page through per-owner indexes (producer/listings.py, the job index of
producer/ownership.py): every item exactly once across the pages, in a stable order, never another
key's; stale entries (a job RQ expired or recreated for another key, a deleted or corrupted
scene) are skipped and removed, never a 500; and the time of a page does not grow with the number
of jobs or the size of the scenes (3,000 jobs and a scene at the JSON-document limit present: p99 far below the seconds
a full read takes; the 50 ms goal is measured by ``bench.listings``, see docs/reliability.md).

No workers run here: jobs stay queued, which is all a listing needs."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from redis import Redis

from api_schemas.service import RenderRequest
from producer.ownership import job_index_key
from producer.renders import enqueue_render
from producer.settings import Settings
from producer.store import open_store
from producer.upkeep import INDEX_BUILT_KEY, run_upkeep
from service.core.security import hash_key, owner_of
from tests.service.api.conftest import small_scene

A = {"Authorization": "Bearer alice"}
B = {"Authorization": "Bearer bob"}
ALICE = owner_of(hash_key("alice"))
BOB = owner_of(hash_key("bob"))
CAM = {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0, 0], "width": 8, "height": 8}


@pytest.fixture
def c(make_app: Any) -> Iterator[TestClient]:
    app: FastAPI = make_app(api_keys=[hash_key("alice"), hash_key("bob")])
    with TestClient(app) as client:
        yield client


def _pages(c: TestClient, url: str, headers: dict[str, str], limit: int, **params: str) -> list[list[str]]:
    """The ids of every page of a listing, following next_cursor to the end."""
    pages: list[list[str]] = []
    cursor: str | None = None
    while True:
        r = c.get(url, params={**params, "limit": limit, **({"cursor": cursor} if cursor else {})}, headers=headers)
        assert r.status_code == 200, r.text
        body = r.json()
        pages.append([item["id"] for item in body["items"]])
        cursor = body["next_cursor"]
        if cursor is None:
            return pages
        assert len(pages) < 1000, "the cursor never ends"


def _flat(pages: list[list[str]]) -> list[str]:
    return [i for p in pages for i in p]


def _render(c: TestClient, sid: str, who: dict[str, str], width: int) -> str:
    r = c.post("/v1/renders", json={"scene_id": sid, "camera": {**CAM, "width": width}}, headers=who)
    assert r.status_code == 202, r.text
    return str(r.json()["job"]["id"])


# ------------------------------------------------------------------------------------ jobs


def test_job_pages_hold_every_job_once_newest_first_and_only_the_callers(c: TestClient, redis_conn: Redis) -> None:
    sid_a = c.post("/v1/scenes", json={"scene": small_scene()}, headers=A).json()["id"]
    sid_b = c.post("/v1/scenes", json={"scene": small_scene()}, headers=B).json()["id"]
    assert sid_a == sid_b  # the same content, held by both
    alice = [_render(c, sid_a, A, 8 + i) for i in range(23)]
    bob = [_render(c, sid_b, B, 100 + i) for i in range(5)]
    shared = _render(c, sid_b, B, 8 + 3)  # the same request as one of Alice's: one job, both hold it
    assert shared == alice[3]

    for limit in (1, 4, 7, 23, 100):
        pages = _pages(c, "/v1/jobs", A, limit)
        assert all(len(p) == limit for p in pages[:-1]) and 0 < len(pages[-1]) <= limit
        assert _flat(pages) == alice[::-1]  # newest first, each once, Bob's own never
    assert _flat(_pages(c, "/v1/jobs", B, 2)) == [shared, *bob[::-1]]  # Bob asked for the shared one last

    # a page boundary stays put while new jobs arrive: they show up on a new first page
    first = c.get("/v1/jobs", params={"limit": 10}, headers=A).json()
    newer = _render(c, sid_a, A, 77)
    rest = _flat(_pages_from(c, "/v1/jobs", A, 10, first["next_cursor"]))
    assert [j["id"] for j in first["items"]] + rest == alice[::-1]
    assert c.get("/v1/jobs", params={"limit": 1}, headers=A).json()["items"][0]["id"] == newer

    # the state filter reads the same index
    assert c.post(f"/v1/jobs/{alice[0]}/cancel", headers=A).status_code == 200
    canceled = _flat(_pages(c, "/v1/jobs", A, 5, state="canceled"))
    assert canceled == [alice[0]]
    assert c.get("/v1/jobs", params={"cursor": "not-a-cursor!"}, headers=A).status_code == 422


def _pages_from(c: TestClient, url: str, headers: dict[str, str], limit: int, cursor: str | None) -> list[list[str]]:
    pages: list[list[str]] = []
    while cursor is not None:
        body = c.get(url, params={"limit": limit, "cursor": cursor}, headers=headers).json()
        pages.append([item["id"] for item in body["items"]])
        cursor = body["next_cursor"]
    return pages


def test_expired_and_reassigned_jobs_leave_the_index(c: TestClient, redis_conn: Redis) -> None:
    sid = c.post("/v1/scenes", json={"scene": small_scene()}, headers=A).json()["id"]
    c.post("/v1/scenes", json={"scene": small_scene()}, headers=B)
    jobs = [_render(c, sid, A, 8 + i) for i in range(12)]
    key = job_index_key(ALICE)
    assert redis_conn.zcard(key) == 12

    # RQ's result / failure TTL: the job's hash expires; the index entry stays until a listing meets it
    for jid in jobs[2:9]:
        redis_conn.pexpire(f"rq:job:{jid}", 1)
    time.sleep(0.05)
    assert _flat(_pages(c, "/v1/jobs", A, 2)) == [jobs[11], jobs[10], jobs[9], jobs[1], jobs[0]]
    assert redis_conn.zcard(key) == 5
    # an expired job in the middle of a page boundary: the cursor still moves on
    for jid in jobs[9:11]:
        redis_conn.pexpire(f"rq:job:{jid}", 1)
    time.sleep(0.05)
    assert _flat(_pages(c, "/v1/jobs", A, 1)) == [jobs[11], jobs[1], jobs[0]]

    # Alice cancels her job, Bob asks for the same render: the job is made anew for Bob alone
    assert c.post(f"/v1/jobs/{jobs[1]}/cancel", headers=A).json()["state"] == "canceled"
    assert _render(c, sid, B, 8 + 1) == jobs[1]
    assert c.get(f"/v1/jobs/{jobs[1]}", headers=A).status_code == 404
    assert _flat(_pages(c, "/v1/jobs", A, 10)) == [jobs[11], jobs[0]]
    assert redis_conn.zscore(key, jobs[1]) is None
    assert _flat(_pages(c, "/v1/jobs", B, 10)) == [jobs[1]]


def test_listed_jobs_equal_the_jobs_read_in_full(redis_conn: Redis) -> None:
    """A listing reads a few fields of each job; what it shows equals ``job_public`` of the job
    read whole, in every state (run by a real RQ worker in this process)."""
    from producer.enqueue import enqueue_unique
    from producer.queue import fetch_job, job_retry
    from producer.status import job_public, list_jobs_page
    from workers import runner

    jobs = "tests.workers.queue.jobs_for_tests"
    specs = [("quick", {"request": {"method": "reference"}}), ("broken", {"x": 1}),
             ("canceled_while_running", {"seconds": 0.2}), ("quick", {"n": 2})]
    ids = []
    for i, (func, payload) in enumerate(specs):
        job = enqueue_unique(redis_conn, "render", f"{jobs}.{func}", payload, f"render-listed-{i}", timeout=60,
                             meta={"kind": "render", "owner": ALICE, "progress": {"fraction": 0.0}},
                             retry=job_retry() if func != "broken" else None, description=func, owner=ALICE)
        assert job is not None
        ids.append(job.id)
    runner.build_worker("render", redis_conn, name="listing-test").work(burst=True, with_scheduler=False)
    queued = enqueue_unique(redis_conn, "render", f"{jobs}.quick", {}, "render-listed-q", timeout=60,
                            meta={"kind": "render", "owner": ALICE}, retry=None, description="q", owner=ALICE)
    assert queued is not None
    items, nxt = list_jobs_page(redis_conn, ALICE, limit=10)
    assert nxt is None
    full = [fetch_job(redis_conn, jid) for jid in ["render-listed-q", *ids[::-1]]]
    assert items == [job_public(j) for j in full if j is not None]
    assert {p.state for p in items} == {"queued", "finished", "failed", "canceled"}
    assert list_jobs_page(redis_conn, BOB, limit=10) == ([], None)


def test_jobs_enqueued_before_the_index_are_indexed_once(redis_conn: Redis, tmp_path: Path) -> None:
    """A Redis written before the job indexes: its jobs (with their owners: the one in the job's
    meta, the others in its owners set) are indexed once by the store upkeep, at their creation
    time, and list like any other."""
    from producer.queue import get_queue
    from producer.status import JOB_INDEX_BUILT_KEY, list_jobs_page

    q = get_queue(redis_conn, "render")
    ids = []
    for i in range(5):
        job = q.enqueue("tests.workers.queue.jobs_for_tests.quick", {"i": i}, job_id=f"render-old-{i}",
                        meta={"kind": "render", "owner": ALICE if i != 2 else BOB})
        ids.append(job.id)
        time.sleep(0.002)
    redis_conn.sadd(f"ibr:job-owners:{ids[3]}", BOB)  # Bob asked for one of Alice's too
    assert list_jobs_page(redis_conn, ALICE, limit=10) == ([], None)
    store = open_store(str(tmp_path / "store"))
    assert run_upkeep(store, 3600.0, redis_conn)["jobs_indexed"] == 5
    assert redis_conn.exists(JOB_INDEX_BUILT_KEY)
    assert [j.id for j in list_jobs_page(redis_conn, ALICE, limit=10)[0]] == [ids[4], ids[3], ids[1], ids[0]]
    assert [j.id for j in list_jobs_page(redis_conn, BOB, limit=10)[0]] == [ids[3], ids[2]]
    assert [j.id for j in list_jobs_page(redis_conn, None, limit=2)[0]] == [ids[4], ids[3]]
    assert run_upkeep(store, 3600.0, redis_conn)["jobs_indexed"] == 0  # once


def test_job_listing_with_auth_off_shows_every_job(client: TestClient) -> None:
    sid = client.post("/v1/scenes", json={"scene": small_scene()}).json()["id"]
    jobs = [_render(client, sid, {}, 8 + i) for i in range(6)]
    assert _flat(_pages(client, "/v1/jobs", {}, 4)) == jobs[::-1]


# ------------------------------------------------------------------------------------ scenes


def _scene(c: TestClient, who: dict[str, str], i: int) -> str:
    r = c.post("/v1/scenes", json={"scene": small_scene(name=f"scene {i}")}, headers=who)
    assert r.status_code in (200, 201), r.text
    return str(r.json()["id"])


def test_scene_pages_hold_every_scene_once_oldest_first_and_only_the_callers(c: TestClient) -> None:
    alice = [_scene(c, A, i) for i in range(13)]
    bob = [_scene(c, B, 100 + i) for i in range(4)]
    assert _scene(c, B, 5) == alice[5]  # Bob stores one of Alice's scenes too
    for limit in (1, 5, 13, 1000):
        pages = _pages(c, "/v1/scenes", A, limit)
        assert all(len(p) == limit for p in pages[:-1])
        assert _flat(pages) == alice  # oldest first (when the scene was first stored), once each
    assert _flat(_pages(c, "/v1/scenes", B, 3)) == sorted([*bob, alice[5]], key=[*alice, *bob].index)
    item = c.get("/v1/scenes", params={"limit": 1}, headers=A).json()["items"][0]
    assert item == c.get(f"/v1/scenes/{alice[0]}", headers=A).json()  # the summary is the scene's view

    # deletes between pages: the pages that follow neither repeat nor skip a remaining scene
    first = c.get("/v1/scenes", params={"limit": 4}, headers=A).json()
    assert c.delete(f"/v1/scenes/{alice[6]}", headers=A).status_code == 204
    assert c.delete(f"/v1/scenes/{alice[5]}", headers=A).status_code == 204  # Bob still holds it
    rest = _flat(_pages_from(c, "/v1/scenes", A, 4, first["next_cursor"]))
    assert [s["id"] for s in first["items"]] + rest == [s for s in alice if s not in (alice[5], alice[6])]
    assert alice[5] in _flat(_pages(c, "/v1/scenes", B, 100))
    assert c.get("/v1/scenes", params={"cursor": "../x"}, headers=A).status_code == 422


def test_stale_scene_entries_are_skipped_and_removed(c: TestClient, store_dir: Path) -> None:
    alice = [_scene(c, A, i) for i in range(6)]
    # a document found corrupt is removed by the reader (with its summary); its index entries stay
    doc = store_dir / "scenes" / f"{alice[1]}.json"
    doc.write_bytes(doc.read_bytes().replace(b"scene 1", b"scene X"))
    assert c.get(f"/v1/scenes/{alice[1]}/document", headers=A).status_code >= 400
    assert not doc.exists()
    # a document and summary removed behind the API's back (a crashed delete, an operator)
    (store_dir / "scenes" / f"{alice[3]}.json").unlink()
    (store_dir / "scene-summaries" / f"{alice[3]}.json").unlink()
    # a summary lost alone: written again from the document
    (store_dir / "scene-summaries" / f"{alice[4]}.json").unlink()
    owner_index = next((store_dir / "scene-index" / "owners").iterdir())
    assert len(list(owner_index.iterdir())) == 6
    assert _flat(_pages(c, "/v1/scenes", A, 2)) == [alice[0], alice[2], alice[4], alice[5]]
    assert len(list(owner_index.iterdir())) == 4  # the stale entries are gone
    assert (store_dir / "scene-summaries" / f"{alice[4]}.json").exists()
    # uploading the corrupted scene again stores and lists it again (as stored now: last)
    assert _scene(c, A, 1) == alice[1]
    assert _flat(_pages(c, "/v1/scenes", A, 3)) == [alice[0], alice[2], alice[4], alice[5], alice[1]]


def test_scene_listing_with_auth_off_and_a_store_written_before_the_index(
    client: TestClient, store_dir: Path
) -> None:
    scenes = [_scene(client, {}, i) for i in range(5)]
    assert _flat(_pages(client, "/v1/scenes", {}, 2)) == scenes
    # what a store written before listings read an index holds: documents and owner markers only
    shutil.rmtree(store_dir / "scene-index")
    shutil.rmtree(store_dir / "scene-summaries")
    assert client.get("/v1/scenes").json()["items"] == []
    store = open_store(str(store_dir))
    assert not store.exists(INDEX_BUILT_KEY)
    assert run_upkeep(store, 3600.0)["scenes_indexed"] == 5
    assert store.exists(INDEX_BUILT_KEY)
    assert _flat(_pages(client, "/v1/scenes", {}, 2)) == scenes
    assert run_upkeep(store, 3600.0)["scenes_indexed"] == 0  # once
    empty = open_store(str(store_dir.parent / "empty"))
    assert run_upkeep(empty, 3600.0)["scenes_indexed"] == 0 and empty.list("") == []


# ------------------------------------------------------------------------------------ datasets


def test_dataset_pages_hold_every_dataset_once_and_survive_a_rebuild(c: TestClient, store_dir: Path) -> None:
    from tests.service.api.test_datasets import multipart, subset

    manifest, files = subset(3)

    def post(who: dict[str, str], name: str) -> str:
        r = c.post("/v1/datasets", files=multipart({**manifest, "name": name}, files), headers=who)
        assert r.status_code in (200, 201), r.text
        return str(r.json()["id"])

    alice = [post(A, f"ds {i}") for i in range(7)]
    bob = [post(B, f"bob {i}") for i in range(2)]
    assert post(B, "ds 4") == alice[4]  # Bob holds one of Alice's too (he sent its files)
    for limit in (1, 3, 7, 100):
        assert _flat(_pages(c, "/v1/datasets", A, limit)) == alice
    assert _flat(_pages(c, "/v1/datasets", B, 2)) == [*bob, alice[4]]  # in the order Bob came to hold them
    first = c.get("/v1/datasets", params={"limit": 3}, headers=A).json()
    assert c.delete(f"/v1/datasets/{alice[3]}", headers=A).status_code == 204
    assert c.delete(f"/v1/datasets/{alice[4]}", headers=A).status_code == 204  # Bob still holds it
    rest = _flat(_pages_from(c, "/v1/datasets", A, 3, first["next_cursor"]))
    assert [d["id"] for d in first["items"]] + rest == [d for d in alice if d not in (alice[3], alice[4])]
    assert alice[4] in _flat(_pages(c, "/v1/datasets", B, 10))
    (store_dir / "datasets" / f"{alice[5]}.json").unlink()  # gone behind the API's back: skipped, removed
    remaining = [alice[0], alice[1], alice[2], alice[6]]
    assert _flat(_pages(c, "/v1/datasets", A, 2)) == remaining
    assert c.get("/v1/datasets", params={"cursor": "x"}, headers=A).status_code == 422

    # a store written before the dataset index: built once by the store upkeep, in the same order
    shutil.rmtree(store_dir / "dataset-index")
    for marker in (store_dir / "dataset-owners").rglob("*"):
        if marker.is_file():
            marker.write_bytes(b"")  # markers were empty then
    assert c.get("/v1/datasets", headers=A).json()["items"] == []
    indexed = run_upkeep(open_store(str(store_dir)), 3600.0)["datasets_indexed"]
    assert indexed == 7  # Alice's four, the one both hold, Bob's two
    assert _flat(_pages(c, "/v1/datasets", A, 3)) == remaining
    assert sorted(_flat(_pages(c, "/v1/datasets", B, 3))) == sorted([*bob, alice[4]])


# ------------------------------------------------------------------------------------ latency


def _big_scene(target_mib: float) -> dict[str, Any]:
    """A legal scene of about ``target_mib`` MiB of JSON: one inline mesh (a triangle strip)."""
    n = int(target_mib * 24_000)
    rng = np.random.default_rng(0)
    v = np.round(rng.random((n, 3)), 4).tolist()
    idx = np.arange(n - 2)
    f = np.stack([idx, idx + 1, idx + 2], 1).tolist()
    doc = small_scene(name="big")
    doc["objects"].append({"type": "mesh", "material": "white", "vertices": v, "faces": f})
    return doc


def _p99_ms(c: TestClient, url: str, headers: dict[str, str], n: int) -> tuple[float, float]:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        r = c.get(url, headers=headers)
        times.append(time.perf_counter() - t0)
        assert r.status_code == 200, r.text
    ms = np.array(times) * 1e3
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 99))


@pytest.mark.slow
def test_listing_latency_with_3000_jobs_and_a_scene_at_the_json_limit(c: TestClient, redis_conn: Redis,
                                                                       store_dir: Path) -> None:
    """Listings answer in tens of milliseconds (p99) with 3,000 jobs in Redis and a scene of just
    under ``max_json_bytes`` (8 MiB) in the store (``bench.listings``: 10,000 jobs and a 30 MiB
    scene under a raised limit). (Reading every job and every scene document took seconds.) Run with ``-s`` to see
    the numbers docs/reliability.md records."""
    big = json.dumps({"scene": _big_scene(7.0)}).encode()
    assert 7 * 2**20 < len(big) <= Settings().max_json_bytes
    t0 = time.perf_counter()
    r = c.post("/v1/scenes", content=big, headers={**A, "content-type": "application/json"})
    t_store = time.perf_counter() - t0
    assert r.status_code == 201, r.text[:500]
    big_id = r.json()["id"]
    small = [_scene(c, A, i) for i in range(20)]
    sid = small[0]
    c.post("/v1/scenes", json={"scene": small_scene(name="scene 0")}, headers=B)

    t0 = time.perf_counter()
    for i in range(3_000):  # the producer's own enqueue path (index included), no worker runs them
        who = ALICE if i % 10 else BOB
        enqueue_render(redis_conn, RenderRequest.model_validate(
            {"scene_id": sid, "camera": CAM, "params": {"spp": 1, "seed": i}}), who)
    t_enqueue = time.perf_counter() - t0
    assert redis_conn.zcard(job_index_key(ALICE)) == 2_700

    n = 100
    jobs_first = _p99_ms(c, "/v1/jobs?limit=100", A, n)
    too_many = c.get("/v1/jobs", params={"limit": 1350}, headers=A)  # over the cap of a page
    assert too_many.status_code == 422 and "1000" in too_many.text
    mid = None
    for _ in range(13):  # a cursor deep in Alice's jobs
        body = c.get("/v1/jobs", params={"limit": 100, **({"cursor": mid} if mid else {})}, headers=A).json()
        mid = body["next_cursor"]
    jobs_deep = _p99_ms(c, f"/v1/jobs?limit=100&cursor={mid}", A, n)
    jobs_bob = _p99_ms(c, "/v1/jobs?limit=100", B, n)
    scenes = _p99_ms(c, "/v1/scenes?limit=100", A, n)
    listed = [s["id"] for s in c.get("/v1/scenes", headers=A).json()["items"]]
    assert listed == [big_id, *small]
    print(f"\nstore a {len(big) / 2**20:.1f} MiB scene: {t_store:.1f} s; enqueue 3,000 renders: {t_enqueue:.1f} s")
    for what, (p50, p99) in (("GET /v1/jobs?limit=100 (2,700 of the key's jobs)", jobs_first),
                             ("GET /v1/jobs?limit=100&cursor=<after 1,300>", jobs_deep),
                             ("GET /v1/jobs?limit=100 (another key, 300 jobs)", jobs_bob),
                             ("GET /v1/scenes?limit=100 (21 scenes, one of 7.3 MiB)", scenes)):
        print(f"{what}: p50 {p50:.1f} ms, p99 {p99:.1f} ms over {n} requests")
    # Reading every job or scene document took 1.6-2.9 s a request here; an index read takes ~10 ms
    # on a quiet machine. The bounds leave room for a loaded CI machine, where one request in a hundred
    # can wait a quarter of a second for a core (p50 14.5 ms, p99 274 ms in one such run; timings are
    # the benchmark's business: bench.listings), and still fail any listing that reads everything.
    for p50, p99 in (jobs_first, jobs_deep, jobs_bob, scenes):
        assert p50 < 250.0 and p99 < 1000.0
