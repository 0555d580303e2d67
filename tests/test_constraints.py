"""constraints.txt pins every package the service's installs name: each direct dependency of
pyproject.toml (runtime and the dev extras) has one exact version there, within the lower bound
pyproject.toml asks for, so `make run`, `make test` and the image install what the tests passed with."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _name(requirement: str) -> str:
    """The normalised distribution name of a requirement (PEP 503: case and ``-_.`` folded)."""
    m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", requirement)
    assert m, requirement
    return re.sub(r"[-_.]+", "-", m.group(1)).lower()


def _version(v: str) -> tuple[int, ...]:
    return tuple(int(x) for x in re.findall(r"\d+", v)[:3])


def _pins() -> dict[str, str]:
    pins: dict[str, str] = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        name, sep, version = line.partition("==")
        assert sep and version, f"constraints.txt: {line!r} is not an exact pin (name==version)"
        assert _name(name) not in pins, f"constraints.txt pins {name} twice"
        pins[_name(name)] = version.strip()
    return pins


def test_every_direct_dependency_is_pinned_within_its_lower_bound() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    requirements = list(project["dependencies"]) + [r for extra in project["optional-dependencies"].values()
                                                    for r in extra]
    pins = _pins()
    missing = [r for r in requirements if _name(r) not in pins]
    assert not missing, f"not pinned in constraints.txt: {missing}"
    for r in requirements:
        low = re.search(r">=\s*([0-9][0-9.]*)", r)
        if low:
            assert _version(pins[_name(r)]) >= _version(low.group(1)), \
                f"{_name(r)}=={pins[_name(r)]} in constraints.txt is below pyproject.toml's {r!r}"


def test_every_install_of_the_service_keeps_to_the_constraints() -> None:
    makefile = (ROOT / "Makefile").read_text()
    installs = [ln for ln in makefile.splitlines() if "pip install" in ln and "-e " in ln]
    assert len(installs) == 2 and all("-c constraints.txt" in ln for ln in installs), installs
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert "COPY pyproject.toml README.md constraints.txt" in dockerfile
    assert "pip install --no-cache-dir -c constraints.txt ." in dockerfile
