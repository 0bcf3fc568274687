"""Hearing a piece: `stage play --audio` renders through FluidSynth (checked for sound where
notes sound and silence where none do), `--synth` plays through FluidSynth on a real JACK
server (recorded back with jack_rec), and what is missing is one line."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
import wave
from pathlib import Path

import numpy as np
import pytest

from stage.app.play import PlayOptions, Player
from stage.events import Note

CLI = [sys.executable, "-m", "stage.cli"]
SOUNDFONT = "/usr/share/sounds/sf2/FluidR3_GM.sf2"

try:
    import fluidsynth  # noqa: F401
    HAVE_FLUIDSYNTH = True
except (ImportError, OSError):
    HAVE_FLUIDSYNTH = False
needs_fluidsynth = pytest.mark.skipif(
    not HAVE_FLUIDSYNTH or not os.path.exists(SOUNDFONT),
    reason="needs pyfluidsynth, libfluidsynth3 and fluid-soundfont-gm (.ci/run installs them)")

# An organ without reverb: it sounds while a key is down and stops soon after
PIECE = """
piece: on and off
tempo: 120
outputs: {tone: midi}
phrases:
  two: {notes: ["C4 2", "rest 4", "G4 2"], gate: 1.0}
sections:
  - name: only
    on_enter: [{program: 19}, {cc: {control: 91, value: 0}}, {cc: {control: 93, value: 0}},
               {play: two}]
"""


def levels(path: Path, window: float = 0.05) -> tuple[np.ndarray, float]:
    """RMS level (dBFS) of each ``window`` of a 16-bit WAV file, and its sample rate."""
    with wave.open(str(path)) as w:
        rate = w.getframerate()
        audio = np.frombuffer(w.readframes(w.getnframes()), "<i2").reshape(-1, w.getnchannels())
    n = int(window * rate)
    blocks = audio[: len(audio) // n * n].astype(np.float64).reshape(-1, n, audio.shape[1])
    rms = np.sqrt(((blocks / 32768.0) ** 2).mean(axis=(1, 2)))
    return 20.0 * np.log10(np.maximum(rms, 1e-10)), rate


def level(db: np.ndarray, t0: float, t1: float, window: float = 0.05) -> tuple[float, float]:
    part = db[int(t0 / window): int(t1 / window)]
    return float(part.min()), float(part.max())


@needs_fluidsynth
def test_audio_sounds_where_notes_sound_and_is_silent_where_none_do(tmp_path):
    piece = tmp_path / "onoff.yaml"
    piece.write_text(PIECE)
    wav = tmp_path / "out.wav"
    result = Player(PlayOptions(piece=str(piece), sim="", offline=True, duration=6.0, seed=1,
                                audio=str(wav)), out=open(os.devnull, "w")).run()
    notes = result.recorded.of(Note)
    assert [(n.t, n.duration) for n in notes] == [(0.0, 1.0), (3.0, 1.0)]
    db, rate = levels(wav)
    assert rate == 44100 and len(db) * 0.05 >= 6.0
    for t0, t1 in ((0.05, 0.95), (3.05, 3.95)):             # the keys are down
        low, high = level(db, t0, t1)
        assert low > -45.0, (t0, low)
    for t0, t1 in ((2.0, 2.95), (5.0, 6.0)):                 # nothing sounds
        low, high = level(db, t0, t1)
        assert high < -70.0, (t0, high)


def test_missing_soundfont_and_library_are_one_line(tmp_path):
    piece = tmp_path / "onoff.yaml"
    piece.write_text(PIECE)
    done = subprocess.run([*CLI, "play", str(piece), "--sim", "--offline", "--duration", "1",
                           "--audio", str(tmp_path / "x.wav"), "--soundfont",
                           str(tmp_path / "none.sf2")], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines() == [f"stage: --soundfont {tmp_path / 'none.sf2'}: "
                                                "no such file"]
    # no pyfluidsynth: the import fails as it does on a machine without it
    code = ("import sys; sys.modules['fluidsynth'] = None\n"
            "from stage.cli.main import main\n"
            f"sys.exit(main(['play', {str(piece)!r}, '--sim', '--offline', '--duration', '1', "
            f"'--audio', {str(tmp_path / 'x.wav')!r}]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        "stage: --audio needs pyfluidsynth (pip install 'stage-kuatro[audio]')"]


def test_synth_without_a_jack_server_is_one_line(tmp_path):
    piece = tmp_path / "onoff.yaml"
    piece.write_text(PIECE)
    env = dict(os.environ, JACK_DEFAULT_SERVER="stage-test-no-such-server")
    done = subprocess.run([*CLI, "play", str(piece), "--sim", "--duration", "1", "--synth"],
                          capture_output=True, text=True, timeout=60, env=env)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith("stage: --synth needs a running "
                                                           "JACK server")
    offline = subprocess.run([*CLI, "play", str(piece), "--sim", "--offline", "--synth"],
                             capture_output=True, text=True, timeout=60)
    assert offline.returncode == 2 and "--synth plays in real time" in offline.stderr


@pytest.mark.integration
@needs_fluidsynth
@pytest.mark.skipif(not (shutil.which("jackd") and shutil.which("jack_rec")),
                    reason="needs jackd and jack_rec (jackd2; .ci/run installs it)")
def test_synth_plays_live_through_fluidsynth_on_jack(tmp_path):
    from stage.testing.jack import start_dummy_jackd, stop_jackd
    piece = tmp_path / "later.yaml"
    piece.write_text(PIECE.replace("{play: two}]", "]\n    triggers:\n"
                                   "      - {name: go, elapsed: 1.5, do: [play: two]}"))
    name = f"stage-synth-{os.getpid()}"
    env = dict(os.environ, JACK_DEFAULT_SERVER=name)
    jackd = start_dummy_jackd(name)
    proc = None
    try:
        proc = subprocess.Popen([*CLI, "play", str(piece), "--sim", "--duration", "7",
                                 "--synth"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, env=env)
        deadline = time.monotonic() + 30
        while "stage-synth:left" not in subprocess.run(["jack_lsp"], capture_output=True,
                                                       text=True, env=env).stdout:
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.05)
        wav = tmp_path / "rec.wav"
        subprocess.run(["jack_rec", "-f", str(wav), "-d", "5", "stage-synth:left",
                        "stage-synth:right"], capture_output=True, env=env, timeout=30)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(5)
        stop_jackd(jackd)
    assert proc.returncode == 0, err
    assert "FluidSynth on JACK ('stage-synth'" in out and "[1] go -> phrase two" in out
    db, _ = levels(wav)
    assert db.max() > -45.0                 # the organ, heard through JACK
    assert db.min() < -70.0                 # and the silence before, between or after
