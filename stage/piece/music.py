"""Notes, chords and phrases: from a composer's text to timed MIDI notes.

Pitches are scientific names (``C4`` = MIDI 60 = middle C, ``F#3``, ``Bb2``)
or MIDI numbers. A phrase item reads ``PITCH[+PITCH...] [BEATS] [vVELOCITY]``:
``G2+D3+B3 1`` is a chord of one beat, ``F#3 1/4`` a sixteenth in 3/4,
``rest 1/2`` a rest; an item without a duration keeps the previous one, as
in LilyPond. A beat is a quarter note and ``tempo`` counts beats per minute.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from fractions import Fraction

from ..errors import MusicError

_STEPS = {"C": 0, "D": 2, "E": 4, "F": 5, "G": 7, "A": 9, "B": 11}
_ACCIDENTALS = {"": 0, "#": 1, "##": 2, "b": -1, "bb": -2}
_PITCH = re.compile(r"([A-Ga-g])(##|#|bb|b)?(-?\d)")
_DURATION = re.compile(r"(\d+(?:\.\d*)?|\.\d+)(?:/(\d+))?")
_NAMES = ("C", "C#", "D", "Eb", "E", "F", "F#", "G", "Ab", "A", "Bb", "B")


def parse_pitch(text: str | int) -> int:
    """'G2' -> 43, 'F#3' -> 54, 'Bb2' -> 46, 60 -> 60. MusicError if not a pitch 0-127."""
    if isinstance(text, int) and not isinstance(text, bool):
        if 0 <= text <= 127:
            return text
        raise MusicError(f"MIDI note {text} is out of range 0-127")
    token = str(text).strip()
    if token.isdigit():
        return parse_pitch(int(token))
    match = _PITCH.fullmatch(token)
    if match is None:
        raise MusicError(f"'{token}' is not a pitch: expected a note name with its octave "
                         "(C4, F#3, Bb2) or a MIDI number 0-127")
    letter, accidental, octave = match.groups()
    midi = 12 * (int(octave) + 1) + _STEPS[letter.upper()] + _ACCIDENTALS[accidental or ""]
    if not 0 <= midi <= 127:
        raise MusicError(f"'{token}' is outside the MIDI range (C-1 to G9)")
    return midi


def parse_chord(text: str | int) -> tuple[int, ...]:
    """'G2+D3+B3' -> (43, 50, 59); a single pitch -> a 1-tuple."""
    if isinstance(text, int) and not isinstance(text, bool):
        return (parse_pitch(text),)
    parts = [p for p in str(text).split("+")]
    if any(not p.strip() for p in parts):
        raise MusicError(f"'{text}' is not a chord: expected pitches joined by '+' (G2+D3+B3)")
    return tuple(parse_pitch(p) for p in parts)


def pitch_name(midi: int) -> str:
    """60 -> 'C4' (flats for black keys except F#/C#)."""
    return f"{_NAMES[midi % 12]}{midi // 12 - 1}"


def parse_duration(text: str) -> Fraction:
    """'1', '1.5', '3/4', '.5' -> Fraction; MusicError when not a positive duration."""
    match = _DURATION.fullmatch(text)
    if match is None:
        raise MusicError(f"'{text}' is not a duration: expected beats like 1, 1.5, 1/4 or 3/8")
    value = Fraction(match.group(1))
    if match.group(2) is not None:
        if int(match.group(2)) == 0:
            raise MusicError(f"'{text}' divides by zero")
        value /= int(match.group(2))
    if value <= 0:
        raise MusicError(f"'{text}': a duration must be greater than 0")
    return value


@dataclass(frozen=True, slots=True)
class PhraseNote:
    """One onset of a phrase: a note or chord (``pitches`` empty for a rest)."""

    onset: Fraction           # beats (or seconds) from the phrase's start
    length: Fraction          # its value: time to the next onset
    pitches: tuple[int, ...]
    velocity: int | None      # None: the phrase's velocity


def parse_item(text: str | int, previous: Fraction) -> tuple[tuple[int, ...], Fraction, int | None]:
    """One phrase item -> (pitches, length, velocity). ``previous``: the length to keep."""
    if isinstance(text, int) and not isinstance(text, bool):
        return (parse_pitch(text),), previous, None
    tokens = str(text).split()
    if not tokens:
        raise MusicError("an empty note: expected 'PITCH [BEATS] [vVELOCITY]', e.g. 'G3 1/2'")
    head, rest = tokens[0], tokens[1:]
    pitches = () if head.lower() in ("r", "rest") else parse_chord(head)
    length, velocity = previous, None
    for token in rest:
        if token[:1] in ("v", "V") and token[1:].isdigit():
            if velocity is not None:
                raise MusicError(f"'{text}' has two velocities")
            velocity = int(token[1:])
            if not 1 <= velocity <= 127:
                raise MusicError(f"velocity {velocity} in '{text}' must be 1-127")
        elif velocity is None and length is previous:
            length = parse_duration(token)
        else:
            raise MusicError(f"'{text}': unexpected '{token}'; expected 'PITCH [BEATS] "
                             "[vVELOCITY]', e.g. 'G3 1/2 v90'")
    return pitches, length, velocity


def meter_beats(meter: str) -> Fraction:
    """Quarter-note beats in one bar: '3/4' -> 3, '6/8' -> 3, '2/2' -> 4."""
    top, bottom = meter.split("/")
    return Fraction(int(top) * 4, int(bottom))


def phrase_notes(items: list, bars: bool, meter: str | None) -> list[PhraseNote]:
    """Parse a phrase's ``notes`` (one item each) or ``bars`` (comma-separated per bar).

    Raises MusicError with ``.index`` (the item's position) set, so the loader
    can point at the line of the faulty item.
    """
    out: list[PhraseNote] = []
    onset, previous = Fraction(0), Fraction(1)
    for index, item in enumerate(items):
        try:
            if bars:
                start = onset
                for part in str(item).split(","):
                    pitches, previous, velocity = parse_item(part, previous)
                    out.append(PhraseNote(onset, previous, pitches, velocity))
                    onset += previous
                if meter is not None:
                    need = meter_beats(meter)
                    if onset - start != need:
                        raise MusicError(f"bar {index + 1} has {_beats(onset - start)} beats; "
                                         f"the meter {meter} needs {_beats(need)}")
            else:
                pitches, previous, velocity = parse_item(item, previous)
                out.append(PhraseNote(onset, previous, pitches, velocity))
                onset += previous
        except MusicError as exc:
            exc.index = index  # type: ignore[attr-defined]
            raise
    return out


def _beats(value: Fraction) -> str:
    return str(value.numerator) if value.denominator == 1 else \
        f"{float(value):g}" if value.denominator in (2, 4, 8) else str(value)
