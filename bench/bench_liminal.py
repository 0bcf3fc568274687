"""Liminal Space rehearsed with N seeds: does it sound like music?

Each seed is the README's main job run offline (``stage play pieces/liminal.yaml --sim
--offline --seed N``) with its MIDI file and events. Per seed, from the MIDI file the MIDI
view wrote (read back with mido, independently of the piece runtime's own account):

- notes: note-ons in the file, and the runtime's count of notes sounded (must agree);
- cut: scheduled notes that sounded shorter than scheduled or not at all (from the
  file: each note-on paired with its note-off), against the cuts the runtime logged
  (NoteCut; the counts must agree), and who cut them: another phrase while the
  output's policy was not ``replace`` (struck again, replaced), or a ``silence``;
- grid: phrase starts off the grid of their quantize (the runtime's PhrasePlayed times
  against the piece's tempo and meter);
- final: the final cadence played whole (every note of its bar in the file, none cut,
  its last note held by the ending's pedal);
- end: the run's end minus the piece's end (the ending's fade and ring over; one
  50 ms piece tick at most) and whether the dancer's exit message was sent.

The reference, measured in the same run on the same seeds: the piece as it played before
issue 12's musical clock (``--reference``): every output layered, nothing quantised, every
goto at once, the kneel silencing the cello and ending at once -- the behaviour the issue
measured.

    python bench/bench_liminal.py                 # 10 seeds, and the reference
    python bench/bench_liminal.py --quick         # 2 seeds
    python bench/bench_liminal.py --seeds 1 2 3 --no-reference
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
import time
from pathlib import Path

from benchlib import machine_busy_s

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import mido  # noqa: E402

from stage.app.play import PlayOptions, Player  # noqa: E402
from stage.app.report import Performance, grid_check  # noqa: E402
from stage.events import Note, NoteCut, PhrasePlayed, TriggerFired  # noqa: E402
from stage.piece import load_piece  # noqa: E402

LIMINAL = REPO / "pieces" / "liminal.yaml"


def reference_text(text: str) -> str:
    """Liminal as it played before the musical clock: layered, unquantised, immediate."""
    text = text.replace("    overlap: queue ", "    overlap: layer ")
    text = re.sub(r"^quantize: beat.*$", "quantize: none", text, flags=re.M)
    text = re.sub(r"^ending: .*$", "ending: {fade: 0, ring: 0}", text, flags=re.M)
    text = text.replace("  arpeggiate: 0.07", "  arpeggiate: 0")
    text = re.sub(r"- goto: next", r"- goto: {to: next, now: true}", text)
    return text.replace("          - play: final ", "          - silence: cello\n"
                                                   "          - play: final ")


def midi_notes(path: Path) -> list[tuple[float, float, int]]:
    """(on s, off s, key) of every note in a Standard MIDI File, paired in order."""
    t, sounding, out = 0.0, {}, []
    for msg in mido.MidiFile(str(path)):
        t += msg.time
        if msg.type == "note_on" and msg.velocity > 0:
            sounding[(msg.channel, msg.note)] = t
        elif msg.type in ("note_off", "note_on"):
            on = sounding.pop((msg.channel, msg.note), None)
            if on is not None:
                out.append((on, t, msg.note))
    return out


def one(piece_path: Path, seed: int, tmp: Path) -> dict:
    mid = tmp / f"{piece_path.stem}-{seed}.mid"
    started = time.perf_counter()
    result = Player(PlayOptions(piece=str(piece_path), sim="", offline=True, seed=seed,
                                midi_file=str(mid)), out=open(os.devnull, "w")).run()
    wall = time.perf_counter() - started
    rt, events = result.runtime, result.recorded.events
    piece = load_piece(piece_path)
    notes = [e for e in events if isinstance(e, Note)]
    played = {e.id: e for e in events if isinstance(e, PhrasePlayed)}
    heard = midi_notes(mid)
    by_key: dict[tuple[int, int], list[tuple[float, float]]] = {}
    for on, off, key in heard:
        by_key.setdefault((key, round(on * 1000)), []).append((on, off))
    cut = 0
    for n in notes:
        ms = round(n.t * 1000)
        match = by_key.get((n.note, ms)) or by_key.get((n.note, ms + 1)) or \
            by_key.get((n.note, ms - 1))
        sounded = (match[0][1] - match[0][0]) if match else 0.0
        if sounded < n.duration - 0.002:     # the file keeps 0.5 ms ticks
            cut += 1
    # who cut them: the runtime's account (its count must be the file's)
    cuts = [e for e in events if isinstance(e, NoteCut)]
    by_phrase = sum(1 for c in cuts if c.why.startswith(("struck again", "replaced by"))
                    and played.get(c.play) is not None and played[c.play].policy != "replace")
    perf = Performance.from_events(events)
    grid = grid_check(perf, piece)
    off_grid = sum(1 for _, unit, on in grid if unit not in (None, "none") and not on)
    quantised = sum(1 for _, unit, _ in grid if unit not in (None, "none"))
    final = [p for p in played.values() if p.phrase == "final"]
    final_notes = [n for n in notes if final and n.play == final[0].id]
    final_whole = bool(final) and len(final_notes) == 6 and all(
        any(abs(on - n.t) < 0.002 and off >= n.t + n.duration - 0.002 for on, off, _ in heard)
        for n in final_notes)
    piece_end = rt.ends_at - rt.started_at if rt.ending else float("nan")
    exits = [e for e in events if isinstance(e, TriggerFired) and e.trigger == "dancer leaves"]
    return {"seed": seed, "seconds": result.seconds, "piece_end": piece_end,
            "ended": rt.ended, "sections": len(set(rt.visited)), "phrases": len(played),
            "skipped": rt.counts["skipped"], "notes": rt.counts["notes"], "midi": len(heard),
            "cut": cut, "logged": len(cuts), "cut_by_other": by_phrase,
            "by_silence": sum(1 for c in cuts if c.why == "silence"), "off_grid": off_grid,
            "quantised": quantised, "final": final_whole, "exit": bool(exits), "wall": wall}


def table(title: str, rows: list[dict]) -> None:
    print(f"\n{title}")
    print(f"{'seed':>4} {'run s':>6} {'piece s':>7} {'end-diff ms':>11} {'sect':>4} "
          f"{'phrases':>7} {'skip':>4} {'notes':>5} {'midi':>5} {'cut':>4} {'logged':>6} "
          f"{'by phrase':>9} {'by silence':>10} {'off grid':>9} {'final':>5} {'exit':>4}")
    for r in rows:
        diff = (r["seconds"] - r["piece_end"]) * 1000
        print(f"{r['seed']:>4} {r['seconds']:6.1f} {r['piece_end']:7.2f} {diff:11.0f} "
              f"{r['sections']:>4} {r['phrases']:>7} {r['skipped']:>4} {r['notes']:>5} "
              f"{r['midi']:>5} {r['cut']:>4} {r['logged']:>6} {r['cut_by_other']:>9} "
              f"{r['by_silence']:>10} "
              f"{r['off_grid']:>4}/{r['quantised']:<4} {'yes' if r['final'] else 'NO':>5} "
              f"{'yes' if r['exit'] else 'no':>4}")
    n = len(rows)
    ends = [r["piece_end"] for r in rows]
    print(f"all {n}: sections 5/5 in {sum(r['sections'] == 5 for r in rows)}, notes = MIDI "
          f"note-ons in {sum(r['notes'] == r['midi'] for r in rows)}, cuts in the MIDI = cuts "
          f"logged in {sum(r['cut'] == r['logged'] for r in rows)}, notes cut by another "
          f"phrase {sum(r['cut_by_other'] for r in rows)}, by a silence "
          f"{sum(r['by_silence'] for r in rows)}, off the grid "
          f"{sum(r['off_grid'] for r in rows)}/{sum(r['quantised'] for r in rows)}, final "
          f"cadence whole in {sum(r['final'] for r in rows)}, exit sent in "
          f"{sum(r['exit'] for r in rows)}; piece end {min(ends):.1f}-{max(ends):.1f} s "
          f"(median {sorted(ends)[n // 2]:.1f} s)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 11)))
    parser.add_argument("--quick", action="store_true", help="seeds 1 and 2")
    parser.add_argument("--no-reference", action="store_true")
    args = parser.parse_args()
    seeds = [1, 2] if args.quick else args.seeds
    busy0, t0 = machine_busy_s(), time.monotonic()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rows = [one(LIMINAL, s, tmp) for s in seeds]
        table("Liminal Space (pieces/liminal.yaml)", rows)
        if not args.no_reference:
            ref = tmp / "liminal.yaml"
            ref.write_text(reference_text(LIMINAL.read_text()))
            (tmp / "liminal.sim.yaml").write_text((REPO / "pieces" / "liminal.sim.yaml")
                                                  .read_text())
            table("reference: the same piece layered, unquantised, every goto at once",
                  [one(ref, s, tmp) for s in seeds])
    elapsed = time.monotonic() - t0
    print(f"\nmachine busy: {(machine_busy_s() - busy0) / elapsed:.2f} cores on average over "
          f"{elapsed:.0f} s ({os.cpu_count()} cores; this bench uses about one)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
