"""Tenant isolation where content is shared, with two API keys (no workers: jobs stay queued).

Content is stored once however many keys send it, but each key sees only what it sent or asked
for itself: knowing a hash grants nothing (404, as for content that does not exist), a manifest
naming another key's files does not commit until this key has sent them, and a bake or a job
that both keys hold is deleted or canceled only when both have let go."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from tests.service.api.conftest import small_scene
from tests.service.api.test_datasets import multipart, sha, subset, with_shas

A = {"Authorization": "Bearer alice"}
B = {"Authorization": "Bearer bob"}
BAKE = {"ldc_resolution": 24, "max_layers": 8, "area_light_samples": 1, "indirect": {"mode": "off"}}


@pytest.fixture
def c(make_app: Any) -> Iterator[TestClient]:
    from service.core.security import hash_key

    app: FastAPI = make_app(api_keys=[hash_key("alice"), hash_key("bob")])
    with TestClient(app) as client:
        yield client


def _alice_dataset(c: TestClient) -> tuple[dict[str, Any], dict[str, bytes], str]:
    manifest, files = subset(3)
    r = c.post("/v1/datasets", files=multipart(manifest, files), headers=A)
    assert r.status_code == 201, r.text
    return manifest, files, str(r.json()["id"])


def test_an_upload_is_visible_only_to_the_key_that_sent_it(c: TestClient) -> None:
    _, files, _ = _alice_dataset(c)
    name, data = sorted(files.items())[0]
    h = sha(data)
    assert c.get(f"/v1/datasets/uploads/{h}", headers=A).status_code == 200
    r = c.get(f"/v1/datasets/uploads/{h}", headers=B)
    assert r.status_code == 404, r.text  # same answer as for a hash nobody sent
    assert c.get(f"/v1/datasets/uploads/{'0' * 64}", headers=B).status_code == 404
    # Bob proves possession by sending the bytes: 201 for him (stored once underneath), then 200
    r = c.put(f"/v1/datasets/uploads/{h}", content=data, headers=B)
    assert r.status_code == 201 and r.json()["sha256"] == h, r.text
    assert c.get(f"/v1/datasets/uploads/{h}", headers=B).status_code == 200
    assert c.put(f"/v1/datasets/uploads/{h}", content=data, headers=B).status_code == 200
    # wrong bytes under the hash prove nothing
    other = files[sorted(files)[1]]
    r = c.put(f"/v1/datasets/uploads/{sha(other)}", content=data, headers=B)
    assert r.status_code == 422 and c.get(f"/v1/datasets/uploads/{sha(other)}", headers=B).status_code == 404


def test_a_manifest_naming_another_keys_files_does_not_commit(c: TestClient) -> None:
    manifest, files, did = _alice_dataset(c)
    full = with_shas(manifest, files)
    r = c.post("/v1/datasets", json=full, headers=B)
    assert r.status_code == 200, r.text
    status = r.json()
    assert status["dataset_id"] == did and status["state"] == "pending"
    assert {m["sha256"] for m in status["missing"]} == {sha(d) for d in files.values()} and status["received"] == 0
    r = c.post(f"/v1/datasets/{did}/commit", headers=B)
    assert r.status_code == 409, r.text
    assert "has not been uploaded" in r.text
    assert c.get(f"/v1/datasets/{did}", headers=B).status_code == 404
    # multipart with the manifest only, naming files by sha256: the shortcut for files received earlier
    # applies only to files Bob sent himself
    r = c.post("/v1/datasets", files=multipart(full, {}), headers=B)
    assert r.status_code == 422 and "no file part named" in r.text, r.text
    assert c.get(f"/v1/datasets/{did}", headers=B).status_code == 404
    # once Bob has sent every file he joins the dataset (one document underneath)
    for data in files.values():
        assert c.put(f"/v1/datasets/uploads/{sha(data)}", content=data, headers=B).status_code == 201
    r = c.post(f"/v1/datasets/{did}/commit", headers=B)
    assert r.status_code == 200 and r.json()["id"] == did, r.text
    assert c.get(f"/v1/datasets/{did}", headers=B).status_code == 200
    assert len(c.get("/v1/datasets", headers=B).json()["items"]) == 1


def test_dataset_files_are_not_readable_through_a_hash_alone(c: TestClient) -> None:
    """Bob knows the hashes of Alice's files (not the bytes): every way to a dataset naming them
    that he could then read the files through is closed."""
    manifest, files, did = _alice_dataset(c)
    name = manifest["images"][0]["file"]
    h = sha(files[name])
    r = c.get(f"/v1/datasets/{did}/files/{h}", headers=A)
    assert r.status_code == 200 and r.content == files[name]
    full = with_shas(manifest, files)
    c.post("/v1/datasets", json=full, headers=B)
    c.post(f"/v1/datasets/{did}/commit", headers=B)
    c.post("/v1/datasets", files=multipart(full, {}), headers=B)
    mine = {**full, "name": "bob's own manifest"}  # another dataset id, same files
    r = c.post("/v1/datasets", json=mine, headers=B)
    c.post(f"/v1/datasets/{r.json()['dataset_id']}/commit", headers=B)
    assert c.get("/v1/datasets", headers=B).json()["items"] == []
    for dataset in (did, r.json()["dataset_id"]):
        assert c.get(f"/v1/datasets/{dataset}/files/{h}", headers=B).status_code == 404


def _shared_scene(c: TestClient) -> str:
    sids = {c.post("/v1/scenes", json={"scene": small_scene()}, headers=who).json()["id"] for who in (A, B)}
    assert len(sids) == 1  # identical content: one scene, two owners
    return sids.pop()


def test_a_bake_is_deleted_only_when_its_last_holder_lets_go(c: TestClient) -> None:
    sid = _shared_scene(c)
    r = c.post(f"/v1/scenes/{sid}/bakes", json=BAKE, headers=A)
    assert r.status_code == 202, r.text
    key = r.json()["key"]
    url = f"/v1/scenes/{sid}/bakes/{key}"
    # Bob shares the scene but never asked for this bake: he neither sees nor deletes it
    assert c.get(url, headers=B).status_code == 404
    assert c.get(f"/v1/scenes/{sid}/bakes", headers=B).json()["items"] == []
    assert c.delete(url, headers=B).status_code == 404
    assert c.get(url, headers=A).status_code == 200
    # Bob asks for the same bake: it is shared; his delete lets go of his hold only
    assert c.post(f"/v1/scenes/{sid}/bakes", json=BAKE, headers=B).json()["key"] == key
    assert c.get(url, headers=B).status_code == 200
    assert c.delete(url, headers=B).status_code == 204
    assert c.get(url, headers=B).status_code == 404
    assert c.get(url, headers=A).status_code == 200
    assert [b["key"] for b in c.get(f"/v1/scenes/{sid}/bakes", headers=A).json()["items"]] == [key]
    # Alice is the last holder: her delete is the real one (409 while its jobs are queued)
    assert c.delete(url, headers=A).status_code == 409
    assert c.get(url, headers=A).status_code == 200
    job = f"bake-{key}"
    assert c.post(f"/v1/jobs/{job}/cancel", headers=A).json()["state"] == "canceled"
    assert c.delete(url, headers=A).status_code == 204
    assert c.get(url, headers=A).status_code == 404


def test_a_shared_job_is_canceled_only_when_every_owner_canceled_it(c: TestClient) -> None:
    sid = _shared_scene(c)
    req = {"scene_id": sid, "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0],
                                       "fov_y_deg": 40, "width": 16, "height": 12}}
    ja = c.post("/v1/renders", json=req, headers=A).json()["job"]["id"]
    jb = c.post("/v1/renders", json=req, headers=B).json()["job"]["id"]
    assert ja == jb  # identical requests share one job
    r = c.post(f"/v1/jobs/{ja}/cancel", headers=B)
    assert r.status_code == 200 and r.json()["state"] == "queued", r.text  # Bob let go; Alice still waits
    assert c.get(f"/v1/jobs/{ja}", headers=A).json()["state"] == "queued"
    # Bob asks again: attached again, so Alice's cancel alone does not end it either
    assert c.post("/v1/renders", json=req, headers=B).json()["job"]["id"] == ja
    assert c.post(f"/v1/jobs/{ja}/cancel", headers=A).json()["state"] == "queued"
    assert c.post(f"/v1/jobs/{ja}/cancel", headers=B).json()["state"] == "canceled"
    assert c.get(f"/v1/jobs/{ja}", headers=A).json()["state"] == "canceled"
    assert c.post(f"/v1/jobs/{ja}/cancel", headers=A).status_code == 409  # ended


def test_the_first_owner_of_a_job_is_one_owner_among_others(c: TestClient) -> None:
    """The key a job's meta names (who enqueued it) lets go like any other."""
    sid = _shared_scene(c)
    req = {"scene_id": sid, "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0],
                                       "fov_y_deg": 40, "width": 16, "height": 14}}
    job = c.post("/v1/renders", json=req, headers=A).json()["job"]["id"]
    assert c.post("/v1/renders", json=req, headers=B).json()["job"]["id"] == job
    assert c.post(f"/v1/jobs/{job}/cancel", headers=A).json()["state"] == "queued"
    assert c.get(f"/v1/jobs/{job}", headers=B).json()["state"] == "queued"
    assert c.post(f"/v1/jobs/{job}/cancel", headers=B).json()["state"] == "canceled"


