"""MIDI ports through python-rtmidi: which MIDI system to use, and opening a port.

Which API (``choose_api``), in order:

1. ``STAGE_MIDI_API`` (``jack``, ``alsa``, ``coremidi``, ``winmm``) or mido's
   ``MIDO_BACKEND`` with an API suffix (``mido.backends.rtmidi/UNIX_JACK``):
   the user's choice, used as given;
2. Linux: the ALSA sequencer when ``/dev/snd/seq`` exists, else JACK when a
   JACK server runs (its socket in ``/dev/shm``, jackd2 or jackd1, or a
   PipeWire socket, whose JACK library serves JACK clients);
3. macOS: CoreMIDI; Windows: Windows MM;
4. otherwise none: the caller falls back to a Standard MIDI File.

Detecting a server by its socket instead of trying to connect keeps libjack
and alsa-lib from printing their own errors when nothing is there.

A port name is looked up among the existing destinations (exact, then
case-insensitive, then a client name or ALSA-style prefix: "fluidsynth" finds
"fluidsynth:midi_00", "Synth" finds "Synth MIDI 1 128:0"); when none matches, a virtual port of that name is created
(client "stage"), for a synth or DAW to connect to.
"""

from __future__ import annotations

import glob
import logging
import os
import socket
import sys
import time
from typing import Sequence

import rtmidi

from stage.errors import TransportError

log = logging.getLogger("stage.views.midi")

_API_NAMES = {
    "jack": rtmidi.API_UNIX_JACK, "unix_jack": rtmidi.API_UNIX_JACK,
    "alsa": rtmidi.API_LINUX_ALSA, "linux_alsa": rtmidi.API_LINUX_ALSA,
    "coremidi": rtmidi.API_MACOSX_CORE, "macosx_core": rtmidi.API_MACOSX_CORE,
    "winmm": rtmidi.API_WINDOWS_MM, "windows_mm": rtmidi.API_WINDOWS_MM,
}


def jack_server_running(server: str | None = None) -> bool:
    """Whether a JACK server (named ``server`` or $JACK_DEFAULT_SERVER or "default") listens."""
    name = server or os.environ.get("JACK_DEFAULT_SERVER") or "default"
    uid = os.getuid() if hasattr(os, "getuid") else 0
    patterns = [f"/dev/shm/jack_{name}_{uid}_*",           # jackd2
                f"/dev/shm/jack-{uid}/{name}/jack_*"]      # jackd1
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime:
        patterns.append(os.path.join(runtime, "pipewire-0"))  # pipewire-jack
    return any(glob.glob(p) for p in patterns)


def jack_server_alive(server: str | None = None) -> bool:
    """``jack_server_running``, but a socket left behind by a killed jackd2 does not count.

    A killed server leaves its socket in /dev/shm; connecting to it tells (refused).
    Used to notice a synth's JACK server going away mid-show and coming back.
    """
    name = server or os.environ.get("JACK_DEFAULT_SERVER") or "default"
    uid = os.getuid() if hasattr(os, "getuid") else 0
    sockets = glob.glob(f"/dev/shm/jack_{name}_{uid}_*")
    if not sockets:
        return jack_server_running(server)
    for path in sockets:
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.settimeout(0.5)
        try:
            probe.connect(path)
            return True
        except OSError:
            continue
        finally:
            probe.close()
    return False


