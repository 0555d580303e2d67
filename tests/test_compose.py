"""docker-compose.yml is checked by docker-compose itself (no Docker engine here to run it)."""

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(shutil.which("docker-compose") is None, reason=".ci/run installs docker-compose")
def test_compose_file_is_valid():
    r = subprocess.run(["docker-compose", "-f", str(ROOT / "docker-compose.yml"), "config", "-q"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_dockerfile_copies_every_package():
    text = (ROOT / "Dockerfile").read_text()
    for pkg in ("api_schemas", "engine", "workers", "service", "samples"):
        assert f"COPY {pkg} {pkg}" in text
