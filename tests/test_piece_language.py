"""The piece language: note names, phrases in bars, the loader's model, and the JSON
Schema generated from the same definitions (shipped, and up to date)."""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import pytest
import yaml

from stage.errors import ConfigError, MusicError
from stage.piece import load_piece, loads_piece
from stage.piece.music import parse_chord, parse_pitch, phrase_notes
from stage.piece.schema import PACKAGE_COPY, PIECES_COPY, main as schema_main, schema_text

REPO = Path(__file__).resolve().parents[1]
PIECES = sorted(p for p in (REPO / "pieces").glob("*.yaml") if not p.name.endswith(".sim.yaml"))


# ------------------------------------------------------------------ music
@pytest.mark.parametrize("name, midi", [("C4", 60), ("A4", 69), ("G2", 43), ("D3", 50),
                                        ("F#3", 54), ("Bb2", 46), ("C#4", 61), ("Cb4", 59),
                                        ("E##3", 54), ("c-1", 0), ("G9", 127), ("55", 55)])
def test_pitch_names(name, midi):
    assert parse_pitch(name) == midi


@pytest.mark.parametrize("bad", ["H3", "C", "G10", "Cb-1", "128", "C4#", ""])
def test_bad_pitches(bad):
    with pytest.raises(MusicError):
        parse_pitch(bad)


def test_chords_durations_rests_and_carried_durations():
    assert parse_chord("G2+D3+B3") == (43, 50, 59)
    notes = phrase_notes(["G2+D3+B3 1", "F#3 1/4", "A3", "rest 1/2", "C4 3/8 v90"], False, None)
    assert [(n.onset, n.length, n.pitches, n.velocity) for n in notes] == [
        (0, 1, (43, 50, 59), None), (1, Fraction(1, 4), (54,), None),
        (Fraction(5, 4), Fraction(1, 4), (57,), None), (Fraction(3, 2), Fraction(1, 2), (), None),
        (2, Fraction(3, 8), (60,), 90)]


def test_bars_must_fill_the_meter():
    notes = phrase_notes(["D4 1/2, F3, E3 13/16, D3 1/16, C3, B2, C3 1/2, E3"], True, "3/4")
    assert sum(n.length for n in notes) == 3
    with pytest.raises(MusicError, match=r"bar 2 has 2\.5 beats; the meter 3/4 needs 3"):
        phrase_notes(["G3 3", "G3 1, A3 3/2"], True, "3/4")
    assert sum(n.length for n in phrase_notes(["G3 3/2, A3 3/2"], True, "6/8")) == 3


def test_liminal_phrases_are_bars_of_the_sarabande():
    """Every phrase of Liminal Space is a whole bar of 3/4 in G major's range of the cello."""
    piece = load_piece(REPO / "pieces" / "liminal.yaml")
    assert piece.meter == "3/4"
    for name, phrase in piece.phrases.items():
        assert phrase.length_beats() == 3, name
        pitches = [p for n in phrase.notes for p in n.pitches]
        assert all(36 <= p <= 62 for p in pitches), name          # C2 .. D4: the cello
    opening = piece.phrases["bar1"].notes
    assert opening[0].pitches == (43, 50, 59)                       # G2 D3 B3
    assert [n.length for n in opening] == [1, Fraction(3, 2), Fraction(1, 2)]
    assert piece.phrases["final"].notes[-1].pitches == (43,)        # ends on G2
    sets = [set(s.phrases) for s in piece.sections]
    assert all(not (a & b) for i, a in enumerate(sets) for b in sets[i + 1:])  # own phrases


# ------------------------------------------------------------------ the model
def test_defaults_and_shorthands():
    piece = loads_piece("""
piece: p
sections:
  - name: s
    triggers:
      - {enters: z, do: [note: G3]}
zones:
  z: {shape: sphere, centre: [0, 1, 0], radius: 0.5}
""")
    assert list(piece.outputs) == ["midi"]                      # a default MIDI output
    trig = piece.sections[0].triggers[0]
    assert trig.name == "body enters z" and trig.cooldown == 0.5 and trig.hysteresis == 0.05
    assert trig.joints == (-1,)
    assert piece.zones["z"].contains(0, 1.4, 0) and not piece.zones["z"].contains(0, 1.6, 0)
    assert piece.zones["z"].contains(0, 1.52, 0, margin=0.05)


def test_every_key_of_the_language_is_documented():
    """docs/pieces.md names every key the loader accepts (in `backticks`)."""
    import re
    from stage.piece.language import PIECE
    from stage.piece.spec import reachable_objects
    doc = (REPO / "docs" / "pieces.md").read_text(encoding="utf-8")
    objects = {id(o): o for o in reachable_objects(PIECE)}
    missing = sorted({f"{o.name or 'Piece'}.{key}" for o in objects.values() for key in o.fields
                      if not re.search(r"`[^`]*\b" + re.escape(key) + r"\b[^`]*`", doc)})
    assert missing == [], f"not documented in docs/pieces.md: {missing}"


def test_every_shipped_piece_loads():
    assert {p.name for p in PIECES} >= {"liminal.yaml", "circles.yaml", "arms.yaml"}
    for path in PIECES:
        piece = load_piece(path)
        assert piece.sections


# ------------------------------------------------------------------ the JSON Schema
def test_shipped_schema_files_are_up_to_date():
    text = schema_text()
    assert PACKAGE_COPY.read_text(encoding="utf-8") == text, \
        "stage/piece/piece.schema.json is stale: run python -m stage.piece.schema"
    assert PIECES_COPY.read_text(encoding="utf-8") == text, \
        "pieces/piece.schema.json is stale: run python -m stage.piece.schema"
    assert schema_main(["--check"]) == 0


def test_the_schema_covers_the_language():
    schema = json.loads(schema_text())
    trigger = schema["$defs"]["Trigger"]
    assert trigger["additionalProperties"] is False
    assert {"enters", "rises_above", "hand", "step", "cooldown", "while", "do"} <= set(
        trigger["properties"])
    assert "HandLeft" in trigger["properties"]["joint"]["enum"]
    assert {"required": ["enters"]} in trigger["oneOf"]
    assert schema["required"] == ["piece", "sections"]


def _validator():
    # only these tests need it (a test extra): a module-level skip would hide the whole file
    jsonschema = pytest.importorskip("jsonschema", reason="pip install jsonschema (test extra)")
    schema = json.loads(schema_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


@pytest.mark.parametrize("path", PIECES, ids=[p.name for p in PIECES])
def test_shipped_pieces_validate_against_the_schema(path):
    errors = list(_validator().iter_errors(yaml.safe_load(path.read_text(encoding="utf-8"))))
    assert errors == []


@pytest.mark.parametrize("edit", [
    ("cooldown: 2.5", "cooldwn: 2.5"),                 # an unknown key
    ("joint: HandLeft", "joint: Handleft"),            # an unknown joint
    ("shape: cylinder", "shape: cylindre"),            # an unknown shape
    ("rises_above: Head", "rises_above: Head\n        hand: open"),   # two things to watch
    ("cooldown: 2.5", "cooldown: -1"),                 # a negative time
])
def test_schema_and_loader_reject_the_same_mistakes(edit, tmp_path):
    text = (REPO / "pieces" / "liminal.yaml").read_text(encoding="utf-8").replace(*edit, 1)
    assert list(_validator().iter_errors(yaml.safe_load(text)))
    bad = tmp_path / "bad.yaml"
    bad.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError):
        load_piece(bad)
