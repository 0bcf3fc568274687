"""What a piece asks the outputs to do: the contract between the piece runtime and views.

The piece runtime (engine thread) turns fused bodies into these events; views
(MIDI, OSC, monitor, ...) turn them into sound and pictures. Every event has
``t``, the engine-clock time (seconds) at which it should take effect: "now"
for most, later for the notes of a phrase, so a view can schedule precisely
instead of on the next frame. ``output`` names an output declared in the
piece (``outputs:``); views are bound to output names, never the reverse.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Protocol, Union


@dataclass(frozen=True, slots=True)
class Note:
    """A note with its own note-off: on at ``t``, off at ``t + duration``."""

    t: float
    output: str
    channel: int      # 0-15 (MIDI channel 1-16 in the piece file)
    note: int         # 0-127
    velocity: int     # 1-127
    duration: float   # seconds, > 0
    play: int = 0     # the PhrasePlayed it belongs to (its ``id``); 0: none


@dataclass(frozen=True, slots=True)
class ControlChange:
    t: float
    output: str
    channel: int
    control: int      # 0-127
    value: int        # 0-127


@dataclass(frozen=True, slots=True)
class ProgramChange:
    t: float
    output: str
    channel: int
    program: int      # 0-127


@dataclass(frozen=True, slots=True)
class AllNotesOff:
    """Silence an output (one channel, or all when ``channel`` is None); pending notes are cancelled."""

    t: float
    output: str | None = None   # None: every output
    channel: int | None = None


@dataclass(frozen=True, slots=True)
class OscOut:
    """An OSC message the piece sends to a named OSC output."""

    t: float
    output: str
    address: str
    args: tuple[Any, ...] = ()


@dataclass(frozen=True, slots=True)
class SectionChange:
    t: float
    section: str
    previous: str | None
    index: int        # position of ``section`` in the piece, 0-based
    cause: str = ""   # the trigger that moved on, or "operator" / "start"


@dataclass(frozen=True, slots=True)
class TriggerFired:
    """A trigger fired (for logs, ``--events`` files and the monitor)."""

    t: float
    section: str
    trigger: str
    person: int | None = None
    joint: str | None = None
    value: float | None = None
    #: > 0: fired on a crossing predicted this many seconds ahead, not yet measured
    anticipated: float = 0.0


@dataclass(frozen=True, slots=True)
class TriggerContradicted:
    """A trigger fired on a predicted crossing that the measurements did not make in time
    (docs/anticipation.md); ``fired``: when it fired; ``cut``: its notes were cut short."""

    t: float
    section: str
    trigger: str
    person: int | None
    joint: str | None
    fired: float
    cut: bool = False


@dataclass(frozen=True, slots=True)
class PhrasePlayed:
    """A phrase (or a note action) was scheduled on an output (for logs and scores).

    ``t``: when it starts (on the grid when quantised; later when it waited for
    another phrase); ``decided``: when its trigger fired; ``end``: ``t`` plus its
    musical length. Its notes carry ``play == id``.
    """

    t: float
    output: str
    phrase: str
    id: int
    section: str
    trigger: str
    end: float
    notes: int
    decided: float
    policy: str = "queue"


@dataclass(frozen=True, slots=True)
class PhraseSkipped:
    """A firing asked for a phrase that was not played (its output's policy said no)."""

    t: float
    output: str
    phrase: str
    section: str
    trigger: str
    why: str


@dataclass(frozen=True, slots=True)
class NoteCut:
    """A note did not sound as scheduled: ``sounded`` 0 means it was cancelled before
    its onset; otherwise it was cut short after ``sounded`` of its ``duration`` seconds.

    ``t``: when it was cut; ``onset``: the note's own time; ``why``: "silence",
    "replace", "stop", or "struck again" (the same key started by another phrase).
    """

    t: float
    output: str
    channel: int
    note: int
    onset: float
    duration: float
    sounded: float
    play: int = 0
    why: str = ""


@dataclass(frozen=True, slots=True)
class MappingValue:
    """A continuous mapping's current output value (sent on change)."""

    t: float
    mapping: str
    value: float


@dataclass(frozen=True, slots=True)
class ZoneState:
    """A zone became occupied or empty (sent on change, for monitors and logs)."""

    t: float
    zone: str
    occupied: bool
    persons: tuple[int, ...] = ()


Event = Union[Note, ControlChange, ProgramChange, AllNotesOff, OscOut, SectionChange,
              TriggerFired, TriggerContradicted, MappingValue, ZoneState, PhrasePlayed,
              PhraseSkipped, NoteCut]


def to_json(event: Event) -> dict[str, Any]:
    """A JSON-ready dict: {"type": "Note", "t": ..., ...} (one line per event in --events files)."""
    out: dict[str, Any] = {"type": type(event).__name__}
    for f in dataclasses.fields(event):
        value = getattr(event, f.name)
        out[f.name] = list(value) if isinstance(value, tuple) else value
    return out


@dataclass(frozen=True, slots=True)
class OutputDecl:
    """An output a piece declares: where its events go, bound to a view at play time.

    kind "midi": ``target`` is a MIDI port name, or None for the command line's
    choice (--midi PORT / --midi-file OUT.mid / a new virtual port). kind "osc":
    ``target`` is "host:port", or None for the command line's --osc; its target
    gets only the piece's messages unless ``skeletons`` asks for the bodies too.
    """

    name: str
    kind: str                 # "midi" or "osc"
    target: str | None = None
    skeletons: bool = False   # osc: the target also gets the Server-to-View API (bodies)


class EventSink(Protocol):
    def emit(self, events: list[Event]) -> None:
        """Take events from the engine thread; must not block (queue and return)."""
