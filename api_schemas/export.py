"""Write the scene JSON Schema: ``python -m api_schemas.export docs/scene.schema.json``.

``--check`` compares instead of writing and exits 1 when the file is stale (for CI).
The committed ``docs/scene.schema.json`` is kept current by a test that does the same.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from api_schemas.scene import scene_json_schema

__all__ = ["DEFAULT_PATH", "main", "render_schema"]

DEFAULT_PATH = Path("docs/scene.schema.json")


def render_schema() -> str:
    """The schema as committed: 2-space indented JSON with a trailing newline."""
    return json.dumps(scene_json_schema(), indent=2, ensure_ascii=False) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m api_schemas.export", description="Write the scene JSON Schema."
    )
    parser.add_argument("path", nargs="?", type=Path, default=DEFAULT_PATH, help="output file")
    parser.add_argument("--check", action="store_true", help="exit 1 if the file differs; do not write")
    args = parser.parse_args(argv)
    text = render_schema()
    path: Path = args.path
    if args.check:
        current = path.read_text(encoding="utf-8") if path.exists() else None
        if current != text:
            print(f"{path} is out of date; run: python -m api_schemas.export {path}", file=sys.stderr)
            return 1
        return 0
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
