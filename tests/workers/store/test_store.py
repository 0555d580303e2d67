"""The object-store contract, run on both backends (local directory, S3 via moto's server),
plus each backend's own failure modes: atomic local writes under injected faults, an
unreachable or silent S3 endpoint (docs/hard-cases.md #25)."""

from __future__ import annotations

import errno
import os
import socket
import stat
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from producer.store import (
    LocalStore,
    NotFound,
    ObjectStore,
    StoreError,
    StoreUnavailable,
    open_store,
    validate_key,
    validate_prefix,
)
from producer.store.s3 import S3Store

BAD_KEYS = [
    "",
    "/abs",
    "a//b",
    "a/",
    "..",
    "../x",
    "a/../b",
    "./a",
    "a/./b",
    "a b",
    "a\\b",
    "C:\\..\\x",
    "x\x00y",
    "caf\u00e9",
    "a~b",
    "a" * 1025,
]


def _files_under(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file() or p.is_symlink())


# ------------------------------------------------------------------------------ key validation


def test_validate_key_accepts_our_key_shapes() -> None:
    for key in ["blobs/" + "a" * 64, "scenes/x.json", "artifacts/k/manifest.json", "a-b_c.D/E.F", "a" * 1024, ".x"]:
        assert validate_key(key) == key


@pytest.mark.parametrize("key", BAD_KEYS)
def test_validate_key_rejects(key: str) -> None:
    with pytest.raises(ValueError, match="invalid object key"):
        validate_key(key)


@pytest.mark.parametrize("prefix", ["", "a", "a/", "a/b", "artifacts/ab"])
def test_validate_prefix_accepts(prefix: str) -> None:
    assert validate_prefix(prefix) == prefix


@pytest.mark.parametrize("prefix", ["/", "/a", "a//", "../", "a/../", "a b/", "a//b/"])
def test_validate_prefix_rejects(prefix: str) -> None:
    with pytest.raises(ValueError):
        validate_prefix(prefix)


# ------------------------------------------------------------------------------ the contract, both backends


def test_store_implements_protocol(any_store: ObjectStore) -> None:
    assert isinstance(any_store, ObjectStore)


def test_put_get_roundtrip_and_overwrite(any_store: ObjectStore) -> None:
    data = bytes(range(256)) * 5
    any_store.put_bytes("a/b/c.bin", data)
    assert any_store.get_bytes("a/b/c.bin") == data
    any_store.put_bytes("a/b/c.bin", b"second", "text/plain")
    assert any_store.get_bytes("a/b/c.bin") == b"second"
    any_store.put_bytes("empty", b"")
    assert any_store.get_bytes("empty") == b""
    assert any_store.exists("empty")


def test_missing_key_is_not_found(any_store: ObjectStore) -> None:
    with pytest.raises(NotFound):
        any_store.get_bytes("no/such/key")
    with pytest.raises(NotFound):
        any_store.open_stream("no/such/key")  # raised by the call itself, before any chunk
    assert not any_store.exists("no/such/key")
    any_store.put_bytes("dir/file", b"x")
    with pytest.raises(NotFound):
        any_store.get_bytes("dir")  # a "directory" is not an object
    assert not any_store.exists("dir")
    assert not issubclass(NotFound, StoreUnavailable)


def test_exists_and_idempotent_delete(any_store: ObjectStore) -> None:
    any_store.put_bytes("k/1", b"1")
    assert any_store.exists("k/1")
    any_store.delete("k/1")
    assert not any_store.exists("k/1")
    with pytest.raises(NotFound):
        any_store.get_bytes("k/1")
    any_store.delete("k/1")  # again: no error
    any_store.delete("never/was")


def test_list_sorted_by_string_prefix(any_store: ObjectStore) -> None:
    keys = ["b/2", "a/b/c", "a/bc", "a/b/a", "a/x/y/z", "ab", "c"]
    for k in keys:
        any_store.put_bytes(k, k.encode())
    assert any_store.list("") == sorted(keys)
    assert any_store.list("a/") == ["a/b/a", "a/b/c", "a/bc", "a/x/y/z"]
    assert any_store.list("a/b") == ["a/b/a", "a/b/c", "a/bc"]
    assert any_store.list("a/b/") == ["a/b/a", "a/b/c"]
    assert any_store.list("a") == ["a/b/a", "a/b/c", "a/bc", "a/x/y/z", "ab"]
    assert any_store.list("zzz/") == []
    assert any_store.list("c/") == []  # "c" is an object, not a directory
    any_store.delete("a/b/c")
    assert any_store.list("a/b/") == ["a/b/a"]


