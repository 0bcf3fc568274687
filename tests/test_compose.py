"""The composer's tools: `stage new` (a starter that plays at once), `stage schema`,
rehearsal scenarios beside pieces in `stage check`, `stage report` and the score, and the
default simulated dancer's choreography as the docs give it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from stage.app.play import PlayOptions, Player
from stage.app.report import Performance, audio_report, grid_check
from stage.app.score import draw_score
from stage.piece import load_piece
from stage.sensors.sim.scenario import describe, load_scenario

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "stage.cli"]


def run(*args: str, env: dict | None = None, cwd: Path | None = None):
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=120,
                          env={**os.environ, **(env or {})}, cwd=cwd)


@pytest.fixture()
def data_home(tmp_path):
    return {"XDG_DATA_HOME": str(tmp_path / "data")}


def test_stage_new_writes_a_starter_that_checks_and_plays(tmp_path, data_home):
    done = run("new", str(tmp_path / "dusk.yaml"), env=data_home)
    assert done.returncode == 0, done.stderr
    piece, rehearsal = tmp_path / "dusk.yaml", tmp_path / "dusk.sim.yaml"
    first = piece.read_text().splitlines()[0]
    schema = Path(data_home["XDG_DATA_HOME"]) / "stage" / "piece.schema.json"
    assert first == f"# yaml-language-server: $schema={schema}"     # absolute: works anywhere
    assert json.loads(schema.read_text())["$id"] == schema.resolve().as_uri()
    again = run("new", str(piece), env=data_home)
    assert again.returncode == 2 and again.stderr.strip().splitlines() == [
        f"stage: {piece} exists; choose another name or give --force"]
    check = run("check", str(piece), str(rehearsal))
    assert check.returncode == 0, check.stderr
    assert "rehearsal scenario 'dusk'" in check.stdout
    result = Player(PlayOptions(piece=str(piece), sim="", offline=True, seed=1,
                                midi_file=str(tmp_path / "dusk.mid")),
                    out=open(os.devnull, "w")).run()
    runtime = result.runtime
    assert runtime.ended and runtime.visited == ["calling", "answering"]
    fired = {e.trigger for e in result.recorded.events if type(e).__name__ == "TriggerFired"}
    assert {"hand up", "to the centre", "step", "kneel", "arrives", "leaves"} <= fired
    assert runtime.counts["notes"] > 10 and runtime.counts["cancelled"] == 0
    assert result.seconds == pytest.approx(runtime.ends_at, abs=0.06)   # ends with the piece


def test_stage_check_takes_the_rehearsal_scenarios_beside_the_pieces(tmp_path):
    done = run("check", *sorted(str(p) for p in (REPO / "pieces").glob("*.yaml")))
    assert done.returncode == 0, done.stderr
    assert "liminal.sim.yaml: ok -- rehearsal scenario 'liminal'" in done.stdout
    assert "   2.0-  3.0 s  raise left to 175 over 1" in done.stdout   # its choreography
    bad = tmp_path / "bad.sim.yaml"
    bad.write_text("name: bad\nperformers:\n  - name: d\n    timeline:\n      - {rase: left}\n")
    done = run("check", str(bad))
    assert done.returncode == 2 and done.stderr.startswith(f"stage: {bad}:5:")
    assert "'rase'" in done.stderr and len(done.stderr.strip().splitlines()) == 1


def test_stage_schema_prints_installs_and_registers_with_vscode(tmp_path, data_home):
    done = run("schema")
    schema = json.loads(done.stdout)
    assert "$id" not in schema and schema["title"] == "stage piece"   # no $id that points nowhere
    settings = tmp_path / "settings.json"
    settings.write_text(json.dumps({"editor.fontSize": 13}))
    done = run("schema", "--install", "--vscode", str(settings), env=data_home)
    assert done.returncode == 0, done.stderr
    path = Path(data_home["XDG_DATA_HOME"]) / "stage" / "piece.schema.json"
    assert f"$schema={path}" in done.stdout
    merged = json.loads(settings.read_text())
    assert merged["editor.fontSize"] == 13
    assert merged["yaml.schemas"] == {path.resolve().as_uri(): ["*.piece.yaml"]}
    settings.write_text("{\n  // a comment\n}\n")
    done = run("schema", "--install", "--vscode", str(settings), env=data_home)
    assert done.returncode == 2 and "not plain JSON" in done.stderr
    assert settings.read_text() == "{\n  // a comment\n}\n"          # left alone


def test_the_default_dancers_choreography_is_documented_as_it_is():
    """docs/sources.md gives the default dancer's steps with their times; they are the
    simulator's own (`stage check` on the scenario prints the same lines)."""
    doc = (REPO / "docs" / "sources.md").read_text(encoding="utf-8")
    lines = describe(load_scenario("default"))[1:]
    missing = [line for line in lines if line.strip() not in doc]
    assert missing == []


def test_report_and_score_of_a_rehearsal(tmp_path, monkeypatch):
    piece = tmp_path / "dusk.yaml"
    from stage.piece.starter import write_starter
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    write_starter(piece)
    events = tmp_path / "dusk.jsonl"
    result = Player(PlayOptions(piece=str(piece), sim="", offline=True, seed=2,
                                events=str(events), midi_file=str(tmp_path / "d.mid"),
                                score=str(tmp_path / "play.png")),
                    out=open(os.devnull, "w")).run()
    assert (tmp_path / "play.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    perf = Performance.load(events)
    c = result.runtime.counts
    assert perf.counts()["notes"] == c["notes"] and perf.counts()["phrases"] == len(
        [e for e in result.recorded.events if type(e).__name__ == "PhrasePlayed"])
    assert [s.name for s in perf.sections] == ["calling", "answering"]
    checked = grid_check(perf, load_piece(piece))
    assert checked and all(on for _, unit, on in checked if unit == "beat")
    done = run("report", str(events), "--piece", str(piece))
    assert done.returncode == 0, done.stderr
    assert f"{c['notes']} notes sounded" in done.stdout and "on the grid (beat" in done.stdout
    assert (tmp_path / "dusk.png").exists()                      # beside the events
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"type": "Note", "t": 0}\nnot json\n')
    done = run("report", str(bad))
    assert done.returncode == 2 and done.stderr.strip() == \
        f"stage: {bad}:2: line 2 is not JSON: expected one event per line (stage play --events)"


def test_audio_report_finds_silence_where_notes_sound(tmp_path):
    """The report is not a rubber stamp: a WAV silent where notes sound is said so."""
    import wave
    import numpy as np
    from stage.events import Note, SectionChange
    perf = Performance.from_events([SectionChange(0.0, "only", None, 0, "start"),
                                    Note(1.0, "x", 0, 60, 80, 2.0, 1)])
    rate = 8000
    audio = np.zeros((rate * 6, 2), np.int16)
    audio[rate: int(rate * 1.5)] = 8000                           # sound for 0.5 s of the 2
    with wave.open(str(tmp_path / "x.wav"), "wb") as w:
        w.setnchannels(2)
        w.setsampwidth(2)
        w.setframerate(rate)
        w.writeframes(audio.tobytes())
    rep = audio_report(perf, tmp_path / "x.wav")
    assert rep["silent_while_notes"] == [(pytest.approx(1.5), pytest.approx(3.0))]
    assert rep["sound_without_notes"] == []
    draw_score(perf, tmp_path / "x.svg")
    assert (tmp_path / "x.svg").read_text().lstrip().startswith("<?xml")
