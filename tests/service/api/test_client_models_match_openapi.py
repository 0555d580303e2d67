"""The client's models (``api_schemas``, as the ``ibr-client`` distribution ships them) against the
app's own ``/openapi.json``: every model the server documents that the client has a model for,
field by field (names, required, types), every model the client reads answers with, and every
request body. A server whose routes document another model than the client reads, or a field
that differs, fails here (``ibr_client.schema_check``)."""

from __future__ import annotations

import copy
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import create_model

from ibr_client.schema_check import CLIENT_MODELS, client_models, model_drift


@pytest.fixture
def openapi(client: TestClient) -> dict[str, Any]:
    r = client.get("/openapi.json")
    assert r.status_code == 200
    doc: dict[str, Any] = r.json()
    return doc


def test_the_client_models_match_the_live_openapi(openapi: dict[str, Any]) -> None:
    assert model_drift(openapi) == []
    compared = {k.split("-")[0] for k in openapi["components"]["schemas"]} & set(client_models())
    # every answer the client reads and the request bodies of renders, batches, bakes, walkthroughs
    assert set(CLIENT_MODELS) - {"DatasetManifest", "MeshFileObject", "Scene"} <= compared
    assert {"ScenePublic", "RenderRequest", "BatchRequest", "BakeRequest", "WalkthroughRequest",
            "RenderPublic", "JobPublic", "Problem"} <= compared
    assert len(compared) >= 50


def test_drift_is_found_field_by_field(openapi: dict[str, Any]) -> None:
    schemas = openapi["components"]["schemas"]
    renamed = copy.deepcopy(openapi)
    props = renamed["components"]["schemas"]["ScenePublic"]["properties"]
    props["n_lamps"] = props.pop("n_lights")
    assert model_drift(renamed) == [
        "ScenePublic.n_lamps: the server has this field, the client's model does not",
        "ScenePublic.n_lights: the client's model has this field, the server's does not",
    ]

    retyped = copy.deepcopy(openapi)
    retyped["components"]["schemas"]["JobPublic"]["properties"]["progress"] = {"type": "number"}
    (line,) = model_drift(retyped)
    assert line.startswith("JobPublic.progress: the server types it {'type': 'number'}, the client")

    required = copy.deepcopy(openapi)
    name = next(k for k in schemas if k.split("-")[0] == "RenderRequest")
    required["components"]["schemas"][name]["required"] = ["scene_id", "method"]
    assert any(p.startswith(f"{name}: required fields differ") for p in model_drift(required))

    missing = copy.deepcopy(openapi)
    del missing["components"]["schemas"]["BatchPublic"]
    assert "BatchPublic: the client reads this model, the server documents no such model" in model_drift(missing)


def test_a_client_model_with_another_field_is_found(openapi: dict[str, Any]) -> None:
    models = client_models()
    models["JobPublic"] = create_model("JobPublic", __base__=models["JobPublic"], priority=(int, 0))
    assert model_drift(openapi, models) == [
        "JobPublic.priority: the client's model has this field, the server's does not"]