def test_an_environment_map_needs_its_bytes_too(c: TestClient) -> None:
    """Bob stores the same dataset (he sent every file, so he joins it) but names Alice's
    environment map by its hash only: refused as not uploaded, as for a hash nobody sent."""
    manifest, files, did = _alice_dataset(c)
    r = c.post("/v1/datasets", files=multipart(manifest, files), headers=B)
    assert r.status_code == 200 and r.json()["id"] == did, r.text  # stored already: Bob joins it
    relight = {"dataset_id": did, "lights": [{"type": "environment", "image_sha256": "a" * 64}]}
    r = c.post("/v1/relights", json=relight, headers=B)
    assert r.status_code == 422 and "not uploaded" in r.text, r.text
    more, more_files = subset(4)
    alice_env = more_files[more["images"][3]["file"]]  # a file of Alice's that Bob never sent
    assert c.put(f"/v1/datasets/uploads/{sha(alice_env)}", content=alice_env, headers=A).status_code == 201
    relight["lights"] = [{"type": "environment", "image_sha256": sha(alice_env)}]
    r = c.post("/v1/relights", json=relight, headers=B)
    assert r.status_code == 422 and "not uploaded" in r.text, r.text
    r = c.post("/v1/relights", json=relight, headers=A)
    assert r.status_code == 409 and "not baked" in r.text, r.text  # past the file check: the bake is next


