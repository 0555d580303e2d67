"""The ``ibr`` client commands against the real API (uvicorn in a thread, embedded Redis, no workers):
results alone on stdout, progress and messages on stderr, bad ids exit 2 with a message, upload
errors name the file as the manifest does."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from click.testing import Result
from typer.testing import CliRunner

from service.cli import app as cli_app
from tests.service.api.conftest import small_scene
from tests.service.api.test_datasets import subset

runner = CliRunner()


def ibr(api_url: str, *args: str) -> Result:
    return runner.invoke(cli_app, list(args), env={"IBR_API_URL": api_url, "IBR_API_KEY": ""})


def _dataset_dir(tmp_path: Path, k: int = 3, bad: str | None = None) -> tuple[Path, list[str]]:
    manifest, files = subset(k)
    d = tmp_path / "ds"
    d.mkdir()
    (d / "manifest.json").write_text(json.dumps(manifest))
    for name, data in files.items():
        (d / name).write_bytes(b"this is not an image" if name == bad else data)
    return d, [img["file"] for img in manifest["images"]]


def test_results_alone_on_stdout(api_url: str, tmp_path: Path) -> None:
    d, _ = _dataset_dir(tmp_path)
    r = ibr(api_url, "datasets", "upload", str(d))  # resumable: shows a progress bar
    assert r.exit_code == 0, r.output
    dataset_id = r.stdout.strip()
    assert r.stdout == dataset_id + "\n" and len(dataset_id) == 64  # what DS=$(ibr datasets upload DIR) captures
    assert "images" in r.stderr  # the summary is a message
    r = ibr(api_url, "datasets", "show", r.stdout[:-1])  # "$DS": the shell strips only the trailing newline
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["id"] == dataset_id

    (tmp_path / "scene.json").write_text(json.dumps(small_scene()))
    r = ibr(api_url, "scenes", "add", str(tmp_path / "scene.json"))
    assert r.exit_code == 0, r.output
    assert len(r.stdout) == 65 and r.stdout.endswith("\n")


def test_bad_ids_exit_2_with_a_message(api_url: str) -> None:
    for args, words in [
        (("datasets", "show", "\n" + "a" * 64), "invalid dataset id"),
        (("scenes", "show", "../datasets"), "invalid scene id"),
        (("jobs", "show", "a b"), "invalid job id"),
        (("bakes", "show", "a" * 64, "k/../x"), "invalid bake key"),
        (("datasets", "show", "b" * 64), "404"),  # well-formed, unknown: the API's answer
        (("jobs", "cancel", "no-such-job"), "404"),
    ]:
        r = ibr(api_url, *args)
        assert r.exit_code == 2, (args, r.output)
        assert isinstance(r.exception, SystemExit), (args, r.exception)  # no traceback
        assert words in r.stderr and r.stdout == "", (args, r.stdout, r.stderr)
        assert "Traceback" not in r.output


def test_upload_names_a_bad_file_as_given(api_url: str, tmp_path: Path) -> None:
    bad = subset(3)[0]["images"][1]["file"]
    d, _ = _dataset_dir(tmp_path, bad=bad)
    sha = hashlib.sha256(b"this is not an image").hexdigest()
    for mode in ("--resumable", "--multipart"):
        r = ibr(api_url, "datasets", "upload", str(d), mode)
        assert r.exit_code == 2, (mode, r.output)
        assert f"files.{bad}" in r.stderr, (mode, r.stderr)
        assert sha not in r.output and sha[:8] not in r.output, (mode, r.output)
        assert r.stdout == ""


def test_scenes_list_and_the_client_follow_every_page(api_url: str, tmp_path: Path) -> None:
    from service.client import Client

    ids = []
    for i in range(7):
        (tmp_path / f"s{i}.json").write_text(json.dumps(small_scene(name=f"paged {i}")))
        r = ibr(api_url, "scenes", "add", str(tmp_path / f"s{i}.json"))
        assert r.exit_code == 0, r.output
        ids.append(r.stdout.strip())
    with Client(api_url) as c:
        assert [s.id for s in c.iter_scenes(page_size=3)] == ids
        first = c.list_scenes(limit=5)
        assert [s.id for s in first.items] == ids[:5] and first.next_cursor is not None
        assert [s.id for s in c.list_scenes(limit=5, cursor=first.next_cursor).items] == ids[5:]
        assert c.jobs(limit=3).items == [] and c.jobs(state=["failed"]).next_cursor is None
    r = ibr(api_url, "scenes", "list")
    assert r.exit_code == 0, r.output
    assert [line.split()[0] for line in r.stdout.splitlines()] == ids


def test_render_and_calibrate_name_the_bake_ibr_bake_makes(api_url: str, tmp_path: Path) -> None:
    """``--ldc-resolution`` and ``--indirect-noise`` of ``ibr render`` / ``ibr calibrate`` pick the
    bake that ``ibr bake`` makes with ``--ldc-resolution`` and ``--noise``: the one key."""
    from service.client import Client

    (tmp_path / "scene.json").write_text(json.dumps(small_scene(name="bake options")))
    sid = ibr(api_url, "scenes", "add", str(tmp_path / "scene.json")).stdout.strip()
    r = ibr(api_url, "bake", sid, "--ldc-resolution", "16", "--noise", "0.1")
    assert r.exit_code == 0, r.output
    key = r.stdout.strip()
    r = ibr(api_url, "calibrate", sid, "--ldc-resolution", "16", "--indirect-noise", "0.1", "--bake-missing",
            "--no-wait")
    assert r.exit_code == 0, r.output
    r = ibr(api_url, "render", sid, "--method", "ldc", "--ldc-resolution", "16", "--indirect-noise", "0.1",
            "--bake-missing", "--no-wait")
    assert r.exit_code == 0, r.output
    with Client(api_url) as c:
        bakes = c.list_bakes(sid).items
        assert [b.key for b in bakes] == [key], bakes  # no second bake queued: the same parameters
        assert bakes[0].params.ldc_resolution == 16 and bakes[0].params.indirect.noise == 0.1
    # another noise is another bake; the flag's range is the API's
    r = ibr(api_url, "calibrate", sid, "--ldc-resolution", "16", "--indirect-noise", "0.9", "--no-wait")
    assert r.exit_code == 2 and "noise" in r.stderr, r.output
