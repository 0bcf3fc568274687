"""A small language for describing YAML formats once, for both validation and JSON Schema.

The piece format is written down as ``Kind`` objects (numbers, names, lists,
objects with known keys, ...). The same objects

* check a file loaded with ``stage.yamlio.load_marked`` and raise one-line
  ``ConfigError``s that point at ``file:line:column`` and say what was
  expected (with a spelling suggestion where one is likely), and
* produce the JSON Schema shipped for editors (``Kind.schema()``),

so the schema and the loader can never disagree about which keys exist,
what type they have and which values are allowed. Cross-references (a zone a
trigger names, a phrase a section lists) and musical checks are done by the
compiler afterwards, with the same kind of messages.
"""

from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

from ..errors import ConfigError
from ..joints import GROUPS, JOINTS, suggest_joint
from ..yamlio import Mark, MarkedDict, MarkedList, Where

#: A value and where it was written (line, column), passed down while checking.
Located = tuple[Any, Mark | None]


def type_name(value: Any) -> str:
    """How a YAML value reads to a composer: 'a number', 'text', 'a list', ..."""
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        return "true/false"
    if isinstance(value, (int, float)):
        return f"the number {value:g}" if isinstance(value, float) else f"the number {value}"
    if isinstance(value, str):
        return f"'{value}'"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "a mapping"
    return type(value).__name__


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """'; did you mean 'x'?' when a choice is close to ``word``, else ''."""
    choices = [str(c) for c in choices]
    lowered = {c.lower(): c for c in choices}
    if word.lower() in lowered:
        return f"; did you mean '{lowered[word.lower()]}'?"
    close = difflib.get_close_matches(word.lower(), list(lowered), n=1, cutoff=0.6)
    return f"; did you mean '{lowered[close[0]]}'?" if close else ""


class Kind:
    """One type of value in the format. ``expected`` reads as 'X must be <expected>'."""

    doc: str = ""
    expected: str = "a value"

    def check(self, value: Any, mark: Mark | None, what: str, where: Where) -> Any:
        raise NotImplementedError

    def schema(self) -> dict:
        raise NotImplementedError

    def accepts_type(self, value: Any) -> bool:
        """Whether ``value`` has the right YAML type for this kind (used by ``AnyOf``)."""
        raise NotImplementedError

    def _with_doc(self, out: dict) -> dict:
        if self.doc:
            out["description"] = self.doc
        return out

    def fail(self, value: Any, mark: Mark | None, what: str, where: Where,
             extra: str = "") -> ConfigError:
        return where.error(f"{what} must be {self.expected}, got {type_name(value)}{extra}", mark)


@dataclass
class Number(Kind):
    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: float | None = None
    unit: str = ""
    doc: str = ""

    @property
    def expected(self) -> str:  # type: ignore[override]
        text = "a number"
        if self.exclusive_minimum is not None:
            text += f" greater than {self.exclusive_minimum:g}"
        elif self.minimum is not None and self.maximum is not None:
            text += f" from {self.minimum:g} to {self.maximum:g}"
        elif self.minimum is not None:
            text += f" of at least {self.minimum:g}"
        if self.unit:
            text += f" ({self.unit})"
        return text

    def accepts_type(self, value: Any) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool)

    def check(self, value, mark, what, where):
        if not self.accepts_type(value) or not math.isfinite(value):
            raise self.fail(value, mark, what, where)
        if ((self.minimum is not None and value < self.minimum)
                or (self.maximum is not None and value > self.maximum)
                or (self.exclusive_minimum is not None and value <= self.exclusive_minimum)):
            raise self.fail(value, mark, what, where)
        return float(value)

    def schema(self):
        out: dict = {"type": "number"}
        if self.minimum is not None:
            out["minimum"] = self.minimum
        if self.maximum is not None:
            out["maximum"] = self.maximum
        if self.exclusive_minimum is not None:
            out["exclusiveMinimum"] = self.exclusive_minimum
        return self._with_doc(out)


