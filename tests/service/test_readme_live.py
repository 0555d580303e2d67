"""The README's commands work as written: its shell blocks (the curl API tour and the CLI block; not
the install blocks, ``make run`` / ``make test``) run with bash against a live ``ibr up`` stack (the
sample scenes loaded, as ``make run`` does), from a directory laid out like a fresh clone.

Only two things are substituted: ``.venv/bin/`` by the directory of the Python running the tests
(its ``ibr``), and the README's API address by the stack's (also given to the CLI as
``IBR_API_URL``). Each command must exit 0, or the code its comment names (``# exit 2, ...``);
every file a command writes with ``-o`` must be a non-empty image / video of that type; every
variable a command captures with ``X=$(...)`` must hold exactly an id (64 hex digits, no stray
progress output)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from engine.imageio import read_image
from service.up import Stack
from tests.fixtures.stack import own_stack

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
README_API = "http://127.0.0.1:8000"
BLOCK = re.compile(r"^```sh\n(.*?)^```", re.M | re.S)
EXPECT = re.compile(r"#\s*exit (\d+)\b")
OUTPUT = re.compile(r"(?:^|\s)-o\s+(\S+)")
CAPTURE = re.compile(r"^([A-Za-z_]\w*)=\$\(", re.M)
# what a clone holds that the commands may not see: the developer's own outputs and environment
NOT_CLONED = {".git", ".venv", "out", ".ibr-data", "test-artifacts", ".pytest_cache", ".ruff_cache", ".mypy_cache"}
BLOCK_TIMEOUT_S = 420.0


def _code_lines(block: str) -> list[str]:
    return [ln for ln in block.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def readme_blocks() -> list[str]:
    """The README's ``sh`` blocks other than the install ones (every line a ``make`` target)."""
    blocks = BLOCK.findall(README.read_text(encoding="utf-8"))
    return [b for b in blocks if not all(ln.startswith("make ") for ln in _code_lines(b))]


def commands(block: str) -> list[str]:
    """The block split into complete commands, as bash parses them: lines are joined until
    ``bash -n`` accepts the text (a quoted JSON body or ``$(...)`` spans lines) and the last line
    does not continue with a backslash. Comment lines between commands are dropped."""
    out: list[str] = []
    buf: list[str] = []
    for line in block.splitlines():
        if not buf and (not line.strip() or line.lstrip().startswith("#")):
            continue
        buf.append(line)
        if line.rstrip().endswith("\\"):
            continue
        text = "\n".join(buf)
        if subprocess.run(["bash", "-n"], input=text, text=True, capture_output=True).returncode == 0:
            out.append(text)
            buf = []
    assert not buf, f"README.md: a command bash cannot parse: {chr(10).join(buf)}"
    return out


def expected_exit(command: str) -> int:
    m = EXPECT.search(command.splitlines()[-1])
    return int(m.group(1)) if m else 0


def test_readme_blocks_are_found_and_split() -> None:
    """The extraction itself: the tour (its multi-line JSON command kept whole) and the CLI block."""
    blocks = [commands(b) for b in readme_blocks()]
    assert len(blocks) >= 2, blocks
    tour, cli = blocks[0], next(b for b in blocks if any(".venv/bin/ibr datasets upload" in c for c in b))
    assert tour[0].startswith("API=") and README_API in tour[0]
    assert tour[1].startswith("SCENE=$(curl") and tour[1].endswith("[\"id\"])')") and tour[1].count("\n") == 7
    assert len(cli) >= 10 and all(".venv/bin/ibr " in c for c in cli), cli
    assert [expected_exit(c) for c in cli].count(2) == 1
    assert commands("a \\\n  b\n# note\nX=$(echo '\n)')\n") == ["a \\\n  b", "X=$(echo '\n)')"]


def _fresh_clone(dest: Path) -> None:
    """Every tracked top-level entry of the repository, linked into ``dest`` (the commands only read it)."""
    for p in ROOT.iterdir():
        if p.name not in NOT_CLONED and not p.name.endswith(".egg-info") and p.name != "__pycache__":
            (dest / p.name).symlink_to(p)


