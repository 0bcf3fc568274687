"""Musical time and voices: the beat grid, quantised starts, the overlap policies, broken
chords, and the honest account of what sounded -- checked against the MIDI view's own
scheduler fed the same events (the two must agree note for note)."""

from __future__ import annotations

import math

import pytest

from stage.errors import ConfigError
from stage.events import AllNotesOff, Note, NoteCut, PhrasePlayed, PhraseSkipped
from stage.piece import PieceRuntime, RecordingSink, loads_piece
from stage.piece.model import voice_times
from stage.piece.voices import Grid
from stage.testing.script import ScriptedStage, standing
from stage_plugins.midi.schedule import NOTE_ON, MidiScheduler

HEAD = """
piece: voices
tempo: 120                 # a beat is 0.5 s
meter: 3/4                 # a bar is 1.5 s
outputs:
  solo: {type: midi, overlap: OVERLAP}
phrases:
  long: {notes: ["C4 2", "E4 2"], output: solo}          # 2 s
  low: {notes: ["C4 1", "G3 1"], output: solo}           # 1 s, C4 again
  chord: {notes: ["G2+D3+B3+G4 2"], output: solo, arpeggiate: 0.05, gate: 1.0}
"""


def make(overlap: str, triggers: str, extra: str = ""):
    piece = loads_piece(HEAD.replace("OVERLAP", overlap) + extra + f"""
sections:
  - name: one
    triggers:
{triggers}
""")
    sink = RecordingSink()
    runtime = PieceRuntime(piece, sink, seed=1)
    return runtime, sink, ScriptedStage(runtime)


TWO_HANDS = """
      - {name: left, joint: HandLeft, rises_above: 1.5, cooldown: 0, do: [play: long]}
      - {name: right, joint: HandRight, rises_above: 1.5, cooldown: 0, do: [play: low]}
"""


def hands(stage, left_at: float, right_at: float, until: float = 6.0, t0: float = 0.0):
    up = lambda t, at: math.pi if t >= at else 0.0
    stage.run(t0, until, lambda t: {1: standing(0, 0, left_arm=up(t, left_at),
                                                right_arm=up(t, right_at))})


def midi_agrees(sink: RecordingSink, runtime: PieceRuntime) -> MidiScheduler:
    """The MIDI view's scheduler, fed every event: it must sound what the runtime says."""
    sched = MidiScheduler()
    for e in sink.events:
        sched.add(e, now=e.t)
    out = sched.due(math.inf)
    ons = [o for o in out if o.data[0] & 0xF0 == NOTE_ON and o.data[2] > 0]
    assert len(ons) == runtime.counts["notes"]
    assert sched.stats["cancelled"] == runtime.counts["cancelled"]
    struck = [c for c in sink.of(NoteCut) if c.why.startswith("struck again")]
    assert sched.stats["retriggered"] == len(struck)
    return sched


# ------------------------------------------------------------------ the grid
def test_grid_beats_bars_and_where():
    grid = Grid(10.0, 120.0, 3.0)
    assert grid.next(10.0, "beat") == 10.0 and grid.next(10.01, "beat") == 10.5
    assert grid.next(10.01, "bar") == 11.5 and grid.next(11.5, "bar") == 11.5
    assert grid.next(10.3, "none") == 10.3 and grid.next(10.3, None) == 10.3
    assert grid.on(13.0, "bar") and not grid.on(13.5, "bar") and grid.on(13.5, "beat")
    assert grid.where(13.5) == "bar 3 beat 2"


def test_quantised_phrases_start_on_the_next_beat_or_bar():
    for unit, step in (("beat", 0.5), ("bar", 1.5)):
        runtime, sink, stage = make("layer", TWO_HANDS, extra=f"quantize: {unit}\n")
        hands(stage, 0.75, 99.0, until=2.0)
        (played,) = sink.of(PhrasePlayed)
        assert played.decided > 0.75 and played.t == pytest.approx(
            math.ceil(played.decided / step) * step)
        assert min(n.t for n in sink.of(Note)) == pytest.approx(played.t)


