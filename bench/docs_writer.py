"""Replace a marked block in a Markdown file, so several benchmarks can share one page."""

from __future__ import annotations

from pathlib import Path


def replace_block(path: str | Path, name: str, body: str, title: str = "") -> None:
    """Write ``body`` between ``<!-- bench:NAME:start -->`` and ``<!-- bench:NAME:end -->``
    in ``path`` (creating the file / block at the end when missing)."""
    p = Path(path)
    start, end = f"<!-- bench:{name}:start -->", f"<!-- bench:{name}:end -->"
    text = p.read_text() if p.exists() else (f"# {title}\n\n" if title else "")
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text and end in text:
        a, b = text.index(start), text.index(end) + len(end)
        text = text[:a] + block + text[b:]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text if text.endswith("\n") else text + "\n")
