"""The JSON Schema of piece files, generated from ``stage.piece.language``.

Shipped as ``stage/piece/piece.schema.json`` (package data) and copied to
``pieces/piece.schema.json`` so editors find it next to the pieces (YAML
language server: ``# yaml-language-server: $schema=piece.schema.json``).
Regenerate both after changing the language::

    python -m stage.piece.schema            # writes both files
    python -m stage.piece.schema --check    # exit 1 if either is out of date
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..yamlio import write_atomic
from .language import PIECE
from .spec import definitions

SCHEMA_ID = "https://stage.invalid/piece.schema.json"
PACKAGE_COPY = Path(__file__).with_name("piece.schema.json")
PIECES_COPY = Path(__file__).resolve().parents[2] / "pieces" / "piece.schema.json"


def piece_schema() -> dict:
    """The schema as a dict (draft 2020-12)."""
    root = PIECE.schema()
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "$id": SCHEMA_ID,
            "title": "stage piece", **root, "$defs": definitions(PIECE)}


def schema_text() -> str:
    return json.dumps(piece_schema(), indent=2, sort_keys=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stage.piece.schema", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="only compare; exit 1 if stale")
    args = parser.parse_args(argv)
    text = schema_text()
    stale = []
    for path in (PACKAGE_COPY, PIECES_COPY):
        current = path.read_text(encoding="utf-8") if path.exists() else None
        if current == text:
            continue
        if args.check:
            stale.append(str(path))
        elif path.parent.is_dir():
            write_atomic(path, text)
            print(f"wrote {path}")
    if stale:
        print("out of date (run python -m stage.piece.schema): " + ", ".join(stale), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