def test_quantize_bar_needs_a_meter():
    with pytest.raises(ConfigError, match=r"'quantize: bar' in the piece needs the piece's "
                                          r"'meter'"):
        loads_piece("piece: x\nquantize: bar\nsections: [{name: a}]\n")
    piece = loads_piece(HEAD.replace("OVERLAP", "queue") + """
sections:
  - name: one
    quantize: bar
    triggers:
      - {name: t, joint: HandLeft, rises_above: 1.5, quantize: none, do: [play: long]}
""")
    assert piece.quantize == "none" and piece.sections[0].quantize == "bar"
    assert piece.sections[0].triggers[0].quantize == "none"


# ------------------------------------------------------------------ the policies
def test_queue_waits_for_the_sounding_phrase_and_nothing_is_cut():
    runtime, sink, stage = make("queue", TWO_HANDS)
    hands(stage, 0.5, 1.0)
    first, second = sink.of(PhrasePlayed)
    assert (first.phrase, second.phrase) == ("long", "low")
    assert second.t == pytest.approx(first.end) and second.decided < first.end
    assert not sink.of(NoteCut) and runtime.counts["notes"] == 4
    midi_agrees(sink, runtime)


def test_queue_does_not_pile_up_a_hesitating_trigger():
    runtime, sink, stage = make("queue", """
      - {name: left, joint: HandLeft, rises_above: 1.5, cooldown: 0, hysteresis: 0.01,
         do: [play: long]}
""")
    arm = lambda t: math.pi if (0.5 <= t < 0.8 or 1.0 <= t < 1.3 or 1.5 <= t < 1.8) else 0.0
    stage.run(0.0, 6.0, lambda t: {1: standing(0, 0, left_arm=arm(t))})
    assert [p.phrase for p in sink.of(PhrasePlayed)] == ["long", "long"]  # sounding + waiting
    (skipped,) = sink.of(PhraseSkipped)
    assert skipped.why == "its previous phrase is still waiting (queue)"
    assert runtime.counts["skipped"] == 1


def test_layer_sounds_at_once_and_reports_a_key_struck_again():
    runtime, sink, stage = make("layer", TWO_HANDS)
    hands(stage, 0.5, 1.0)                     # 'low' strikes C4 while 'long' holds it
    first, second = sink.of(PhrasePlayed)
    assert second.t == pytest.approx(second.decided)
    (cut,) = sink.of(NoteCut)
    assert cut.note == 60 and cut.why == "struck again by low"
    assert cut.onset == pytest.approx(first.t) and cut.sounded == pytest.approx(second.t - first.t)
    assert runtime.counts["shortened"] == 1
    midi_agrees(sink, runtime)


def test_replace_cuts_the_sounding_phrase_and_cancels_what_had_not_begun():
    runtime, sink, stage = make("replace", TWO_HANDS)
    hands(stage, 0.5, 1.0)
    first, second = sink.of(PhrasePlayed)
    (off,) = sink.of(AllNotesOff)
    assert off.t == pytest.approx(second.t) and off.output == "solo"
    cuts = sink.of(NoteCut)
    assert [(c.note, c.sounded > 0) for c in cuts] == [(60, True), (64, False)]
    assert all(c.why == "replaced by low" for c in cuts)
    assert runtime.counts == {**runtime.counts, "notes": 3, "cancelled": 1, "shortened": 1}
    midi_agrees(sink, runtime)


def test_ignore_drops_a_phrase_while_another_sounds():
    runtime, sink, stage = make("ignore", TWO_HANDS)
    hands(stage, 0.5, 1.0)
    assert [p.phrase for p in sink.of(PhrasePlayed)] == ["long"]
    (skipped,) = sink.of(PhraseSkipped)
    assert skipped.phrase == "low" and "still playing" in skipped.why