def test_open_stream_yields_bounded_chunks(any_store: ObjectStore) -> None:
    data = os.urandom(10_000)
    any_store.put_bytes("big", data)
    chunks = list(any_store.open_stream("big", chunk=3000))
    assert b"".join(chunks) == data
    assert len(chunks) == 4
    assert max(len(c) for c in chunks) <= 3000
    with pytest.raises(ValueError):
        any_store.open_stream("big", chunk=0)


@pytest.mark.parametrize("key", ["", "../x", "a//b", "x\x00y", "C:\\..\\x", "a/../../b"])
def test_every_method_validates_keys(any_store: ObjectStore, key: str) -> None:
    calls: list[Callable[[], Any]] = [
        lambda: any_store.put_bytes(key, b"x"),
        lambda: any_store.get_bytes(key),
        lambda: any_store.exists(key),
        lambda: any_store.delete(key),
        lambda: any_store.open_stream(key),
    ]
    for call in calls:
        with pytest.raises(ValueError):
            call()
    with pytest.raises(ValueError):
        any_store.list("../")
    assert any_store.list("") == []


def test_check_passes_on_a_healthy_store(any_store: ObjectStore) -> None:
    any_store.check()
    assert any_store.list("") == []  # the probe leaves nothing behind


def test_second_writer_of_a_key_succeeds(any_store: ObjectStore) -> None:
    data = os.urandom(5000)
    any_store.put_bytes("blobs/same", data)
    any_store.put_bytes("blobs/same", data)
    assert any_store.get_bytes("blobs/same") == data
    assert any_store.list("") == ["blobs/same"]


def test_local_concurrent_writers_of_one_key_all_succeed(local_store: LocalStore) -> None:
    # Threads on LocalStore only: S3 PUTs are atomic by the service's contract, but moto's
    # server is not thread-safe for concurrent PUTs of one key (500 "I/O operation on
    # closed file" while it computes the ETag of an object another request replaced).
    data = os.urandom(50_000)
    errors: list[BaseException] = []
    seen: list[bytes] = []

    def writer() -> None:
        try:
            for _ in range(40):
                local_store.put_bytes("blobs/same", data)
                seen.append(local_store.get_bytes("blobs/same"))
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=writer) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert len(seen) == 240 and all(s == data for s in seen)  # never a partial object
    assert local_store.get_bytes("blobs/same") == data
    assert [p.name for p in _files_under(local_store.root)] == ["same"]  # no temp files left


# ------------------------------------------------------------------------------ LocalStore specifics


def test_local_layout_is_plain_files(local_store: LocalStore) -> None:
    local_store.put_bytes("a/b/c", b"abc")
    assert (local_store.root / "a" / "b" / "c").read_bytes() == b"abc"
    assert _files_under(local_store.root) == [local_store.root / "a" / "b" / "c"]


def test_local_reads_of_missing_root_find_nothing(tmp_path: Path) -> None:
    store = LocalStore(tmp_path / "not" / "yet")
    assert store.list("") == []
    assert not store.exists("x")
    with pytest.raises(NotFound):
        store.get_bytes("x")
    store.put_bytes("x", b"1")  # the first write creates the root
    assert store.get_bytes("x") == b"1"