def choose_api() -> tuple[int | None, str]:
    """(rtmidi API or None when no MIDI system is available, why: one line for logs)."""
    compiled = set(rtmidi.get_compiled_api())
    wanted = os.environ.get("STAGE_MIDI_API", "").strip().lower()
    backend = os.environ.get("MIDO_BACKEND", "")
    if not wanted and "/" in backend and "rtmidi" in backend:
        wanted = backend.rsplit("/", 1)[1].strip().lower()
    if wanted:
        api = _API_NAMES.get(wanted)
        if api is None:
            return None, f"unknown MIDI API '{wanted}' (use jack, alsa, coremidi or winmm)"
        if api not in compiled:
            return None, f"MIDI API '{wanted}' is not compiled into python-rtmidi"
        return api, f"{rtmidi.get_api_display_name(api)} (chosen by environment)"
    if sys.platform.startswith("linux"):
        if rtmidi.API_LINUX_ALSA in compiled and os.path.exists("/dev/snd/seq"):
            return rtmidi.API_LINUX_ALSA, "ALSA sequencer"
        if rtmidi.API_UNIX_JACK in compiled and jack_server_running():
            return rtmidi.API_UNIX_JACK, "JACK (no ALSA sequencer here)"
        return None, "no ALSA sequencer (/dev/snd/seq) and no JACK server running"
    if sys.platform == "darwin" and rtmidi.API_MACOSX_CORE in compiled:
        return rtmidi.API_MACOSX_CORE, "CoreMIDI"
    if sys.platform == "win32" and rtmidi.API_WINDOWS_MM in compiled:
        return rtmidi.API_WINDOWS_MM, "Windows MM"
    return None, f"no MIDI API for {sys.platform} in python-rtmidi"


def match_port(wanted: str, available: Sequence[str]) -> int | None:
    """Index of the destination ``wanted`` names, or None (ambiguous names raise)."""
    if wanted in available:
        return list(available).index(wanted)
    low = wanted.lower()
    # no substring matching: "bench" must not pick "bench-rx:in" when the user
    # meant a new port of that name
    for rule in (lambda p: p.lower() == low,
                 lambda p: p.lower().startswith(low + " ") or p.lower().startswith(low + ":")):
        hits = [k for k, p in enumerate(available) if rule(p)]
        if len(hits) == 1:
            return hits[0]
        if len(hits) > 1:
            raise TransportError(f"MIDI port '{wanted}' is ambiguous: "
                                 + ", ".join(available[k] for k in hits))
    return None


# How long a JACK port stays open after its last message. python-rtmidi builds RtMidi
# without HAVE_SEMAPHORE, so RtMidi's closePort unregisters the port at once instead of
# waiting for JACK's process callback to copy the ring buffer into the port: what was sent
# in the last period or so (the all-notes-off at stop) is lost. Measured with a dummy
# jackd (256 frames at 48 kHz) and three busy loops on this 2-core machine: closing right
# after sending lost 20-30 of 60 messages; closing 20 or 50 ms after the last one lost none.
JACK_DRAIN_S = 0.1
# A JACK client that misses the period in which the stop's note-offs and all-notes-off
# pass (an xrun: a synth, or jack_midi_dump, starved by other load) never gets them: the
# note sounds on. A JACK port sends what it was given for that (``again_at_close``) again,
# JACK_STOP_REPEATS times JACK_STOP_REPEAT_S apart, before it drains and closes. Measured
# with a dummy jackd and six busy loops on this 2-core machine: tests/test_midi.py's
# performer stopping mid-phrase left a note sounding in 7 of 39 runs without the repeats,
# in none of 24 with them; bench_midi_stop.py --repeats 0,3 --load 6 lost 2 and 8 of 60
# messages with the drain alone, none with the repeats (docs/reports/issue-10.md, stop 47).
JACK_STOP_REPEATS = 3
JACK_STOP_REPEAT_S = 0.1


