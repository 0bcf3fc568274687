"""Hearing a piece without a synthesizer of one's own: FluidSynth, rendered or live.

``WavRenderer`` (``stage play --audio OUT.wav``) collects the MIDI messages of
the show with their engine times and, when the show ends, renders them
through FluidSynth into a 16-bit stereo WAV file that starts when the view
started (the show's start), then lets the last sounds die away. ``LiveSynth``
(``--synth``) sends them as they are due to a FluidSynth that plays through
JACK (``audio.jack.autoconnect``: straight to the system's playback ports).

FluidSynth comes through pyfluidsynth (``pip install 'stage-kuatro[audio]'``,
a ctypes binding) and the FluidSynth library; the sounds come from a General
MIDI soundfont (Debian: ``apt-get install fluid-soundfont-gm``) or the file
given with ``--soundfont``. When one of them (or, for ``--synth``, a JACK
server) is missing the show does not start and the error says, in one line,
what to install: a ``ConfigError``, since the command line asked for something
this machine cannot do.
"""

from __future__ import annotations

import ctypes
import logging
import os
import wave
from pathlib import Path
from typing import Any

import numpy as np

from stage.errors import ConfigError

from .ports import jack_server_running

log = logging.getLogger("stage.views.midi")

SAMPLE_RATE = 44100
#: General MIDI soundfonts where distributions install them (Debian and Fedora first)
SOUNDFONTS = ("/usr/share/sounds/sf2/FluidR3_GM.sf2", "/usr/share/sounds/sf2/default-GM.sf2",
              "/usr/share/soundfonts/FluidR3_GM.sf2", "/usr/share/soundfonts/default.sf2",
              "/usr/share/soundfonts/FluidR3_GM2-2.sf2")
#: after the last message, render until the sound has died away, at most this long
TAIL_MAX_S = 4.0
#: "died away": the RMS of a 100 ms block below this (dBFS)
TAIL_SILENCE_DB = -80.0
#: FluidSynth's gain: a solo line peaks around -10 dBFS with the GM soundfont
GAIN = 0.5


def load_fluidsynth(what: str) -> Any:
    """The pyfluidsynth module, or a one-line ConfigError naming what to install."""
    try:
        import fluidsynth  # noqa: PLC0415  (optional: only --audio and --synth need it)
    except (ImportError, OSError) as exc:
        lib = "Couldn't find the FluidSynth library" in str(exc)
        need = ("the FluidSynth library (apt-get install libfluidsynth3, brew install "
                "fluid-synth)" if lib else "pyfluidsynth (pip install 'stage-kuatro[audio]')")
        raise ConfigError(f"{what} needs {need}") from None
    _quiet(fluidsynth)
    return fluidsynth


def find_soundfont(given: str | os.PathLike | None, what: str) -> str:
    """The soundfont to use: ``given``, else a General MIDI one where distributions put it."""
    if given:
        path = Path(given)
        if not path.is_file():
            raise ConfigError(f"--soundfont {given}: no such file")
        return str(path)
    for candidate in SOUNDFONTS:
        if os.path.isfile(candidate):
            return candidate
    raise ConfigError(f"{what} needs a General MIDI soundfont: apt-get install "
                      "fluid-soundfont-gm, or give --soundfont FILE.sf2")


_LOG_FN = None


def _quiet(fluidsynth: Any) -> None:
    """FluidSynth's own messages go to our log (debug), not to the console."""
    global _LOG_FN
    set_log = getattr(getattr(fluidsynth, "_fl", None), "fluid_set_log_function", None)
    if set_log is None or _LOG_FN is not None:
        return
    proto = ctypes.CFUNCTYPE(None, ctypes.c_int, ctypes.c_char_p, ctypes.c_void_p)

    def to_log(level: int, message: bytes, data: Any) -> None:
        log.debug("fluidsynth: %s", message.decode("utf-8", "replace") if message else "")
    _LOG_FN = proto(to_log)
    set_log.argtypes = [ctypes.c_int, proto, ctypes.c_void_p]
    for level in range(5):       # panic, error, warning, info, debug
        set_log(level, _LOG_FN, None)


def _apply(synth: Any, data: bytes) -> None:
    """One channel message to a pyfluidsynth Synth."""
    if not data:
        return
    status, channel = data[0] & 0xF0, data[0] & 0x0F
    if status == 0x90 and len(data) >= 3 and data[2] > 0:
        synth.noteon(channel, data[1], data[2])
    elif status in (0x80, 0x90) and len(data) >= 3:
        synth.noteoff(channel, data[1])
    elif status == 0xB0 and len(data) >= 3:
        synth.cc(channel, data[1], data[2])
    elif status == 0xC0 and len(data) >= 2:
        synth.program_change(channel, data[1])