@pytest.mark.parametrize("fail_at", ["write", "fsync", "replace"])
def test_local_failed_write_leaves_no_partial_object_and_no_temp_file(
    local_store: LocalStore, monkeypatch: pytest.MonkeyPatch, fail_at: str
) -> None:
    local_store.put_bytes("obj", b"old")
    real_write = os.write

    def half_write(fd: int, data: Any) -> int:
        real_write(fd, bytes(data)[: max(1, len(data) // 2)])
        raise OSError(errno.ENOSPC, "No space left on device")

    def fail(*args: Any, **kwargs: Any) -> Any:
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(os, fail_at, half_write if fail_at == "write" else fail)
    with pytest.raises(StoreUnavailable):
        local_store.put_bytes("obj", b"new content" * 1000)
    with pytest.raises(StoreUnavailable):
        local_store.put_bytes("fresh/key", b"new content")
    monkeypatch.undo()

    assert local_store.get_bytes("obj") == b"old"  # old object intact
    assert not local_store.exists("fresh/key")
    leftovers = [p.name for p in _files_under(local_store.root)]
    assert leftovers == ["obj"], leftovers  # no temp files, no partial objects
    assert local_store.list("") == ["obj"]


def test_local_write_fsyncs_file_and_directory(local_store: LocalStore, monkeypatch: pytest.MonkeyPatch) -> None:
    local_store.put_bytes("d/first", b"1")  # directories exist
    kinds: list[str] = []
    replaced: list[bool] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        kinds.append(("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file") + ("+renamed" if replaced else ""))
        real_fsync(fd)

    def replace(src: Any, dst: Any) -> None:
        real_replace(src, dst)
        replaced.append(True)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    local_store.put_bytes("d/second", b"2")
    assert kinds == ["file", "dir+renamed"]  # data synced before the rename, directory after


def test_local_list_ignores_temp_and_foreign_files(local_store: LocalStore) -> None:
    local_store.put_bytes("a/real", b"1")
    (local_store.root / "a" / ".real~0123abcd.tmp").write_bytes(b"crash leftover")
    (local_store.root / "a" / "with space").write_bytes(b"not ours")
    assert local_store.list("") == ["a/real"]


def test_local_disk_trouble_is_unavailable(local_store: LocalStore, monkeypatch: pytest.MonkeyPatch) -> None:
    local_store.put_bytes("x", b"1")

    def denied(*args: Any, **kwargs: Any) -> Any:
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr("producer.store.local.open", denied, raising=False)
    with pytest.raises(StoreUnavailable):
        local_store.get_bytes("x")
    with pytest.raises(StoreUnavailable):
        local_store.open_stream("x")
    monkeypatch.setattr(os, "stat", denied)
    with pytest.raises(StoreUnavailable):
        local_store.exists("x")
    monkeypatch.undo()
    monkeypatch.setattr(os, "scandir", denied)
    with pytest.raises(StoreUnavailable):
        local_store.list("")
    monkeypatch.undo()
    monkeypatch.setattr(os, "mkdir", denied)
    with pytest.raises(StoreUnavailable):
        local_store.put_bytes("new/dir/key", b"1")
    monkeypatch.undo()
    assert local_store.list("") == ["x"]


def test_local_check_fails_when_root_cannot_be_created(tmp_path: Path) -> None:
    (tmp_path / "file").write_bytes(b"")
    store = LocalStore(tmp_path / "file" / "store")  # parent is a regular file
    with pytest.raises(StoreUnavailable):
        store.check()
    with pytest.raises(StoreError):
        store.put_bytes("k", b"1")


def test_local_check_fails_when_root_is_not_writable(local_store: LocalStore, monkeypatch: pytest.MonkeyPatch) -> None:
    local_store.check()

    def read_only(*args: Any, **kwargs: Any) -> Any:
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(os, "open", read_only)
    with pytest.raises(StoreUnavailable, match="Read-only"):
        local_store.check()


def test_local_delete_prunes_empty_dirs_without_breaking_concurrent_writers(local_store: LocalStore) -> None:
    local_store.put_bytes("p/q/r", b"1")
    local_store.delete("p/q/r")
    assert not (local_store.root / "p").exists()
    assert local_store.root.is_dir()

    errors: list[BaseException] = []
    stop = threading.Event()

    def churn() -> None:
        try:
            while not stop.is_set():
                local_store.put_bytes("d/e/x", b"x")
                local_store.delete("d/e/x")
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    def writer() -> None:
        try:
            for i in range(150):
                local_store.put_bytes(f"d/e/y{i % 3}", b"y")
                local_store.delete(f"d/e/y{i % 3}")
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    churner = threading.Thread(target=churn)
    churner.start()
    writer()
    stop.set()
    churner.join()
    assert errors == []


# ------------------------------------------------------------------------------ S3Store specifics


def test_s3_prefix_isolates_and_sets_content_type(s3_bucket: str, s3_config: dict[str, Any], s3_client: Any) -> None:
    one = S3Store(s3_bucket, prefix="tenant/one", **s3_config)
    two = open_store(f"s3://{s3_bucket}/tenant/two/", **s3_config)
    one.put_bytes("k/a", b"1", "image/png")
    two.put_bytes("k/a", b"2")
    assert one.get_bytes("k/a") == b"1" and two.get_bytes("k/a") == b"2"
    assert one.list("") == ["k/a"] and two.list("k/") == ["k/a"]
    raw = s3_client
    head = raw.head_object(Bucket=s3_bucket, Key="tenant/one/k/a")
    assert head["ContentType"] == "image/png"
    listed = sorted(o["Key"] for o in raw.list_objects_v2(Bucket=s3_bucket)["Contents"])
    assert listed == ["tenant/one/k/a", "tenant/two/k/a"]


def test_s3_list_skips_foreign_object_names(s3_store: S3Store, s3_client: Any) -> None:
    s3_store.put_bytes("ok/key", b"1")
    s3_client.put_object(Bucket=s3_store.bucket, Key="ok/bad name", Body=b"x")
    assert s3_store.list("") == ["ok/key"]


def test_s3_listing_follows_pages(s3_store: S3Store) -> None:
    s3_store.list_page_size = 4
    keys = [f"p/{i:02d}" for i in range(11)]
    for k in reversed(keys):
        s3_store.put_bytes(k, b"")
    s3_store.put_bytes("q", b"")
    assert s3_store.list("p/") == keys


def test_s3_missing_bucket_is_unavailable(s3_config: dict[str, Any]) -> None:
    store = S3Store("no-such-bucket-here", **s3_config)
    with pytest.raises(StoreUnavailable, match="does not exist"):
        store.check()
    with pytest.raises(StoreUnavailable):
        store.get_bytes("k")
    with pytest.raises(StoreUnavailable):
        store.put_bytes("k", b"1")


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


def test_s3_unreachable_endpoint_fails_fast(tmp_path: Path) -> None:
    """docs/hard-cases.md #25 with the default timeouts and retries: a clear StoreUnavailable
    within a few seconds for every operation."""
    store = S3Store("bucket", endpoint_url=f"http://127.0.0.1:{_closed_port()}", access_key="a", secret_key="b")
    calls: list[Callable[[], Any]] = [
        store.check,
        lambda: store.put_bytes("k", b"1"),
        lambda: store.get_bytes("k"),
        lambda: store.exists("k"),
        lambda: store.delete("k"),
        lambda: store.list(""),
        lambda: store.open_stream("k"),
    ]
    for call in calls:
        t0 = time.monotonic()
        with pytest.raises(StoreUnavailable, match="127.0.0.1"):
            call()
        assert time.monotonic() - t0 < 5.0


def test_s3_defaults_are_short_timeouts_and_few_attempts() -> None:
    """What keeps a black-holed endpoint (no RST, so no quick refusal) from hanging a request."""
    config = S3Store("bucket", endpoint_url="http://127.0.0.1:1", access_key="a", secret_key="b")._client.meta.config
    assert config.connect_timeout <= 3 and config.read_timeout <= 15
    assert config.retries["total_max_attempts"] <= 3
    assert config.s3["addressing_style"] == "path"


@pytest.fixture
def silent_endpoint() -> Iterator[str]:
    """A TCP port that accepts connections (kernel backlog) but never answers."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(64)
        yield f"http://127.0.0.1:{s.getsockname()[1]}"


def test_s3_silent_endpoint_times_out(silent_endpoint: str) -> None:
    store = S3Store("bucket", endpoint_url=silent_endpoint, access_key="a", secret_key="b", read_timeout=0.3)
    t0 = time.monotonic()
    with pytest.raises(StoreUnavailable):
        store.check()
    assert time.monotonic() - t0 < 4.0


class _CuttingProxy:
    """Forwards TCP to ``target`` but closes both sides after ``limit`` request bytes:
    an S3 upload that dies halfway through its body."""

    def __init__(self, target: tuple[str, int], limit: int) -> None:
        self.target, self.limit = target, limit
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.port: int = self.sock.getsockname()[1]
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                client, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._pipe, args=(client,), daemon=True).start()

    def _pipe(self, client: socket.socket) -> None:
        upstream = socket.create_connection(self.target)
        sent = 0
        try:
            while sent < self.limit:
                data = client.recv(min(65536, self.limit - sent))
                if not data:
                    break
                upstream.sendall(data)
                sent += len(data)
        except OSError:
            pass
        finally:
            client.close()
            upstream.close()

    def close(self) -> None:
        self.sock.close()


def test_s3_upload_cut_halfway_writes_nothing(s3_store: S3Store, s3_config: dict[str, Any]) -> None:
    host, port = s3_config["endpoint_url"].removeprefix("http://").split(":")
    proxy = _CuttingProxy((host, int(port)), limit=40_000)
    try:
        cut = S3Store(
            s3_store.bucket, **{**s3_config, "endpoint_url": f"http://127.0.0.1:{proxy.port}"}, read_timeout=2.0
        )
        with pytest.raises(StoreUnavailable):
            cut.put_bytes("half/written", os.urandom(200_000))
    finally:
        proxy.close()
    time.sleep(0.2)  # let the server finish with the broken request
    assert not s3_store.exists("half/written")
    assert s3_store.list("") == []


def test_s3_store_rejects_bad_settings() -> None:
    with pytest.raises(ValueError):
        S3Store("", endpoint_url="http://127.0.0.1:1")
    with pytest.raises(ValueError):
        S3Store("bucket", access_key="only-one")
    with pytest.raises(ValueError):
        S3Store("bucket", prefix="../up")


# ------------------------------------------------------------------------------ open_store


def test_open_store_urls(tmp_path: Path, s3_bucket: str, s3_config: dict[str, Any]) -> None:
    a = open_store((tmp_path / "a b").as_uri())
    assert isinstance(a, LocalStore) and a.root == tmp_path / "a b"
    b = open_store(str(tmp_path / "b"), **s3_config)  # S3 settings are ignored for a local URL
    assert isinstance(b, LocalStore) and b.root == tmp_path / "b"
    c = open_store(f"file://localhost{tmp_path}/c")
    assert isinstance(c, LocalStore) and c.root == tmp_path / "c"
    rel = open_store("relative/dir")
    assert isinstance(rel, LocalStore) and rel.root.is_absolute()
    s = open_store(f"s3://{s3_bucket}/some/prefix", **s3_config)
    assert isinstance(s, S3Store) and s.bucket == s3_bucket and s.prefix == "some/prefix/"
    s.put_bytes("k", b"v")
    assert S3Store(s3_bucket, **s3_config).get_bytes("some/prefix/k") == b"v"
    assert isinstance(open_store(f"s3://{s3_bucket}", **s3_config), S3Store)


@pytest.mark.parametrize("url", ["", "ftp://host/x", "s3://", "s3:///prefix", "file://otherhost/x", "file:relative"])
def test_open_store_rejects(url: str) -> None:
    with pytest.raises(ValueError):
        open_store(url)


def test_list_page_resumes_after_a_key(any_store: ObjectStore) -> None:
    keys = [f"idx/o/{i:04d}-k" for i in range(23)]
    for k in keys:
        any_store.put_bytes(k, b"")
    any_store.put_bytes("idx/other", b"")  # outside the prefix
    any_store.put_bytes("idx/o0", b"")  # starts with "idx/o" but not "idx/o/"
    got: list[str] = []
    after = ""
    while True:
        page = any_store.list_page("idx/o/", start_after=after, limit=5)
        got += page
        if len(page) < 5:
            break
        after = page[-1]
    assert got == keys
    assert any_store.list_page("idx/o/", start_after=keys[20], limit=100) == keys[21:]
    assert any_store.list_page("idx/none/", limit=3) == []
    assert any_store.list_page("idx/", limit=100) == any_store.list("idx/")  # nested keys too


def _age(path: Path, seconds: float) -> None:
    t = time.time() - seconds
    os.utime(path, (t, t))


def test_local_sweep_removes_only_the_old_temp_files(local_store: LocalStore) -> None:
    key = "artifacts/" + "a" * 64
    local_store.put_bytes(f"{key}/ldc_axis.npz", b"kept")
    d = local_store.root / key
    old = d / ".ldc_axis.npz~0123456789abcdef.tmp"  # a writer killed an hour ago
    live = d / ".llf_views.npz~fedcba9876543210.tmp"  # a write in progress
    old.write_bytes(b"partial")
    live.write_bytes(b"partial")
    _age(old, 2 * 3600)
    lone = local_store.root / "artifacts" / ("b" * 64) / ".manifest.json~00ff00ff00ff00ff.tmp"
    lone.parent.mkdir(parents=True)
    lone.write_bytes(b"{")
    _age(lone, 2 * 3600)
    removed = local_store.sweep_temp_files(3600)
    assert sorted(removed) == sorted(p.relative_to(local_store.root).as_posix() for p in (old, lone))
    assert not old.exists() and live.exists() and not lone.parent.exists()  # the emptied directory went too
    assert local_store.get_bytes(f"{key}/ldc_axis.npz") == b"kept"
    assert local_store.sweep_temp_files(3600) == []