class PortSink:
    """One open MIDI output (an existing destination or a new virtual port).

    ``check()`` (the MIDI view calls it every couple of seconds) notices the port's
    server or destination going away (a JACK server killed, a synth quit) and opens
    the port again when it is back; meanwhile sends are counted as ``dropped``.
    """

    # class defaults, so a subclass that opens nothing (a test's fake) still has a state
    api_id: int | None = None
    connected = True
    reason = ""
    dropped = reconnects = 0
    down_since: float | None = None
    down_s = 0.0
    destination: str | None = None
    _again: tuple[bytes, ...] = ()

    def __init__(self, name: str, api: int, client: str = "stage", existing: bool = True) -> None:
        """existing: look ``name`` up among the destinations first (False: always a new port)."""
        self.name, self.api_id, self.client, self.existing = name, api, client, existing
        self.sent = 0
        self.errors = 0
        self.dropped = 0                # messages not sent while disconnected
        self.reconnects = 0
        self.connected = False
        self.reason = ""
        self.down_since: float | None = None
        self.down_s = 0.0               # total seconds disconnected (for the summary)
        self.destination: str | None = None
        self._out = None
        self._abandoned: list = []
        self._last_send = -1e9          # time.monotonic() of the last message handed to rtmidi
        self._open()

    def _open(self) -> None:
        try:
            out = rtmidi.MidiOut(rtapi=self.api_id, name=self.client)
        except Exception as exc:  # rtmidi raises its own SystemError/RuntimeError kinds
            raise TransportError(f"cannot open the MIDI system: {exc}") from None
        self.api = rtmidi.get_api_display_name(out.get_current_api())
        try:
            index = match_port(self.name, out.get_ports()) if self.existing else None
            if index is None:
                out.open_virtual_port(self.name)
                self.destination = None
                self.where = f"new virtual port '{self.client}:{self.name}' ({self.api})"
            else:
                self.destination = out.get_ports()[index]
                out.open_port(index, self.name)
                self.where = f"port '{self.destination}' ({self.api})"
        except TransportError:
            out.delete()
            raise
        except Exception as exc:
            out.delete()
            raise TransportError(f"cannot open MIDI port '{self.name}': {exc}") from None
        self._out = out
        self.connected, self.reason = True, ""

    def check(self) -> str | None:
        """Notice a lost server or destination, or reconnect; returns what changed, or None."""
        if self.connected:
            why = self._lost()
            if why is None:
                return None
            self._drop(why)
            return f"MIDI port '{self.name}' lost: {why}; reconnecting when it is back"
        if self.api_id == rtmidi.API_UNIX_JACK and not jack_server_alive():
            return None
        try:
            self._open()
        except TransportError as exc:
            self.reason = f"reconnecting: {exc}"
            return None
        if self.down_since is not None:
            self.down_s += time.monotonic() - self.down_since
            self.down_since = None
        self.reconnects += 1
        return f"MIDI port '{self.name}' is back: {self.where}"

    def _lost(self) -> str | None:
        if self.api_id == rtmidi.API_UNIX_JACK and not jack_server_alive():
            return "the JACK server is gone"
        if self.destination is not None:
            try:
                ports = self._out.get_ports() if self._out is not None else []
            except Exception:
                ports = []
            if self.destination not in ports:
                return f"destination '{self.destination}' is gone"
        return None

    def _drop(self, why: str) -> None:
        self.connected, self.reason = False, why
        self.down_since = time.monotonic()
        out, self._out = self._out, None
        if out is None:
            return
        if self.api_id == rtmidi.API_UNIX_JACK:
            # closing a JACK client whose server died can block in libjack: keep it unclosed
            self._abandoned.append(out)
            return
        try:
            out.close_port()
        finally:
            out.delete()

    def state(self) -> dict:
        """For health: connected, reconnecting, errors, the reason."""
        down = self.down_s + (time.monotonic() - self.down_since if self.down_since else 0.0)
        return {"connected": self.connected, "reconnecting": not self.connected,
                "errors": self.errors, "dropped": self.dropped, "reconnects": self.reconnects,
                "down_s": round(down, 1), "reason": self.reason}

    def send(self, data: bytes) -> None:
        if not self.connected or self._out is None:
            self.dropped += 1
            return
        try:
            self._out.send_message(data)
            self._last_send = time.monotonic()
            self.sent += 1
        except Exception:  # a vanished destination must not stop the show; counted
            self.errors += 1

    def again_at_close(self, data: bytes) -> None:
        """A message a JACK port sends again before it closes (the stop's silence): see
        ``JACK_STOP_REPEATS``. Idempotent ones only: note-offs, all-notes-off."""
        self._again = self._again + (data,)   # (a tuple: the class default is shared)

    def close(self) -> None:
        """Close the port; a JACK port first sends the stop's silence again (a client in an
        xrun missed it) and lets its last messages reach JACK."""
        if self._out is None:
            return
        if self.api_id == rtmidi.API_UNIX_JACK:
            for _ in range(JACK_STOP_REPEATS if self._again and self.connected else 0):
                time.sleep(JACK_STOP_REPEAT_S)
                for data in self._again:
                    self.send(data)
            wait = self._last_send + JACK_DRAIN_S - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        try:
            self._out.close_port()
        finally:
            self._out.delete()
            self._out = None