def _check_output(path: Path, command: str) -> None:
    assert path.is_file() and path.stat().st_size > 0, f"{command!r} did not write {path}"
    data = path.read_bytes()
    suffix = path.suffix.lower()
    if suffix == ".mp4":
        assert data[4:8] == b"ftyp", f"{path}: not an MP4"
        return
    magic = {".png": b"\x89PNG", ".exr": b"v/1\x01"}[suffix]
    assert data[:4] == magic, f"{path}: not a {suffix} file"
    img, _ = read_image(path)
    assert np.isfinite(img).all() and img.max() > 0, f"{path}: an all-black or non-finite image"


@pytest.fixture(scope="module")
def stack() -> Iterator[Stack]:
    with own_stack(samples=True) as st:  # as `make run`: the sample scenes loaded
        yield st


# Everyday runs skip this (make test-fast): the whole service started as processes, driven by bash.
@pytest.mark.slow
def test_every_readme_command_works_as_written(stack: Stack, tmp_path: Path) -> None:
    bin_dir = Path(sys.executable).parent  # not resolved: the venv's bin, where its ibr lives
    assert (bin_dir / "ibr").is_file(), f"no ibr next to {sys.executable}"
    readme = README.read_text(encoding="utf-8")
    assert README_API in readme and ".venv/bin/ibr" in readme  # what the substitutions replace
    clone = tmp_path / "clone"
    clone.mkdir()
    _fresh_clone(clone)
    env = {**os.environ, "IBR_API_URL": stack.api_url}
    env.pop("IBR_API_KEY", None)

    for n, block in enumerate(readme_blocks()):
        cmds = [c.replace(".venv/bin/", f"{bin_dir}/").replace(README_API, stack.api_url)
                for c in commands(block)]
        logs = tmp_path / f"block{n}"
        logs.mkdir()
        lines = ["set -o pipefail"]
        for i, c in enumerate(cmds):
            lines += ["{", c, f'}} >"{logs}/{i}.out" 2>"{logs}/{i}.err"', f'echo "{i} $? $SECONDS" >>"{logs}/rc"']
        captured = sorted(set(CAPTURE.findall("\n".join(cmds))))
        lines += [f'printf "%s" "${name}" >"{logs}/var.{name}"' for name in captured]
        script = logs / "block.sh"
        script.write_text("\n".join(lines) + "\n")
        t0 = time.monotonic()
        subprocess.run(["bash", str(script)], cwd=clone, env=env, timeout=BLOCK_TIMEOUT_S, check=False)
        took = time.monotonic() - t0
        ends = [ln.split() for ln in (logs / "rc").read_text().splitlines()]
        codes = {i: rc for i, rc, _ in ends}
        stamps = [0] + [int(t) for _, _, t in ends]  # bash's $SECONDS after each command
        took_each = [b - a for a, b in zip(stamps[:-1], stamps[1:], strict=True)]
        for i, c in enumerate(cmds):
            out, err = (logs / f"{i}.out").read_text(), (logs / f"{i}.err").read_text()
            want = expected_exit(c)
            assert codes.get(str(i)) == str(want), (
                f"README block {n}, command {i} exited {codes.get(str(i))}, not {want}:\n{c}\n"
                f"--- stdout\n{out[-2000:]}\n--- stderr\n{err[-4000:]}")
            if want == 2:  # bad input: a message naming the problem, no result
                assert err.startswith("error: ") and not out.strip(), (c, out, err)
            for target in OUTPUT.findall(c):
                _check_output(clone / target, c)
        for name in captured:
            value = (logs / f"var.{name}").read_text()
            assert re.fullmatch(r"[0-9a-f]{64}", value), f"${name} captured {value!r}, not an id"
        print(f"README block {n}: {len(cmds)} commands in {took:.1f} s; each (s): {took_each}")