class _Synth:
    """A FluidSynth with a General MIDI soundfont loaded on every channel."""

    def __init__(self, soundfont: str | None, what: str, **settings: Any) -> None:
        fs = load_fluidsynth(what)
        self.soundfont = find_soundfont(soundfont, what)
        self.synth: Any = fs.Synth(gain=GAIN, samplerate=float(SAMPLE_RATE), **settings)
        sfid = self.synth.sfload(self.soundfont)
        if sfid < 0:
            self.synth.delete()
            raise ConfigError(f"{what}: FluidSynth cannot read the soundfont {self.soundfont}")
        for channel in range(16):
            self.synth.program_select(channel, sfid, 128 if channel == 9 else 0, 0)


class WavRenderer(_Synth):
    """A MIDI sink (``write(t, data)``) rendered into the WAV file ``path`` as it goes.

    ``begin(t0)``: engine time ``t0`` is the file's first sample. Each message renders the
    audio up to its time first (FluidSynth renders far faster than real time,
    so a live show loses nothing by it); ``close`` renders the tail until the
    sound has died away and finishes the file.
    """

    def __init__(self, path: str | os.PathLike, soundfont: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.parent.is_dir():
            raise ConfigError(f"--audio {path}: folder '{self.path.parent}' does not exist")
        super().__init__(soundfont, "--audio")   # loading the soundfont takes a moment
        self.t0 = 0.0
        self.done = 0                          # frames written so far
        self.messages = 0
        self._wav: Any = None

    def begin(self, t0: float) -> None:
        """Open the file; engine time ``t0`` is its first sample (the show's start)."""
        self.t0 = t0
        self._wav = wave.open(str(self.path), "wb")
        self._wav.setnchannels(2)
        self._wav.setsampwidth(2)
        self._wav.setframerate(SAMPLE_RATE)

    @property
    def seconds(self) -> float:
        return self.done / SAMPLE_RATE

    def write(self, t: float, data: bytes) -> None:
        if self.synth is None or self._wav is None:
            return
        at = int(round((t - self.t0) * SAMPLE_RATE))
        if at > self.done:
            self._write(_samples(self.synth, at - self.done))
        _apply(self.synth, data)
        self.messages += 1

    def _write(self, frames: np.ndarray) -> None:
        self._wav.writeframes(frames.astype("<i2").tobytes())
        self.done += len(frames)

    def close(self) -> None:
        """Render the tail (until the sound has died away) and finish the file."""
        if self.synth is None:
            return
        if self._wav is None:                  # never begun: nothing to write
            self.synth.delete()
            self.synth = None
            return
        block = int(0.1 * SAMPLE_RATE)
        for _ in range(int(TAIL_MAX_S / 0.1)):
            tail = _samples(self.synth, block)
            self._write(tail)
            rms = float(np.sqrt(np.mean(tail.astype(np.float64) ** 2))) / 32768.0
            if rms == 0.0 or 20.0 * np.log10(rms) < TAIL_SILENCE_DB:
                break
        self.synth.delete()
        self.synth = None
        self._wav.close()
        log.info("audio: %s (%.1f s, %d MIDI messages, soundfont %s)", self.path, self.seconds,
                 self.messages, self.soundfont)


def _samples(synth: Any, n: int) -> np.ndarray:
    """``n`` stereo frames (n, 2) int16, rendered in pieces FluidSynth takes."""
    out = []
    while n > 0:
        k = min(n, 65536)
        out.append(np.asarray(synth.get_samples(k), np.int16).reshape(-1, 2))
        n -= k
    return np.concatenate(out) if out else np.zeros((0, 2), np.int16)


class LiveSynth(_Synth):
    """A MIDI sink (``send(data)``) playing live through FluidSynth's JACK driver."""

    live = True

    def __init__(self, soundfont: str | None = None, client: str = "stage-synth") -> None:
        if not jack_server_running():
            raise ConfigError("--synth needs a running JACK server (e.g. jackd -d alsa, "
                              "qjackctl, or PipeWire's JACK); or render with --audio OUT.wav")
        super().__init__(soundfont, "--synth", **{"audio.driver": "jack",
                                                  "audio.jack.id": client,
                                                  "audio.jack.autoconnect": 1})
        fs = load_fluidsynth("--synth")
        self.driver = fs.new_fluid_audio_driver(self.synth.settings, self.synth.synth)
        if not self.driver:
            self.synth.delete()
            raise ConfigError("--synth: FluidSynth could not connect to the JACK server "
                              f"'{os.environ.get('JACK_DEFAULT_SERVER', 'default')}'")
        self._delete = fs.delete_fluid_audio_driver
        self.client = client
        self.sent = 0
        self.where = f"FluidSynth on JACK ('{client}', {Path(self.soundfont).name})"

    def send(self, data: bytes) -> None:
        if self.synth is not None:
            _apply(self.synth, data)
            self.sent += 1

    def close(self) -> None:
        if self.synth is None:
            return
        self.synth.all_notes_off(-1)
        self._delete(self.driver)
        self.synth.delete()
        self.synth = None
