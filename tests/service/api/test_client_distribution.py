"""The ``ibr-client`` distribution (clients/python/) installed into a fresh virtual environment:
the wheel built from this checkout with ``--no-deps``, then only the dependencies it declares.
There, numba, Embree (embreex), OpenImageIO, scipy and the server's packages cannot be imported,
while ``ibr --help`` lists the client commands and the commands talk to a live API (uvicorn in a
thread): a scene file with its mesh, a sample scene, a batch, the job list, and the installed
models checked against the live ``/openapi.json``.

pip reads its usual configuration (the machine's wheel directory and index first); the
environment is built once for the module, without a pip of its own: the test process's pip installs
into it (``pip --python``), which skips bootstrapping a pip there (ensurepip). The installed files are
not byte-compiled at install time (``--no-compile``: that compiled every module of numpy, pydantic,
rich, ... and was half of the install's ~13 s); the processes the tests start in the environment
write the byte code of what they import instead (``PYTHONDONTWRITEBYTECODE`` is dropped for them,
else every ``ibr`` would compile its imports from source again)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import venv
from email.parser import Parser
from pathlib import Path
from zipfile import ZipFile

import pytest

REPO = Path(__file__).resolve().parents[3]
CLIENT_DIR = REPO / "clients" / "python"

# A virtual environment and a wheel build: tens of seconds.
pytestmark = pytest.mark.slow


def _env() -> dict[str, str]:
    """The environment without this test process's Python paths (PYTHONPATH points at the checkout), and
    with byte code written (module docstring)."""
    return {k: v for k, v in os.environ.items()
            if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONDONTWRITEBYTECODE")}


def _run(args: list[str | Path], cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(a) for a in args], cwd=cwd, env={**_env(), **env}, capture_output=True, text=True,
                          timeout=600)


@pytest.fixture(scope="module")
def client_venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("ibr-client")
    venv.create(root / "venv", with_pip=False)
    py = root / "venv" / "bin" / "python"
    pip: list[str | Path] = [sys.executable, "-m", "pip", "--python", py]  # this process's pip, on the new env
    r = _run([*pip, "wheel", "--no-deps", "-q", "-w", root / "dist", CLIENT_DIR], cwd=root)
    assert r.returncode == 0, r.stdout + r.stderr
    (wheel,) = (root / "dist").glob("ibr_client-*.whl")
    with ZipFile(wheel) as z:
        meta = Parser().parsestr(z.read(next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))).decode())
    declared = meta.get_all("Requires-Dist") or []
    assert sorted(d.split(">")[0].split("=")[0].strip().lower() for d in declared) == [
        "httpx", "numpy", "pydantic", "rich", "typer"]
    r = _run([*pip, "install", "-q", "--no-compile", "--no-deps", wheel], cwd=root)
    assert r.returncode == 0, r.stdout + r.stderr
    r = _run([*pip, "install", "-q", "--no-compile", *declared], cwd=root)
    assert r.returncode == 0, r.stdout + r.stderr
    return root / "venv"


def test_the_engine_is_not_installed(client_venv: Path) -> None:
    code = """
import importlib.util, json, sys
import ibr_client, ibr_client.cli, ibr_client.schema_check, api_schemas.service, producer.scene_import
absent = ["numba", "llvmlite", "embreex", "OpenImageIO", "scipy", "trimesh", "fastapi", "redis", "rq", "boto3",
          "service", "workers", "engine.raycast", "engine.reference", "producer.renders", "producer.settings"]
print(json.dumps({"found": [m for m in absent if importlib.util.find_spec(m) is not None],
                  "loaded": [m for m in ("numba", "scipy") if m in sys.modules],
                  "client": ibr_client.__file__}))
"""
    r = _run([client_venv / "bin" / "python", "-c", code], cwd=client_venv)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["found"] == [] and out["loaded"] == []
    assert out["client"].startswith(str(client_venv))  # the installed copy, not the checkout


def test_the_client_commands_run_against_a_live_api(client_venv: Path, api_url: str, tmp_path: Path) -> None:
    ibr = client_venv / "bin" / "ibr"
    env = {"IBR_API_URL": api_url, "IBR_API_KEY": ""}
    r = _run([ibr, "--help"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    for command in ("scenes", "render", "calibrate", "batch", "datasets", "jobs", "walkthrough", "relight"):
        assert f" {command} " in r.stdout, command
    for server_command in (" up ", " worker ", " render-local ", " validate "):
        assert server_command not in r.stdout

    pyramid = REPO / "examples" / "scenes" / "pyramid.json"
    r = _run([ibr, "scenes", "add", pyramid], cwd=tmp_path, **env)
    assert r.returncode == 0, r.stderr
    pyramid_id = r.stdout.strip()
    assert len(pyramid_id) == 64
    r = _run([ibr, "scenes", "add", "teapot_glossy"], cwd=tmp_path, **env)  # a sample, with its PLY mesh
    assert r.returncode == 0 and len(r.stdout.strip()) == 64, r.stderr
    r = _run([ibr, "batch", pyramid, REPO / "examples" / "scenes" / "spheres.json", "--spp", "1"], cwd=tmp_path,
             **env)
    assert r.returncode == 0, r.stderr
    r = _run([ibr, "jobs", "list"], cwd=tmp_path, **env)
    assert r.returncode == 0 and r.stdout.count("queued") == 2, r.stdout + r.stderr  # no workers: both queued
    r = _run([ibr, "scenes", "show", pyramid_id], cwd=tmp_path, **env)
    assert r.returncode == 0 and json.loads(r.stdout)["meshes"][0]["path"] == "meshes/pyramid.obj"
    r = _run([ibr, "scenes", "show", "not an id"], cwd=tmp_path, **env)
    assert r.returncode == 2 and "invalid scene id" in r.stderr

    r = _run([client_venv / "bin" / "python", "-m", "ibr_client.schema_check", api_url], cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout == "" and " 0 mismatches" in r.stderr


def test_the_wheel_holds_the_checkouts_files(client_venv: Path) -> None:
    """One source of truth: the installed modules are byte-for-byte the repository's."""
    site = next((client_venv / "lib").glob("python3.*/site-packages"))
    for rel in ("ibr_client/client.py", "ibr_client/cli.py", "api_schemas/service.py", "api_schemas/scene.py",
                "engine/methods.py", "producer/scene_import/gltf.py", "samples/scenes/teapot_glossy.json"):
        assert (site / rel).read_bytes() == (REPO / rel).read_bytes(), rel
    assert not (site / "engine" / "raycast.py").exists() and not (site / "producer" / "__init__.py").exists()