@dataclass
class Integer(Kind):
    minimum: int | None = None
    maximum: int | None = None
    doc: str = ""

    @property
    def expected(self) -> str:  # type: ignore[override]
        if self.minimum is not None and self.maximum is not None:
            return f"a whole number from {self.minimum} to {self.maximum}"
        if self.minimum is not None:
            return f"a whole number of at least {self.minimum}"
        return "a whole number"

    def accepts_type(self, value):
        return isinstance(value, int) and not isinstance(value, bool)

    def check(self, value, mark, what, where):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if not self.accepts_type(value):
            raise self.fail(value, mark, what, where)
        if ((self.minimum is not None and value < self.minimum)
                or (self.maximum is not None and value > self.maximum)):
            raise self.fail(value, mark, what, where)
        return int(value)

    def schema(self):
        out: dict = {"type": "integer"}
        if self.minimum is not None:
            out["minimum"] = self.minimum
        if self.maximum is not None:
            out["maximum"] = self.maximum
        return self._with_doc(out)


@dataclass
class Boolean(Kind):
    doc: str = ""
    expected: str = "true or false"

    def accepts_type(self, value):
        return isinstance(value, bool)

    def check(self, value, mark, what, where):
        if not isinstance(value, bool):
            raise self.fail(value, mark, what, where)
        return value

    def schema(self):
        return self._with_doc({"type": "boolean"})


@dataclass
class Text(Kind):
    pattern: str | None = None
    expected: str = "text"
    doc: str = ""

    def accepts_type(self, value):
        return isinstance(value, str)

    def check(self, value, mark, what, where):
        if isinstance(value, (int, float)) and not isinstance(value, bool) and self.pattern is None:
            value = str(value)  # a section called 2 is a name, not a mistake
        if not isinstance(value, str) or (self.pattern and not re.fullmatch(self.pattern, value)):
            raise self.fail(value, mark, what, where)
        return value

    def schema(self):
        out: dict = {"type": "string"}
        if self.pattern:
            out["pattern"] = f"^(?:{self.pattern})$"
        return self._with_doc(out)


@dataclass
class Choice(Kind):
    values: tuple[str, ...] = ()
    doc: str = ""

    @property
    def expected(self) -> str:  # type: ignore[override]
        return "one of " + ", ".join(self.values)

    def accepts_type(self, value):
        return isinstance(value, str)

    def check(self, value, mark, what, where):
        if isinstance(value, bool) and "true" in self.values:
            return "true" if value else "false"
        if not isinstance(value, str) or value not in self.values:
            hint = did_you_mean(value, self.values) if isinstance(value, str) else ""
            raise self.fail(value, mark, what, where, hint)
        return value

    def schema(self):
        return self._with_doc({"enum": list(self.values)})


@dataclass
class JointName(Kind):
    """One of the 25 joint names, a group (``hands``), or extra names (``body``)."""

    groups: bool = True
    extra: tuple[str, ...] = ()
    doc: str = ""

    @property
    def names(self) -> tuple[str, ...]:
        return (*JOINTS, *(GROUPS if self.groups else ()), *self.extra)

    @property
    def expected(self) -> str:  # type: ignore[override]
        return "a joint name (HandLeft, Head, FootRight, ...)" + (
            " or a group (hands, feet, ...)" if self.groups else "")

    def accepts_type(self, value):
        return isinstance(value, str)

    def check(self, value, mark, what, where):
        if not isinstance(value, str):
            raise self.fail(value, mark, what, where)
        if value in self.names:
            return value
        hint = suggest_joint(value)
        if hint is not None and hint not in self.names:
            hint = None
        if hint is None:
            close = difflib.get_close_matches(value, list(self.extra), n=1)
            hint = close[0] if close else None
        tail = f"; did you mean '{hint}'?" if hint else f"; expected {self.expected}"
        raise where.error(f"unknown joint '{value}'{tail}", mark)

    def schema(self):
        return self._with_doc({"enum": list(self.names)})


