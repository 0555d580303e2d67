"""docker-compose.yml is checked by docker-compose itself (no Docker engine here to run it)."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(not os.environ.get("CI") and shutil.which("docker-compose") is None,
                    reason=".ci/run installs docker-compose (under CI a missing one fails)")
def test_compose_file_is_valid():
    r = subprocess.run(["docker-compose", "-f", str(ROOT / "docker-compose.yml"), "config", "-q"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_dockerfile_copies_every_package():
    text = (ROOT / "Dockerfile").read_text()
    for pkg in ("api_schemas", "engine", "producer", "workers", "service", "samples"):
        assert f"COPY {pkg} {pkg}" in text


def test_compose_has_the_service_stack():
    import yaml

    doc = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = doc["services"]
    for name in ("redis", "minio", "api", "bake-worker", "render-worker"):
        assert name in services, name
    assert "--appendonly" in services["redis"]["command"]  # persistence on (docs/hard-cases.md #22)
    assert services["bake-worker"]["command"] == ["worker", "--queue", "bake"]
    assert services["render-worker"]["command"] == ["worker", "--queue", "render"]
    env = doc["x-ibr-env"]
    assert env["IBR_STORE_URL"].startswith("s3://") and env["IBR_S3_ENDPOINT_URL"] == "http://minio:9000"


def test_compose_restarts_services_and_checks_worker_health():
    """Long-running services come back when they exit; workers report health from Redis
    (``python -m workers.runner --healthcheck``, exercised in tests/workers/queue/test_outages.py)."""
    import yaml

    services = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    for name in ("redis", "minio", "api", "bake-worker", "render-worker"):
        assert services[name].get("restart") in ("unless-stopped", "always"), name
        assert "healthcheck" in services[name], name
    assert "restart" not in services["minio-init"]  # a one-shot job
    for queue in ("bake", "render"):
        test = services[f"{queue}-worker"]["healthcheck"]["test"]
        assert test[:4] == ["CMD", "python", "-m", "workers.runner"] and "--healthcheck" in test
        assert test[test.index("--queue") + 1] == queue
