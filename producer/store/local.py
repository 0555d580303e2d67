"""Object store in a local directory (the default backend).

Every write goes to a temp file in the destination directory, is flushed and fsynced,
then renamed over the destination with ``os.replace`` (atomic on POSIX), and the
directory is fsynced so the rename itself survives a crash. Readers therefore see the
old object, the new one or nothing. Temp files carry a '~' in their name, a character
no key may contain, so they can never be mistaken for (or collide with) an object; they
are removed on every error path.
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import stat
import time
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from producer.store.base import (
    DEFAULT_CHUNK,
    NotFound,
    StoreError,
    StoreUnavailable,
    is_valid_key,
    validate_key,
    validate_prefix,
)

__all__ = ["LocalStore"]

_Keys = list[str]
"""(A name of the type: inside the classes ``list`` is the method.)"""

_TEMP_MARK = "~"
_PUT_ATTEMPTS = 16
"""A concurrent delete may prune a directory between our mkdir and our open: retry. (Three
attempts lost the race once in a fresh-clone CI run of the concurrent prune test on the loaded
2-core machine; each retry costs a mkdir, so a generous bound is cheap.)"""


def _unavailable(what: str, exc: OSError) -> StoreUnavailable:
    reason = os.strerror(exc.errno) if exc.errno is not None else str(exc)
    return StoreUnavailable(f"local store: {what}: {reason}")


class LocalStore:
    """Objects as files under ``root`` (key ``a/b/c`` -> ``root/a/b/c``).

    No I/O happens in the constructor: a missing root is created on the first write (or
    by :meth:`check`); reads from a missing root find nothing (NotFound / empty list)."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root: Path = Path(root).absolute()

    def __repr__(self) -> str:
        return f"LocalStore({str(self.root)!r})"

    @property
    def url(self) -> str:
        return self.root.as_uri()

    # ------------------------------------------------------------------ helpers

    def _path(self, key: str) -> Path:
        validate_key(key)
        return self.root.joinpath(*key.split("/"))

    @staticmethod
    def _fsync_dir(directory: Path) -> None:
        try:
            fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        except FileNotFoundError:
            # pruned by a concurrent delete: our entry in it is gone too, nothing to sync
            return
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def _ensure_dir(self, directory: Path) -> None:
        if directory.is_dir():
            return
        missing: list[Path] = []
        p = directory
        while not p.is_dir():
            missing.append(p)
            if p.parent == p:
                break
            p = p.parent
        for d in reversed(missing):
            try:
                os.mkdir(d)
            except FileExistsError:
                # a file here is a key clash; nothing here (FileNotFoundError from the stat) is a
                # concurrent delete that pruned the directory since our mkdir: the caller retries
                if not stat.S_ISDIR(os.stat(d).st_mode):
                    raise NotADirectoryError(errno.ENOTDIR, "exists and is not a directory", str(d)) from None
                continue
            self._fsync_dir(d.parent)

    def _write_atomic(self, path: Path, data: bytes | bytearray | memoryview) -> None:
        tmp = path.parent / f".{path.name}{_TEMP_MARK}{secrets.token_hex(8)}.tmp"
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        try:
            try:
                view = memoryview(data).cast("B")
                while view:
                    written = os.write(fd, view)
                    view = view[written:]
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
        self._fsync_dir(path.parent)

    def _prune_empty_dirs(self, directory: Path) -> None:
        """Remove now-empty directories up to (not including) the root; best effort."""
        p = directory
        while p != self.root and self.root in p.parents:
            try:
                os.rmdir(p)
            except OSError:
                return
            p = p.parent

    # ------------------------------------------------------------------ protocol

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        path = self._path(key)
        for attempt in range(_PUT_ATTEMPTS):
            try:
                self._ensure_dir(path.parent)
                self._write_atomic(path, data)
                return
            except FileNotFoundError as exc:
                if attempt == _PUT_ATTEMPTS - 1:
                    raise _unavailable(f"cannot write {key}", exc) from exc
            except (IsADirectoryError, NotADirectoryError) as exc:
                # a key and a "directory" key clash (``a`` vs ``a/b``): a bug in our key layout
                raise StoreError(f"local store: cannot write {key}: a path component clashes with another key") from exc
            except OSError as exc:  # permission, disk full, read-only fs, I/O error
                raise _unavailable(f"cannot write {key}", exc) from exc

    def _open(self, key: str) -> BinaryIO:
        path = self._path(key)
        try:
            return open(path, "rb")  # noqa: SIM115 - returned to the caller, closed there
        except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
            raise NotFound(key) from None
        except OSError as exc:
            raise _unavailable(f"cannot read {key}", exc) from exc

    def get_bytes(self, key: str) -> bytes:
        with self._open(key) as f:
            try:
                return f.read()
            except OSError as exc:
                raise _unavailable(f"cannot read {key}", exc) from exc

    def exists(self, key: str) -> bool:
        path = self._path(key)
        try:
            st = os.stat(path)
        except (FileNotFoundError, NotADirectoryError):
            return False
        except OSError as exc:
            raise _unavailable(f"cannot stat {key}", exc) from exc
        return stat.S_ISREG(st.st_mode)

    def delete(self, key: str) -> None:
        path = self._path(key)
        try:
            os.unlink(path)
        except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
            return
        except OSError as exc:
            raise _unavailable(f"cannot delete {key}", exc) from exc
        try:
            self._fsync_dir(path.parent)
        except OSError as exc:
            raise _unavailable(f"cannot sync after deleting {key}", exc) from exc
        self._prune_empty_dirs(path.parent)

    def list(self, prefix: str) -> list[str]:
        validate_prefix(prefix)
        head = prefix.rpartition("/")[0]
        base = self.root.joinpath(*head.split("/")) if head else self.root

        def on_error(exc: OSError) -> None:
            if isinstance(exc, FileNotFoundError | NotADirectoryError):
                return  # no such "directory" (or it vanished meanwhile): nothing under it
            raise _unavailable(f"cannot list {prefix!r}", exc) from exc

        keys: list[str] = []
        for dirpath, dirnames, filenames in os.walk(base, onerror=on_error):
            rel = Path(dirpath).relative_to(self.root).as_posix()
            lead = "" if rel == "." else rel + "/"
            # descend only into directories that can hold keys with this prefix
            dirnames[:] = [
                d for d in dirnames if (lead + d + "/").startswith(prefix) or prefix.startswith(lead + d + "/")
            ]
            for name in filenames:
                if _TEMP_MARK in name:
                    continue
                key = lead + name
                if key.startswith(prefix) and is_valid_key(key):
                    keys.append(key)
        keys.sort()
        return keys

    def list_page(self, prefix: str, start_after: str = "", limit: int = 1000) -> _Keys:
        if limit < 1:
            raise ValueError(f"limit must be positive, got {limit}")
        validate_prefix(prefix)
        if prefix.endswith("/"):
            # the usual case, an index "directory": one scandir, no walk, when it holds no subdirectory
            base = self.root.joinpath(*prefix[:-1].split("/"))
            names: list[str] = []
            try:
                with os.scandir(base) as it:
                    for entry in it:
                        if entry.is_dir(follow_symlinks=False):
                            break
                        if _TEMP_MARK not in entry.name:
                            names.append(entry.name)
                    else:
                        keys = sorted(k for k in (prefix + n for n in names) if k > start_after and is_valid_key(k))
                        return keys[:limit]
            except (FileNotFoundError, NotADirectoryError):
                return []
            except OSError as exc:
                raise _unavailable(f"cannot list {prefix!r}", exc) from exc
        return [k for k in self.list(prefix) if k > start_after][:limit]

    def open_stream(self, key: str, chunk: int = DEFAULT_CHUNK) -> Iterator[bytes]:
        if chunk <= 0:
            raise ValueError(f"chunk must be positive, got {chunk}")
        return _iter_file(self._open(key), key, chunk)

    def sweep_temp_files(self, older_than_s: float) -> _Keys:
        """Remove the temp files of writes that never finished (a ``~`` in the name, last modified
        more than ``older_than_s`` seconds ago) anywhere under the root; prunes directories left
        empty. Returns the removed paths, relative to the root. A live writer's temp file is
        younger than the grace period (its write takes less than that), so it is left alone."""
        cutoff = time.time() - older_than_s
        removed: _Keys = []
        for dirpath, _dirnames, filenames in os.walk(self.root):
            for name in filenames:
                if _TEMP_MARK not in name:
                    continue
                path = Path(dirpath) / name
                try:
                    if os.lstat(path).st_mtime >= cutoff:
                        continue
                    os.unlink(path)
                except FileNotFoundError:
                    continue  # renamed into place or removed meanwhile
                except OSError as exc:
                    raise _unavailable(f"cannot remove the stray temp file {path}", exc) from exc
                removed.append(path.relative_to(self.root).as_posix())
                self._prune_empty_dirs(path.parent)
        return removed

    def check(self) -> None:
        try:
            self._ensure_dir(self.root)
            os.listdir(self.root)
            probe = self.root / f".check{_TEMP_MARK}{secrets.token_hex(8)}"
            self._write_atomic(probe, b"ok")
            os.unlink(probe)
        except OSError as exc:
            raise _unavailable(f"root {self.root} is not usable", exc) from exc


def _iter_file(f: BinaryIO, key: str, chunk: int) -> Iterator[bytes]:
    with f:
        while True:
            try:
                block = f.read(chunk)
            except OSError as exc:
                raise _unavailable(f"cannot read {key}", exc) from exc
            if not block:
                return
            yield block