@dataclass
class ListOf(Kind):
    item: Kind = field(default_factory=Kind)
    min_items: int = 0
    max_items: int | None = None
    doc: str = ""
    #: items are called "<item_word> <n> of <owner>" in messages (e.g. "trigger 2 of section 'I'")
    item_word: str = ""

    @property
    def expected(self) -> str:  # type: ignore[override]
        if self.min_items and self.max_items == self.min_items:
            return f"a list of {self.min_items} ({self.item.expected})"
        return f"a list ({self.item.expected})"

    def accepts_type(self, value):
        return isinstance(value, list)

    def check(self, value, mark, what, where, owner: str | None = None):
        if not isinstance(value, list):
            raise self.fail(value, mark, what, where)
        if len(value) < self.min_items or (self.max_items is not None
                                           and len(value) > self.max_items):
            if not value and self.min_items == 1:
                raise where.error(f"{what} is empty; it needs at least one item",
                                  getattr(value, "mark", mark))
            if self.max_items == self.min_items:
                count = f"exactly {self.min_items}"
            elif self.max_items is None:
                count = f"at least {self.min_items}"
            else:
                count = f"{self.min_items} to {self.max_items}"
            raise where.error(f"{what} must have {count} item(s), got {len(value)}",
                              getattr(value, "mark", mark))
        marks = getattr(value, "marks", [mark] * len(value))
        out = MarkedList()
        out.mark, out.marks = getattr(value, "mark", mark), list(marks)
        for k, item in enumerate(value):
            name = (f"{self.item_word} {k + 1} of {owner}" if self.item_word and owner
                    else f"item {k + 1} of {what}")
            out.append(self.item.check(item, marks[k], name, where))
        return out

    def schema(self):
        out: dict = {"type": "array", "items": sub_schema(self.item)}
        if self.min_items:
            out["minItems"] = self.min_items
        if self.max_items is not None:
            out["maxItems"] = self.max_items
        return self._with_doc(out)


@dataclass
class Field:
    kind: Kind
    required: bool = False
    default: Any = None
    doc: str = ""


@dataclass
class Obj(Kind):
    """A mapping with known keys. ``one_of``: exactly one of these keys must be present."""

    name: str = ""
    fields: dict[str, Field] = field(default_factory=dict)
    one_of: tuple[str, ...] = ()
    one_of_what: str = ""
    doc: str = ""
    #: how an object is called in messages, from its own values (e.g. "trigger 'reach'")
    label: Callable[[dict, str], str] | None = None

    @property
    def expected(self) -> str:  # type: ignore[override]
        return "a mapping (key: value lines)"

    def accepts_type(self, value):
        return isinstance(value, dict)

    def check(self, value, mark, what, where):
        if not isinstance(value, dict):
            raise self.fail(value, mark, what, where)
        if self.label is not None:
            what = self.label(value, what)
        marks = getattr(value, "marks", {})
        value_marks = getattr(value, "value_marks", {})
        for key in value:
            if key not in self.fields:
                hint = did_you_mean(str(key), self.fields)
                tail = hint or f"; expected one of: {', '.join(self.fields)}"
                raise where.error(f"unknown key '{key}' in {what}{tail}", marks.get(key, mark))
        if self.one_of:
            present = [k for k in self.one_of if k in value]
            if not present:
                raise where.error(f"{what} needs one of: {', '.join(self.one_of)}"
                                  f"{self.one_of_what}", getattr(value, "mark", mark))
            if len(present) > 1:
                raise where.error(f"{what} has both '{present[0]}' and '{present[1]}'; "
                                  f"it takes only one of: {', '.join(self.one_of)}",
                                  marks.get(present[1], mark))
        out: dict[str, Any] = {}
        for key, spec in self.fields.items():
            if key not in value:
                if spec.required:
                    raise where.error(f"{what} needs '{key}' ({spec.kind.expected})",
                                      getattr(value, "mark", mark))
                if spec.default is not None:
                    out[key] = spec.default
                continue
            sub_mark = value_marks.get(key, mark)
            if isinstance(spec.kind, ListOf):
                out[key] = spec.kind.check(value[key], sub_mark, f"'{key}' of {what}", where,
                                           owner=what)
            else:
                out[key] = spec.kind.check(value[key], sub_mark, f"'{key}' in {what}", where)
        out["__mark__"] = getattr(value, "mark", mark)
        out["__marks__"] = dict(value_marks)
        out["__keymarks__"] = dict(marks)
        return out

    def schema(self):
        props = {}
        for key, spec in self.fields.items():
            sub = sub_schema(spec.kind)
            if spec.doc:
                sub = {**sub, "description": spec.doc}
            if spec.default is not None:
                sub = {**sub, "default": spec.default}
            props[key] = sub
        out: dict = {"type": "object", "properties": props, "additionalProperties": False}
        required = [k for k, f in self.fields.items() if f.required]
        if required:
            out["required"] = required
        if self.one_of:
            out["oneOf"] = [{"required": [k]} for k in self.one_of]
        return self._with_doc(out)


