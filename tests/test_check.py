"""`stage check`: a summary for good pieces, and for mistakes one exact line with
file:line:column that says what was expected, exit status 2.

Each mistake is one edit of a small valid piece (``BASE``); the expected
message is the whole line the user sees on stderr.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from stage.cli.main import main

REPO = Path(__file__).resolve().parents[1]

BASE = """\
piece: test
meter: 3/4
outputs: {cello: midi, space: osc}
zones:
  centre: {shape: cylinder, centre: [0, 0], radius: 0.8}
phrases:
  a: {notes: [G3 1, A3 1/2]}
  b: {bars: ["G2+D3+B3 1, G2+E3+C4 3/2, B3 1/2"]}
sections:
  - name: one
    phrases: [a, b]
    triggers:
      - name: reach
        joint: HandLeft
        rises_above: 1.5
        cooldown: 2
        do:
          - play: random
          - osc: {address: /reach, args: [$y]}
  - name: two
    mappings:
      - {name: pan, joint: body, measure: x, in_range: [-2, 2], osc: /pan}
"""

# (what is wrong, text to replace, replacement, expected message after "FILE:")
MISTAKES = [
    ("misspelt joint", "joint: HandLeft", "joint: Handleft",
     "14:16: unknown joint 'Handleft'; did you mean 'HandLeft'?"),
    ("unknown key in a trigger", "cooldown: 2", "cooldwn: 2",
     "16:9: unknown key 'cooldwn' in trigger 'reach'; did you mean 'cooldown'?"),
    ("unknown key at the top", "meter: 3/4", "metre: 3/4",
     "2:1: unknown key 'metre' in the piece; did you mean 'meter'?"),
    ("zone that does not exist", "rises_above: 1.5", "enters: centr",
     "15:17: zone 'centr' is not defined; did you mean 'centre'?"),
    ("phrase that does not exist", "phrases: [a, b]", "phrases: [a, c]",
     "11:18: phrase 'c' is not defined; defined: a, b"),
    ("section that does not exist", "- play: random", "- goto: three",
     "18:19: section 'three' is not defined; defined: one, two (or next, previous, end)"),
    ("not a pitch", "notes: [G3 1, A3 1/2]", "notes: [G3 1, H3 1/2]",
     "7:21: phrase 'a': 'H3' is not a pitch: expected a note name with its octave (C4, F#3, "
     "Bb2) or a MIDI number 0-127"),
    ("bar that does not fill the meter", '"G2+D3+B3 1, G2+E3+C4 3/2, B3 1/2"',
     '"G2+D3+B3 1, G2+E3+C4 3/2, B3 1/4"',
     "8:14: phrase 'b': bar 1 has 2.75 beats; the meter 3/4 needs 3"),
    ("a number that is text", "cooldown: 2", "cooldown: soon",
     "16:19: 'cooldown' in trigger 'reach' must be a number of at least 0 (seconds), got 'soon'"),
    ("a negative radius", "radius: 0.8", "radius: -0.8",
     "5:53: 'radius' in zone 'centre' must be a number greater than 0 (metres), got the "
     "number -0.8"),
    ("misspelt shape", "shape: cylinder", "shape: cylindre",
     "5:19: 'shape' in zone 'centre' must be one of box, cylinder, sphere, got 'cylindre'; "
     "did you mean 'cylinder'?"),
    ("two things to watch", "        cooldown: 2\n", "        cooldown: 2\n        hand: open\n",
     "17:9: trigger 'reach' has both 'rises_above' and 'hand'; it takes only one of: enters, "
     "leaves, dwells, speed_above, moves, rises_above, falls_below, hand, step, appears, "
     "disappears, stage_empty, elapsed"),
    ("nothing to watch", "        rises_above: 1.5\n", "",
     "13:9: trigger 'reach' needs one of: enters, leaves, dwells, speed_above, moves, "
     "rises_above, falls_below, hand, step, appears, disappears, stage_empty, elapsed "
     "(what to watch for)"),
    ("no actions", "        do:\n          - play: random\n          - osc: {address: /reach, "
     "args: [$y]}\n", "        do: []\n",
     "17:13: 'do' of trigger 'reach' is empty; it needs at least one item"),
    ("OSC to a MIDI output", "{address: /reach, args: [$y]}",
     "{address: /reach, args: [$y], output: cello}",
     "19:18: output 'cello' is MIDI; an OSC message needs an OSC output"),
    ("bad joint reference in OSC arguments", "args: [$y]", "args: [$HandLft.y]",
     "19:43: unknown joint 'HandLft' in '$HandLft.y'; did you mean '$HandLeft.y'?"),
    ("hand trigger on a head", "        joint: HandLeft\n        rises_above: 1.5\n",
     "        joint: Head\n        hand: closed\n",
     "14:16: a hand trigger watches a hand: use HandLeft, HandRight or hands, not 'Head'"),
    ("mapping without a range", "in_range: [-2, 2], ", "",
     "22:9: mapping 'pan' needs 'in_range' ([from, to].)".replace(" ([from, to].)",
                                                               " (a list of 2 (a number))")),
    ("misspelt performer", "        cooldown: 2\n", "        cooldown: 2\n        performer: "
     "dancer\n", "17:20: 'performer' in trigger 'reach' must be any, first, newest or a "
                 "person id, got 'dancer'"),
    ("YAML syntax", "piece: test", "piece: test\n  oops: 1",
     "2:7: YAML syntax: mapping values are not allowed in this context"),
    ("duplicate key", "meter: 3/4", "meter: 3/4\nmeter: 6/8",
     "3:1: duplicate key 'meter'"),
    ("two sections with one name", "  - name: two", "  - name: one",
     "20:11: two sections are called 'one'; names must differ"),
]


def check(tmp_path: Path, text: str, capsys) -> tuple[int, str, str, Path]:
    path = tmp_path / "piece.yaml"
    path.write_text(text, encoding="utf-8")
    status = main(["check", str(path)])
    out, err = capsys.readouterr()
    return status, out, err, path


def test_the_base_piece_is_valid_and_summarised(tmp_path, capsys):
    status, out, err, path = check(tmp_path, BASE, capsys)
    assert status == 0 and err == ""
    lines = out.splitlines()
    assert lines[0] == f'{path}: ok -- "test", 2 section(s), 1 zone(s), 2 phrase(s)'
    assert "  1. one: 2 phrase(s), 1 trigger(s), 0 mapping(s)  (start)" in lines
    assert ("       'reach': HandLeft rises above 1.5 m -> play random; osc /reach $y  "
            "(cooldown 2 s)") in lines
    assert "       'pan': body x -2..2 -> osc /pan on space 0..1" in lines


@pytest.mark.parametrize("what, old, new, message", MISTAKES, ids=[m[0] for m in MISTAKES])
def test_each_mistake_gets_one_exact_line(tmp_path, capsys, what, old, new, message):
    assert BASE.count(old) == 1, f"the test's edit is ambiguous: {old!r}"
    status, out, err, path = check(tmp_path, BASE.replace(old, new), capsys)
    assert status == 2
    assert out == ""
    assert err == f"stage: {path}:{message}\n"


def test_distinct_mistakes_are_at_least_ten():
    assert len({m[3] for m in MISTAKES}) >= 10


def test_missing_and_empty_files(tmp_path, capsys):
    empty = tmp_path / "empty.yaml"
    empty.write_text("", encoding="utf-8")
    assert main(["check", str(empty)]) == 2
    assert capsys.readouterr().err == (f"stage: {empty}: the file is empty; a piece needs at "
                                       "least 'piece' and 'sections'\n")
    missing = tmp_path / "missing.yaml"
    assert main(["check", str(missing)]) == 2
    assert capsys.readouterr().err == f"stage: {missing}: no such file\n"


def test_the_real_command_checks_every_shipped_piece():
    pieces = sorted(str(p) for p in (REPO / "pieces").glob("*.yaml")
                    if not p.name.endswith(".sim.yaml"))
    assert len(pieces) >= 3
    done = subprocess.run([sys.executable, "-m", "stage.cli", "check", *pieces],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.count(": ok -- ") == len(pieces)


def test_the_real_command_exits_2_with_one_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(BASE.replace("joint: HandLeft", "joint: Handleft"), encoding="utf-8")
    done = subprocess.run([sys.executable, "-m", "stage.cli", "check", str(bad)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr == f"stage: {bad}:14:16: unknown joint 'Handleft'; did you mean 'HandLeft'?\n"
    assert "Traceback" not in done.stderr