def test_the_last_scene_owner_clears_the_bake_holders(c: TestClient, store_dir: Any) -> None:
    sid = _shared_scene(c)
    key = c.post(f"/v1/scenes/{sid}/bakes", json=BAKE, headers=A).json()["key"]
    assert c.post(f"/v1/scenes/{sid}/bakes", json=BAKE, headers=B).json()["key"] == key
    for who in (A, B):
        c.post(f"/v1/jobs/bake-{key}/cancel", headers=who)
    assert c.get(f"/v1/jobs/bake-{key}", headers=A).json()["state"] == "canceled"
    markers = store_dir / "bake-owners" / key
    assert len(list(markers.iterdir())) == 2
    assert c.delete(f"/v1/scenes/{sid}", headers=B).status_code == 204
    assert c.get(f"/v1/scenes/{sid}/bakes/{key}", headers=A).status_code == 200  # Alice still has both
    assert c.delete(f"/v1/scenes/{sid}", headers=A).status_code == 204
    assert not markers.exists() or not list(markers.iterdir())


def test_a_bake_queued_by_a_render_is_held_by_the_keys_waiting_for_it(c: TestClient) -> None:
    sid = _shared_scene(c)
    req = {"scene_id": sid, "method": "ldc", "bake": BAKE, "missing_bake": "bake"}
    ra = c.post("/v1/renders", json=req, headers=A)
    assert ra.status_code == 202 and ra.json()["bake"] is not None, ra.text
    key = ra.json()["bake"]["key"]
    url = f"/v1/scenes/{sid}/bakes/{key}"
    assert c.get(url, headers=A).status_code == 200
    assert c.get(url, headers=B).status_code == 404  # Bob has not asked for anything yet
    rb = c.post("/v1/renders", json=req, headers=B)
    assert rb.status_code == 202 and rb.json()["bake"]["key"] == key, rb.text
    assert c.get(url, headers=B).status_code == 200  # his render waits for it: he follows it
    assert [b["key"] for b in c.get(f"/v1/scenes/{sid}/bakes", headers=B).json()["items"]] == [key]
    assert c.delete(url, headers=B).status_code == 204  # lets go of the bake (and of its job) only
    assert c.get(url, headers=B).status_code == 404 and c.get(url, headers=A).status_code == 200
    assert c.get(f"/v1/jobs/bake-{key}", headers=A).json()["state"] == "queued"  # still Alice's