@dataclass
class MapOf(Kind):
    """Names chosen by the composer, each with a value of one kind (zones, phrases, outputs)."""

    value: Kind = field(default_factory=Kind)
    key_pattern: str = r"[A-Za-z0-9][A-Za-z0-9 _.'-]*"
    what_item: str = "entry"
    doc: str = ""

    expected: str = "a mapping of names"

    def accepts_type(self, value):
        return isinstance(value, dict)

    def check(self, value, mark, what, where):
        if value is None:
            return MarkedDict()
        if not isinstance(value, dict):
            raise where.error(f"{what} must be a mapping of names ({self.what_item} name: ...), "
                              f"got {type_name(value)}", mark)
        out = MarkedDict()
        marks = getattr(value, "marks", {})
        value_marks = getattr(value, "value_marks", {})
        out.mark, out.marks, out.value_marks = getattr(value, "mark", mark), marks, value_marks
        for key, item in value.items():
            if not isinstance(key, str) or not re.fullmatch(self.key_pattern, key):
                raise where.error(f"{self.what_item} name {type_name(key)} must be text starting "
                                  "with a letter or digit", marks.get(key, mark))
            out[key] = self.value.check(item, value_marks.get(key, mark),
                                        f"{self.what_item} '{key}'", where)
        return out

    def schema(self):
        sub = sub_schema(self.value)
        return self._with_doc({"type": "object", "propertyNames": {"pattern": f"^{self.key_pattern}$"},
                               "additionalProperties": sub})


@dataclass
class AnyOf(Kind):
    """A value that may take several shapes, chosen by its YAML type (a shorthand and a long form)."""

    options: tuple[Kind, ...] = ()
    doc: str = ""
    says: str = ""       # how messages describe the alternatives, when the options' words do not

    @property
    def expected(self) -> str:  # type: ignore[override]
        return self.says or " or ".join(o.expected for o in self.options)

    def accepts_type(self, value):
        return any(o.accepts_type(value) for o in self.options)

    def check(self, value, mark, what, where):
        for option in self.options:
            if option.accepts_type(value):
                if isinstance(option, (Obj, ListOf, MapOf, JointName)):
                    return option.check(value, mark, what, where)  # its own precise messages
                try:
                    return option.check(value, mark, what, where)
                except ConfigError:
                    # name every alternative, not just the one the value's type picked
                    words = [w for o in self.options if isinstance(o, Choice) for w in o.values]
                    hint = did_you_mean(value, words) if isinstance(value, str) and words else ""
                    raise self.fail(value, mark, what, where, hint) from None
        raise self.fail(value, mark, what, where)

    def schema(self):
        subs = [sub_schema(o) for o in self.options]
        return self._with_doc({"anyOf": subs})


def sub_schema(kind: Kind) -> dict:
    """A named object's ``$ref``, or any other kind's schema inline."""
    if isinstance(kind, Obj) and kind.name:
        return {"$ref": f"#/$defs/{kind.name}"}
    return kind.schema()


def reachable_objects(root: Kind) -> list[Obj]:
    """Every ``Obj`` reachable from ``root`` (named or not), each once, root first."""
    found: dict[int, Obj] = {}

    def walk(kind: Kind) -> None:
        if isinstance(kind, Obj):
            if id(kind) in found:
                return
            found[id(kind)] = kind
            for spec in kind.fields.values():
                walk(spec.kind)
        elif isinstance(kind, ListOf):
            walk(kind.item)
        elif isinstance(kind, MapOf):
            walk(kind.value)
        elif isinstance(kind, AnyOf):
            for option in kind.options:
                walk(option)

    walk(root)
    return list(found.values())


def definitions(root: Kind) -> dict[str, dict]:
    """Every named ``Obj`` reachable from ``root``, as JSON Schema ``$defs``."""
    found = {obj.name: obj for obj in reachable_objects(root) if obj.name and obj is not root}
    return {name: obj.schema() for name, obj in sorted(found.items())}