def test_a_play_may_choose_its_own_policy():
    runtime, sink, stage = make("queue", """
      - {name: left, joint: HandLeft, rises_above: 1.5, do: [play: long]}
      - {name: right, joint: HandRight, rises_above: 1.5,
         do: [{play: {phrase: low, overlap: layer}}]}
""")
    hands(stage, 0.5, 1.0)
    assert [p.policy for p in sink.of(PhrasePlayed)] == ["queue", "layer"]


def test_silence_and_stop_are_logged_as_cuts():
    runtime, sink, stage = make("queue", """
      - {name: left, joint: HandLeft, rises_above: 1.5, do: [play: long]}
      - {name: hush, joint: HandRight, rises_above: 1.5, do: [silence: solo]}
""")
    hands(stage, 0.5, 1.0, until=1.5)
    runtime.stop(1.5)
    cuts = sink.of(NoteCut)
    assert [(c.note, c.why, c.sounded > 0) for c in cuts] == [(60, "silence", True),
                                                             (64, "silence", False)]
    assert runtime.counts["notes"] == 1 and runtime.counts["cancelled"] == 1
    midi_agrees(sink, runtime)


# ------------------------------------------------------------------ broken chords
def test_chords_are_broken_bottom_up_with_the_top_voice_held():
    out = voice_times(10.0, 1.0, 0.9, [67, 43, 50, 59], 0.05)
    assert [(round(t - 10.0, 6), round(d, 6), p) for t, d, p in out] == [
        (0.0, 0.1, 43), (0.05, 0.1, 50), (0.1, 0.1, 59), (0.15, 0.75, 67)]
    assert voice_times(0.0, 1.0, 0.5, [60, 64], 0.0) == [(0.0, 0.5, 60), (0.0, 0.5, 64)]
    # a short chord: the top voice never enters after half its value
    fast = voice_times(0.0, 0.2, 1.0, [40, 50, 60], 0.5)
    assert fast[-1][0] == pytest.approx(0.1)


def test_a_phrase_with_arpeggiate_plays_its_chord_broken():
    runtime, sink, stage = make("queue", """
      - {name: left, joint: HandLeft, rises_above: 1.5, do: [play: chord]}
""")
    hands(stage, 0.5, 99.0, until=1.0)
    notes = sink.of(Note)
    assert [n.note for n in notes] == [43, 50, 59, 67]
    assert [round(n.t - notes[0].t, 6) for n in notes] == [0.0, 0.05, 0.1, 0.15]
    assert notes[-1].t + notes[-1].duration == pytest.approx(notes[0].t + 1.0)  # held: 2 beats


# ------------------------------------------------------------------ the language
@pytest.mark.parametrize("edit, message", [
    ("outputs: {fx: {type: osc, overlap: layer}}", "'overlap' applies to midi outputs only"),
    ("outputs: {fx: {type: midi, skeletons: true}}", "'skeletons' applies to osc outputs only"),
    ("outputs: {fx: {type: midi, overlap: stack}}", "one of queue, layer, replace, ignore"),
])
def test_output_options_belong_to_their_kind(edit, message):
    with pytest.raises(ConfigError, match=message):
        loads_piece(f"piece: x\n{edit}\nsections: [{{name: a}}]\n")


def test_goto_takes_a_name_or_to_and_now():
    piece = loads_piece("""
piece: x
sections:
  - name: a
    triggers:
      - {name: t, elapsed: 1, do: [goto: b, {goto: {to: end, now: true}}]}
  - name: b
""")
    actions = piece.sections[0].triggers[0].actions
    assert [(a.target, a.now) for a in actions] == [("b", False), ("end", True)]
    with pytest.raises(ConfigError, match="section 'c' is not defined"):
        loads_piece("piece: x\nsections: [{name: a, triggers: [{elapsed: 1, do: "
                    "[{goto: {to: c}}]}]}]\n")
