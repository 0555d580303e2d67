"""Every repository path, module and relative link that docs/ and README.md cite exists.

Docs name files (`engine/raycast.py`), modules (`producer.queue`, `workers.jobs.render.render_job`)
and other pages (`[the API](api.md#renders)`); a move that forgets a page leaves a reader at a
dead end. This reads every Markdown file under docs/ plus README.md and checks:

- relative links resolve to a file or directory, and a ``#anchor`` into a Markdown page names one
  of its headings (GitHub's slugs);
- backticked paths that start with a top-level directory of the repository exist (``::name`` and
  ``:line`` suffixes are ignored; globs and ``{a,b}`` patterns are skipped);
- backticked dotted names that start with a top-level package resolve to a module, a package, or
  a name in a package's ``__init__.py`` (what follows a module is an attribute and is not checked).

``ALLOWED`` lists the citations that deliberately name something that does not exist (the old
module names in an upgrade note); ``RUNTIME`` the directories a process creates when it runs.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted([*ROOT.glob("docs/**/*.md"), ROOT / "README.md"])
# the top-level directories a cited path can start with, and the importable packages among them
TOP = sorted(p.name for p in ROOT.iterdir()
             if (p / "__init__.py").exists() or p.name in {"docs", "samples", "examples", ".ci"})
PACKAGES = sorted(p.name for p in ROOT.iterdir() if (p / "__init__.py").exists())

# (page relative to the root, cited text): deliberate names of things that are not in the tree.
ALLOWED: set[tuple[str, str]] = {
    # the upgrade note maps the previous layout's modules to the current ones
    *{("docs/service-design.md", old) for old in (
        "workers.store", "workers.artifacts", "workers.bakes", "workers.walkthroughs", "workers.datasets",
        "workers.scene_outputs", "workers.embedded", "workers.queues", "workers.jobs.payloads",
        "service.core.config.Settings", "workers.settings.WorkerSettings")},
}
# directories a process creates at run time (git-ignored), which a page may name as a default
RUNTIME = ("engine/__pycache__",)

LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")
CODE = re.compile(r"`([^`\n]+)`")
PATH = re.compile(rf"^(?:{'|'.join(map(re.escape, TOP))})/[\w./-]*$")
DOTTED = re.compile(rf"^(?:{'|'.join(map(re.escape, PACKAGES))})(?:\.\w+)+$")


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip())  # a link in a heading: its text
    text = text.lower().replace("`", "")
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(page: Path, text: str | None = None) -> set[str]:
    out: set[str] = set()
    seen: dict[str, int] = {}
    in_fence = False
    for line in (page.read_text(encoding="utf-8") if text is None else text).splitlines():
        if line.lstrip().startswith("```"):
            in_fence = not in_fence
            continue
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m and not in_fence:
            s = _slug(m.group(1))
            n = seen.get(s, 0)
            seen[s] = n + 1
            out.add(s if n == 0 else f"{s}-{n}")
        out.update(re.findall(r'<a\s+(?:name|id)="([^"]+)"', line))
    return out


def _module_exists(dotted: str) -> bool:
    parts = dotted.split(".")
    here = ROOT / parts[0]
    for name in parts[1:]:
        if (here / name).is_dir() and ((here / name / "__init__.py").exists()):
            here = here / name
            continue
        if (here / f"{name}.py").exists():
            return True  # the rest is an attribute of that module
        init = here / "__init__.py"
        # a name the package defines or re-exports
        return bool(init.exists() and re.search(rf"\b{re.escape(name)}\b", init.read_text(encoding="utf-8")))
    return True


def _cited(text: str) -> list[tuple[str, str]]:
    """(kind, text) of every link and backticked path or module on a page, fenced code included."""
    text = re.sub(r"<!--.*?-->", "", text, flags=re.S)
    out: list[tuple[str, str]] = []
    for m in LINK.finditer(text):
        out.append(("link", m.group(1) or m.group(2)))
    for m in CODE.finditer(text):
        token = m.group(1).strip()
        token = re.split(r"::|:(?=\d)", token)[0].rstrip(".,;:")
        if re.search(r"[*{}<>$ ]", token):
            continue
        if PATH.match(token):
            out.append(("path", token))
        elif DOTTED.match(token):
            out.append(("module", token))
    return out


def _problems(page: Path, text: str | None = None) -> list[str]:
    """What ``page`` (or ``text`` read as if it were that page) cites that does not exist."""
    rel = page.relative_to(ROOT).as_posix()
    bad: list[str] = []
    for kind, target in _cited(page.read_text(encoding="utf-8") if text is None else text):
        if (rel, target) in ALLOWED:
            continue
        if kind == "link":
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
                continue
            file_part, _, anchor = target.partition("#")
            dest = (page.parent / file_part).resolve() if file_part else page
            if file_part and not dest.exists():
                bad.append(f"{rel}: link {target!r}: no such file")
            elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest, text if dest == page else None):
                bad.append(f"{rel}: link {target!r}: no heading with that anchor")
        elif kind == "path":
            if target.startswith(RUNTIME):
                continue
            if not (ROOT / target.rstrip("/")).exists():
                bad.append(f"{rel}: path `{target}` does not exist")
        elif not _module_exists(target):
            bad.append(f"{rel}: module `{target}` does not exist")
    return bad


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_cited_paths_exist(page: Path) -> None:
    assert _problems(page) == []


def test_the_check_finds_dead_citations() -> None:
    """The checker itself: a dead path, module, link and anchor are each reported, live ones are not."""
    probe = ("# Probe\n\n`engine/no_such_module.py`, `producer.no_such_module`, [gone](no-such-page.md), "
             "[bad anchor](api.md#no-such-heading), [ok](#probe), [ok](../README.md), "
             "`engine/raycast.py::EmbreeCaster`, `producer.settings.Settings`, `workers.jobs.render.render_job`.\n")
    got = _problems(ROOT / "docs" / "probe.md", probe)
    assert len(got) == 4, got
    assert any("engine/no_such_module.py" in g for g in got)
    assert any("producer.no_such_module" in g for g in got)
    assert any("no-such-page.md" in g for g in got)
    assert any("no-such-heading" in g for g in got)
