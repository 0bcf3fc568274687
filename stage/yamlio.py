"""YAML that remembers where things were written, for file:line:column errors.

``load_marked`` returns plain dicts and lists (subclasses) that carry the
line and column (1-based) of each key and item, so a validator can say
``rig.yaml:12:5: unknown key 'refrence'; did you mean 'reference'?``.
Files are written atomically (temp file in the same folder, fsync, rename).
"""

from __future__ import annotations

import difflib
import os
import tempfile
from pathlib import Path
from typing import Any, Iterable

import yaml

from .errors import ConfigError

Mark = tuple[int, int]


class MarkedDict(dict):
    """A mapping with ``mark`` (its own position) and ``marks[key]`` (each key's)."""

    mark: Mark = (0, 0)
    marks: dict[Any, Mark]
    value_marks: dict[Any, Mark]


class MarkedList(list):
    """A sequence with ``mark`` and ``marks[i]`` for each item."""

    mark: Mark = (0, 0)
    marks: list[Mark]


def _mark(node: yaml.Node) -> Mark:
    return node.start_mark.line + 1, node.start_mark.column + 1


class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
    pass


def _construct_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode) -> MarkedDict:
    loader.flatten_mapping(node)
    out = MarkedDict()
    out.mark, out.marks, out.value_marks = _mark(node), {}, {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if not isinstance(key, (str, int, float, bool)) and key is not None:
            raise ConfigError("a key must be a plain value", line=_mark(key_node)[0],
                              column=_mark(key_node)[1])
        if key in out:
            raise ConfigError(f"duplicate key '{key}'", line=_mark(key_node)[0],
                              column=_mark(key_node)[1])
        out[key] = loader.construct_object(value_node, deep=True)
        out.marks[key] = _mark(key_node)
        out.value_marks[key] = _mark(value_node)
    return out


def _construct_sequence(loader: yaml.SafeLoader, node: yaml.SequenceNode) -> MarkedList:
    out = MarkedList(loader.construct_object(child, deep=True) for child in node.value)
    out.mark, out.marks = _mark(node), [_mark(child) for child in node.value]
    return out


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_SEQUENCE_TAG, _construct_sequence)


def load_marked(path: str | os.PathLike) -> Any:
    """Parse a YAML file; syntax errors become ConfigError with file:line:column."""
    path = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("no such file", path=path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read: {exc}", path=path) from None
    return loads_marked(text, path)


def loads_marked(text: str, path: str = "<string>") -> Any:
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass
    except ConfigError as exc:
        raise ConfigError(exc.bare_message, path=path, line=exc.line, column=exc.column) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        problem = exc.problem or exc.context or "invalid YAML"
        raise ConfigError(f"YAML syntax: {problem}", path=path,
                          line=mark.line + 1 if mark else None,
                          column=mark.column + 1 if mark else None) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"YAML syntax: {exc}", path=path) from None


class Where:
    """Builds ConfigErrors that point into one file."""

    def __init__(self, path: str) -> None:
        self.path = path

    def error(self, message: str, mark: Mark | None = None) -> ConfigError:
        line, column = mark if mark else (None, None)
        return ConfigError(message, path=self.path, line=line, column=column)

    def at_key(self, mapping: Any, key: Any, message: str) -> ConfigError:
        marks = getattr(mapping, "value_marks", {})
        return self.error(message, marks.get(key, getattr(mapping, "mark", None)))

    def mapping(self, value: Any, what: str, mark: Mark | None = None) -> dict:
        if value is None:
            return MarkedDict()
        if not isinstance(value, dict):
            raise self.error(f"{what} must be a mapping (key: value lines)",
                             getattr(value, "mark", mark))
        return value

    def check_keys(self, mapping: dict, allowed: Iterable[str], what: str) -> None:
        allowed = list(allowed)
        for key in mapping:
            if key not in allowed:
                hint = difflib.get_close_matches(str(key), allowed, n=1)
                tail = f"; did you mean '{hint[0]}'?" if hint else f"; expected one of: {', '.join(allowed)}"
                raise self.error(f"unknown key '{key}' in {what}{tail}",
                                 getattr(mapping, "marks", {}).get(key))

    def number(self, mapping: dict, key: str, default: float, *, minimum: float | None = None,
               exclusive_minimum: float | None = None) -> float:
        value = mapping.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
            raise self.at_key(mapping, key, f"'{key}' must be a number, got {value!r}")
        if minimum is not None and value < minimum:
            raise self.at_key(mapping, key, f"'{key}' must be at least {minimum}, got {value}")
        if exclusive_minimum is not None and value <= exclusive_minimum:
            raise self.at_key(mapping, key,
                              f"'{key}' must be greater than {exclusive_minimum}, got {value}")
        return float(value)


def write_atomic(path: str | os.PathLike, text: str) -> None:
    """Replace ``path`` with ``text`` so a reader sees the old or the new file, never half."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
