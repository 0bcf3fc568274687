"""The JSON Schema of piece files, generated from ``stage.piece.language``.

Shipped as ``stage/piece/piece.schema.json`` (package data) and copied to
``pieces/piece.schema.json`` so editors find it next to the pieces (YAML
language server: ``# yaml-language-server: $schema=piece.schema.json``).
Regenerate both after changing the language::

    python -m stage.piece.schema            # writes both files
    python -m stage.piece.schema --check    # exit 1 if either is out of date

For pieces anywhere else, ``install_user_copy()`` (``stage schema --install``,
and ``stage new``) writes a copy to a fixed place of the user's
(``$XDG_DATA_HOME/stage``, else ``~/.local/share/stage``) whose ``$id`` is
its own location; a piece's schema line can name that absolute path. The
shipped copies carry no ``$id``: an identifier must say where the schema is,
and only an installed copy knows.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from ..errors import ConfigError
from ..yamlio import write_atomic
from .language import PIECE
from .spec import definitions

PACKAGE_COPY = Path(__file__).with_name("piece.schema.json")
PIECES_COPY = Path(__file__).resolve().parents[2] / "pieces" / "piece.schema.json"


def piece_schema(location: str | None = None) -> dict:
    """The schema as a dict (draft 2020-12); ``location``: its URI as ``$id``."""
    root = PIECE.schema()
    head = {"$schema": "https://json-schema.org/draft/2020-12/schema"}
    if location:
        head["$id"] = location
    return {**head, "title": "stage piece", **root, "$defs": definitions(PIECE)}


def schema_text(location: str | None = None) -> str:
    return json.dumps(piece_schema(location), indent=2, sort_keys=False) + "\n"


def user_copy_path() -> Path:
    """Where ``install_user_copy`` puts the schema: ``$XDG_DATA_HOME/stage/piece.schema.json``."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local",
                                                           "share")
    return Path(base) / "stage" / "piece.schema.json"


def install_user_copy() -> tuple[Path, bool]:
    """Write (or refresh) the user's copy of the schema; (its path, whether it changed)."""
    path = user_copy_path()
    text = schema_text(path.resolve().as_uri())
    if path.exists() and path.read_text(encoding="utf-8") == text:
        return path, False
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, text)
    except OSError as exc:
        raise ConfigError(f"cannot write the schema to {path}: {exc.strerror}") from None
    return path, True


def modeline(path: str | os.PathLike) -> str:
    """The first line of a piece that points the YAML language server at ``path``."""
    return f"# yaml-language-server: $schema={path}"


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
