"""The MIDI view: scheduling (pure), the Standard MIDI File writer, routing and fallback.

The real-peer test (a JACK server with the dummy driver, ``jack_midi_dump``
connected to the view's port) is in this file too and skips with a reason
when JACK's tools are missing.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import mido
import pytest
import rtmidi

from stage.testing.jack import start_dummy_jackd, start_midi_dump, stop_jackd

import stage_plugins.midi as midi_view
import stage_plugins.midi.ports as midi_ports
from stage_plugins.midi.ports import PortSink, choose_api, jack_server_running, match_port
from stage_plugins.midi.schedule import MidiScheduler
from stage_plugins.midi.smf import TICKS_PER_S, SmfWriter, varlen
from stage.clock import ManualClock
from stage.errors import ConfigError, TransportError
from stage.events import AllNotesOff, ControlChange, MappingValue, Note, OutputDecl, ProgramChange
from stage.views import ViewHost


def hexes(outs) -> list[tuple[float, str, str]]:
    return [(round(o.t, 6), o.output, o.data.hex(" ")) for o in outs]


# ---------------------------------------------------------------- the scheduler (pure)

def test_note_off_is_scheduled_at_its_own_time_not_the_next_frame():
    s = MidiScheduler()
    s.add(Note(1.0, "keys", 2, 60, 100, 0.25), now=0.9)
    assert s.next_time() == 1.0
    assert s.due(0.99) == []
    assert hexes(s.due(1.0)) == [(1.0, "keys", "92 3c 64")]
    assert s.next_time() == 1.25
    assert hexes(s.due(5.0)) == [(1.25, "keys", "82 3c 00")]   # meant time kept, even if late
    assert s.sounding == 0 and s.next_time() is None


def test_same_time_note_off_goes_before_note_on_so_repeated_notes_restrike():
    s = MidiScheduler()
    s.add(Note(1.0, "keys", 0, 60, 100, 0.5), 0.0)
    s.add(Note(1.5, "keys", 0, 60, 90, 0.5), 0.0)
    assert hexes(s.due(1.9)) == [(1.0, "keys", "90 3c 64"), (1.5, "keys", "80 3c 00"),
                                 (1.5, "keys", "90 3c 5a")]
    assert hexes(s.due(2.0)) == [(2.0, "keys", "80 3c 00")]


def test_a_note_struck_again_while_sounding_is_ended_first_and_its_old_off_is_void():
    s = MidiScheduler()
    s.add(Note(1.0, "keys", 0, 60, 100, 1.0), 0.0)    # would end at 2.0
    s.add(Note(1.5, "keys", 0, 60, 80, 1.0), 0.0)     # struck again, ends at 2.5
    out = hexes(s.due(3.0))
    assert out == [(1.0, "keys", "90 3c 64"), (1.5, "keys", "80 3c 00"), (1.5, "keys", "90 3c 50"),
                   (2.5, "keys", "80 3c 00")]
    assert s.stats["retriggered"] == 1


def test_all_notes_off_silences_sounding_cancels_pending_and_spares_later_notes():
    s = MidiScheduler()
    s.add(Note(1.0, "keys", 0, 60, 100, 5.0), 0.0)    # sounding at 2.0
    s.add(Note(1.0, "bass", 1, 36, 100, 5.0), 0.0)    # other output: untouched
    s.add(Note(3.0, "keys", 0, 64, 100, 1.0), 0.0)    # pending at 2.0: cancelled
    s.add(AllNotesOff(2.0, "keys"), 1.0)
    s.add(Note(2.0, "keys", 0, 67, 100, 0.5), 1.0)    # the new section's first note: plays
    out = hexes(s.due(2.0))
    assert out == [(1.0, "keys", "90 3c 64"), (1.0, "bass", "91 24 64"),
                   (2.0, "keys", "80 3c 00"), (2.0, "keys", "b0 7b 00"),
                   (2.0, "keys", "90 43 64")]
    assert hexes(s.due(10.0)) == [(2.5, "keys", "80 43 00"), (6.0, "bass", "81 24 00")]
    assert s.stats["cancelled"] == 1


def test_all_notes_off_by_channel_and_everywhere():
    s = MidiScheduler()
    s.add(Note(0.0, "keys", 0, 60, 100, 9.0), 0.0)
    s.add(Note(0.0, "keys", 3, 62, 100, 9.0), 0.0)
    s.add(Note(0.0, "bass", 1, 36, 100, 9.0), 0.0)
    s.due(0.0)
    s.add(AllNotesOff(1.0, "keys", channel=3), 1.0)
    assert hexes(s.due(1.0)) == [(1.0, "keys", "83 3e 00"), (1.0, "keys", "b3 7b 00")]
    s.add(AllNotesOff(2.0), 2.0)   # every output, every channel
    assert sorted(hexes(s.due(2.0))) == sorted([
        (2.0, "keys", "80 3c 00"), (2.0, "bass", "81 24 00"), (2.0, "keys", "b0 7b 00"),
        (2.0, "keys", "b3 7b 00"), (2.0, "bass", "b1 7b 00")])
    assert s.due(20.0) == []       # the cancelled note-offs are gone


def test_controls_programs_and_stop_silence():
    s = MidiScheduler()
    s.add(ProgramChange(0.0, "keys", 4, 12), 0.0)
    s.add(ControlChange(0.5, "keys", 4, 7, 99), 0.0)
    s.add(Note(0.5, "keys", 4, 72, 60, 3.0), 0.0)
    s.add(Note(9.0, "keys", 4, 74, 60, 1.0), 0.0)
    assert hexes(s.due(1.0)) == [(0.0, "keys", "c4 0c"), (0.5, "keys", "b4 07 63"),
                                 (0.5, "keys", "94 48 3c")]
    assert hexes(s.silence(1.2)) == [(1.2, "keys", "84 48 00"), (1.2, "keys", "b4 7b 00")]
    assert s.pending == 0 and s.sounding == 0 and s.due(100.0) == []


@pytest.mark.parametrize("event,why", [
    (Note(0.0, "k", 16, 60, 100, 1.0), "channel 16 is not a whole number 0-15"),
    (Note(0.0, "k", 0, 128, 100, 1.0), "note 128"),
    (Note(0.0, "k", 0, 60, 0, 1.0), "velocity 0"),
    (Note(0.0, "k", 0, 60, 100, 0.0), "duration 0.0"),
    (Note(float("nan"), "k", 0, 60, 100, 1.0), "time nan"),
    (ControlChange(0.0, "k", 0, 7, 300), "value 300"),
    (ProgramChange(0.0, "k", 0, True), "program True"),
])
def test_bad_events_are_counted_not_played(event, why):
    s = MidiScheduler()
    assert s.add(event, 0.0) is False
    assert s.stats["bad"] == 1 and why in s.last_bad
    assert s.due(10.0) == []


def test_late_events_are_counted_and_played_at_once():
    s = MidiScheduler()
    s.add(Note(1.0, "k", 0, 60, 100, 0.1), now=1.5)
    assert s.stats["late"] == 1 and len(s.due(1.5)) == 2


# ---------------------------------------------------------------- Standard MIDI File

def test_varlen():
    assert [varlen(v).hex() for v in (0, 0x40, 0x7F, 0x80, 0x2000, 0x3FFF, 0x4000, 0x0FFFFFFF)] == \
        ["00", "40", "7f", "8100", "c000", "ff7f", "818000", "ffffff7f"]


def test_smf_is_valid_after_every_flush_and_keeps_real_timing(tmp_path):
    path = tmp_path / "show.mid"
    w = SmfWriter(path, t0=100.0, name="liminal")
    w.write(100.5, bytes((0x90, 60, 100)))
    w.write(101.25, bytes((0x80, 60, 0)))
    w.flush()
    first = mido.MidiFile(path)
    w.write(102.0, bytes((0x91, 62, 90)))
    w.write(101.0, bytes((0x81, 62, 0)))   # out of order (a late event): clamped, never back
    w.close()
    assert [m.type for m in first.tracks[0] if not m.is_meta] == ["note_on", "note_off"]
    f = mido.MidiFile(path)
    assert f.type == 0 and f.ticks_per_beat == 960
    times, t = [], 0.0
    for m in f:                      # mido applies the tempo: seconds between messages
        t += m.time
        if not m.is_meta:
            times.append((round(t, 4), m.type, m.channel, m.note))
    assert times == [(0.5, "note_on", 0, 60), (1.25, "note_off", 0, 60), (2.0, "note_on", 1, 62),
                     (2.0, "note_off", 1, 62)]
    assert f.tracks[0].name == "liminal"
    assert round(1 / TICKS_PER_S * 1000, 3) == 0.521   # ms per tick


class _Clock:
    """time.monotonic and time.sleep for ports.py: sleeping advances the clock."""

    def __init__(self):
        self.t, self.slept = 100.0, []

    def monotonic(self):
        return self.t

    def sleep(self, s):
        self.slept.append(round(s, 6))
        self.t += s


class _Out:
    def __init__(self, clock):
        self.clock, self.calls = clock, []

    def send_message(self, data):
        self.calls.append(("send", self.clock.t))

    def close_port(self):
        self.calls.append(("close", self.clock.t))

    def delete(self):
        self.calls.append(("delete", self.clock.t))


@pytest.mark.parametrize("api, quiet_s, slept", [
    (rtmidi.API_UNIX_JACK, 0.0, [0.1]),       # sent just now: JACK's next periods copy it
    (rtmidi.API_UNIX_JACK, 0.03, [0.07]),     # only the rest of the drain time
    (rtmidi.API_UNIX_JACK, 0.5, []),          # long quiet: closes at once
    (rtmidi.API_LINUX_ALSA, 0.0, []),         # the ALSA sequencer takes each message as sent
])
def test_a_jack_port_lets_its_last_messages_out_before_it_closes(monkeypatch, api, quiet_s,
                                                                  slept):
    """RtMidi as python-rtmidi builds it unregisters a JACK port without waiting for the
    process callback, which lost the all-notes-off sent at stop (CI, stop 27)."""
    clock = _Clock()
    monkeypatch.setattr(midi_ports, "time", clock)
    port = object.__new__(PortSink)
    port.name, port.api_id, port.connected, port._last_send = "keys", api, True, -1e9
    port.sent = port.errors = port.dropped = 0
    port._out = out = _Out(clock)
    port.send(b"\xb0\x7b\x00")
    clock.t += quiet_s
    port.close()
    assert clock.slept == slept
    assert [c for c, _ in out.calls] == ["send", "close", "delete"]
    if api == rtmidi.API_UNIX_JACK:
        assert out.calls[1][1] - out.calls[0][1] >= midi_ports.JACK_DRAIN_S - 1e-9
    assert port._out is None


# ---------------------------------------------------------------- the view, with fake ports

class FakePort(PortSink):
    """A PortSink that opens nothing and records (clock time, bytes)."""

    opened: list["FakePort"] = []

    def __init__(self, name, api, client="stage", existing=True):
        self.name, self.client, self.existing = name, client, existing
        self.where = f"fake port '{client}:{name}'"
        self.got: list[tuple[float, str]] = []
        self.closed = False
        self.sent = self.errors = 0
        FakePort.opened.append(self)

    def send(self, data):
        self.got.append((CLOCK.now(), bytes(data).hex(" ")))
        self.sent += 1

    def close(self):
        self.closed = True


CLOCK = ManualClock(0.0)


@pytest.fixture
def fake_ports(monkeypatch):
    global CLOCK
    CLOCK = ManualClock(50.0)
    FakePort.opened = []
    monkeypatch.setattr(midi_view, "PortSink", FakePort)
    monkeypatch.setattr(midi_view, "choose_api", lambda: (2, "fake"))
    return CLOCK


def play(host: ViewHost, clock: ManualClock, until: float) -> None:
    """Run an unthreaded host's deadlines until ``until`` (what the view thread does)."""
    while True:
        host.pump()
        nxt = host.next_deadline()
        if nxt is None or nxt > until:
            break
        clock.set(max(clock.now(), nxt))
    clock.set(max(clock.now(), until))
    host.pump()


def test_outputs_get_their_own_ports_channels_and_precise_note_offs(fake_ports):
    clock = fake_ports
    outputs = [OutputDecl("keys", "midi"), OutputDecl("bass", "midi", "Synth B"),
               OutputDecl("lights", "osc", "127.0.0.1:9000")]
    host = ViewHost.for_play(outputs, clock=clock, plugins=False, threaded=False).start()
    keys, bass = FakePort.opened
    assert (keys.name, keys.client, keys.existing) == ("keys", "stage", False)
    assert (bass.name, bass.client, bass.existing) == ("Synth B", "stage-2", True)
    host.emit([Note(50.1, "keys", 0, 60, 100, 0.3), Note(50.2, "bass", 1, 36, 80, 0.05),
               MappingValue(50.0, "height", 0.5)])
    play(host, clock, 51.0)
    host.stop()
    assert keys.got == [(50.1, "90 3c 64"), (pytest.approx(50.4), "80 3c 00"),
                        (51.0, "b0 7b 00")]
    assert bass.got == [(50.2, "91 24 50"), (pytest.approx(50.25), "81 24 00"),
                        (51.0, "b1 7b 00")]
    assert keys.closed and bass.closed


def test_stop_sends_note_offs_for_sounding_notes_and_drops_pending(fake_ports):
    clock = fake_ports
    host = ViewHost.for_play([OutputDecl("keys", "midi")], clock=clock, plugins=False,
                             threaded=False).start()
    host.emit([Note(50.0, "keys", 0, 60, 100, 10.0), Note(55.0, "keys", 0, 62, 100, 1.0)])
    play(host, clock, 51.0)
    host.stop()
    host.stop()
    (port,) = FakePort.opened
    assert port.got == [(50.0, "90 3c 64"), (51.0, "80 3c 00"), (51.0, "b0 7b 00")]
    assert host.stats()["midi"]["view"]["cancelled"] == 1


def test_events_for_an_undeclared_output_go_to_the_default_one_with_one_warning(fake_ports,
                                                                              caplog):
    clock = fake_ports
    host = ViewHost.for_play([], midi_port="Synth", clock=clock, plugins=False,
                             threaded=False).start()
    with caplog.at_level(logging.WARNING):
        host.emit([Note(50.0, "piano", 3, 60, 100, 0.1), Note(50.0, "piano", 3, 64, 100, 0.1)])
        play(host, clock, 50.05)
    (port,) = FakePort.opened
    assert port.name == "Synth" and port.got == [(50.0, "93 3c 64"), (50.0, "93 40 64")]
    assert sum("undeclared" in r.getMessage() or "does not declare" in r.getMessage()
               for r in caplog.records) == 1
    host.stop()


def test_no_midi_system_means_one_warning_and_a_file_with_real_timing(monkeypatch, tmp_path,
                                                                    caplog):
    clock = ManualClock(10.0)
    monkeypatch.setattr(midi_view, "choose_api",
                        lambda: (None, "no ALSA sequencer (/dev/snd/seq) and no JACK server"))
    with caplog.at_level(logging.WARNING):
        host = ViewHost.for_play([OutputDecl("keys", "midi"), OutputDecl("bass", "midi")],
                                 clock=clock, plugins=False, threaded=False,
                                 plugin_options={"midi": {"fallback_dir": tmp_path}}).start()
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "no MIDI port available" in warnings[0]
    assert "no JACK server" in warnings[0] and ".mid" in warnings[0]
    host.emit([Note(10.5, "keys", 0, 60, 100, 0.25), Note(11.0, "bass", 1, 36, 100, 0.5)])
    play(host, clock, 12.0)
    host.stop()
    (path,) = tmp_path.glob("stage-*.mid")
    got, t = [], 0.0
    for m in mido.MidiFile(path):
        t += m.time
        if not m.is_meta and m.type.startswith("note"):
            got.append((round(t, 3), m.type, m.channel, m.note))
    assert got == [(0.5, "note_on", 0, 60), (0.75, "note_off", 0, 60),
                   (1.0, "note_on", 1, 36), (1.5, "note_off", 1, 36)]


def test_midi_file_option_records_everything_and_replaces_virtual_ports(fake_ports, tmp_path):
    clock = fake_ports
    out = tmp_path / "take1.mid"
    host = ViewHost.for_play([OutputDecl("keys", "midi"), OutputDecl("bass", "midi", "Synth B")],
                             midi_file=str(out), clock=clock, plugins=False,
                             threaded=False).start()
    (bass,) = FakePort.opened           # no virtual port for 'keys': it goes to the file
    host.emit([Note(50.0, "keys", 0, 60, 100, 0.1), Note(50.0, "bass", 1, 36, 100, 0.1)])
    play(host, clock, 51.0)
    host.stop()
    notes = [(m.type, m.channel) for m in mido.MidiFile(out) if m.type.startswith("note")]
    assert notes == [("note_on", 0), ("note_on", 1), ("note_off", 0), ("note_off", 1)]
    assert [g[1][:2] for g in bass.got] == ["91", "81", "b1"]


def test_midi_file_in_a_missing_folder_is_a_user_error(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        ViewHost.for_play([], midi_file=str(tmp_path / "nope" / "x.mid"), plugins=False)


def test_midi_clock_ticks_24_per_beat_with_start_and_stop(fake_ports):
    clock = fake_ports
    host = ViewHost.for_play([], midi_port="clocked", midi_clock_bpm=120, clock=clock,
                             plugins=False, threaded=False).start()
    play(host, clock, 51.0)            # one second at 120 bpm: 2 beats, 48 pulses (+ the first)
    host.stop()
    (port,) = FakePort.opened
    kinds = [d for _, d in port.got]
    assert kinds[0] == "fa" and kinds[-1] == "fc"
    pulses = [t for t, d in port.got if d == "f8"]
    assert len(pulses) == 49 and pulses[1] - pulses[0] == pytest.approx(60 / 120 / 24)


def test_bad_events_do_not_stop_the_view(fake_ports, caplog):
    clock = fake_ports
    host = ViewHost.for_play([OutputDecl("keys", "midi")], clock=clock, plugins=False,
                             threaded=False).start()
    with caplog.at_level(logging.WARNING):
        host.emit([Note(50.0, "keys", 0, 200, 100, 0.1), Note(50.0, "keys", 0, 60, 100, 0.1)])
        play(host, clock, 50.5)
    assert host.stats()["midi"]["state"] == "running"
    assert host.stats()["midi"]["view"]["bad"] == 1
    assert any("note 200" in r.getMessage() for r in caplog.records)
    host.stop()


# ---------------------------------------------------------------- API choice and names

def test_port_matching_exact_then_client_prefix_never_substring():
    ports = ["Midi Through:Midi Through Port-0 14:0", "fluidsynth:midi_00", "bench-rx:in",
             "Synth A 128:0"]
    assert match_port("fluidsynth:midi_00", ports) == 1
    assert match_port("FLUIDSYNTH:MIDI_00", ports) == 1
    assert match_port("fluidsynth", ports) == 1
    assert match_port("Synth A", ports) == 3
    assert match_port("bench", ports) is None      # a new port named 'bench', not bench-rx
    with pytest.raises(TransportError, match="ambiguous"):
        match_port("x", ["x:1", "x:2"])


def test_api_choice_follows_the_environment(monkeypatch):
    import rtmidi
    monkeypatch.setenv("STAGE_MIDI_API", "jack")
    assert choose_api()[0] == rtmidi.API_UNIX_JACK
    monkeypatch.setenv("STAGE_MIDI_API", "nonsense")
    assert choose_api()[0] is None and "unknown MIDI API" in choose_api()[1]
    monkeypatch.delenv("STAGE_MIDI_API")
    monkeypatch.setenv("MIDO_BACKEND", "mido.backends.rtmidi/UNIX_JACK")
    assert choose_api()[0] == rtmidi.API_UNIX_JACK
    monkeypatch.delenv("MIDO_BACKEND")
    monkeypatch.setenv("JACK_DEFAULT_SERVER", "stage-nobody-runs-this")
    if not os.path.exists("/dev/snd/seq"):
        assert choose_api() == (None, "no ALSA sequencer (/dev/snd/seq) and no JACK server running")


# ---------------------------------------------------------------- real peer: JACK

DUMP_LINE = re.compile(r"^\s*(\d+):((?: [0-9a-f]{2})+)(?= |$)")


#: the jackd processes of the running ``jack_server`` fixture (a test may restart it)
jack_server_processes: list = []


@pytest.fixture
def jack_server(monkeypatch, tmp_path):
    """A private JACK server with the dummy driver; JACK_DEFAULT_SERVER points at it.

    The name comes from a small fixed pool (not the pid), so a server that had to be killed
    leaves a registry entry that the next run with that name reclaims.
    """
    for tool in ("jackd", "jack_connect", "jack_midi_dump", "jack_lsp"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} not installed: apt-get install jackd2")
    for name in ("stage-test-1", "stage-test-2", "stage-test-3"):
        busy = subprocess.run(["jack_lsp"], capture_output=True,
                              env=dict(os.environ, JACK_DEFAULT_SERVER=name)).returncode == 0
        if not busy:
            break
    else:
        pytest.skip("three JACK test servers are already running (other test runs)")
    monkeypatch.setenv("JACK_DEFAULT_SERVER", name)
    log = tmp_path / "jackd.log"
    with open(log, "w") as err:
        try:
            proc = start_dummy_jackd(name, 256, 48000, log=err)
        except RuntimeError as exc:
            pytest.fail(f"{exc}: {log.read_text()[-500:]}")
    jack_server_processes[:] = [proc]
    try:
        assert jack_server_running(name)
        yield name
    finally:
        for running in jack_server_processes:  # a test may stop and restart it
            stop_jackd(running)


def dump_events(lines: list[str]) -> list[str]:
    """The MIDI bytes (hex) of jack_midi_dump's lines so far."""
    return [m.group(2).strip() for m in map(DUMP_LINE.match, list(lines)) if m]


@pytest.mark.integration
def test_scripted_notes_reach_jack_midi_dump_in_order_on_their_channels(jack_server):
    dump, lines, reader = start_midi_dump()
    try:
        host = ViewHost.for_play([OutputDecl("keys", "midi"), OutputDecl("bass", "midi")],
                                 midi_port=None, plugins=False).start()
        try:
            assert host.stats()["midi"]["state"] == "running", host.summary()
            for port in ("stage:keys", "stage-2:bass"):
                done = subprocess.run(["jack_connect", port, "dump:input"], capture_output=True,
                                      text=True)
                assert done.returncode == 0, done.stderr
            now = host.clock.now() + 0.1
            # a short scripted passage: a chord on keys (channel 1), a bass line (channel 3),
            # a program and a control change, then the section ends with all notes off
            host.emit([ProgramChange(now, "keys", 0, 5), Note(now, "keys", 0, 60, 100, 0.30),
                       Note(now + 0.05, "bass", 2, 36, 90, 0.10),
                       Note(now + 0.10, "keys", 0, 64, 80, 0.40),
                       ControlChange(now + 0.17, "keys", 0, 7, 64),
                       Note(now + 0.22, "bass", 2, 38, 90, 0.10),
                       AllNotesOff(now + 0.35, "keys"),
                       Note(now + 0.45, "keys", 0, 67, 70, 0.05)])
            time.sleep(0.7)
        finally:
            host.stop()
        # jack_midi_dump prints from its main thread, which a loaded machine wakes late:
        # wait for the 13 events and the stop's (up to 5 s) rather than a fixed time
        deadline = time.monotonic() + 5
        while (len(dump_events(lines)) < 13 + 2 * (1 + midi_ports.JACK_STOP_REPEATS)
               and time.monotonic() < deadline):
            time.sleep(0.05)
    finally:
        dump.terminate()
        dump.wait(timeout=5)
        reader.join(timeout=5)
    out = "".join(lines)
    events = []
    for line in out.splitlines():
        m = DUMP_LINE.match(line)
        if m:
            events.append((int(m.group(1)), m.group(2).strip()))
    got = [data for _, data in events]
    assert got[:13] == ["c0 05", "90 3c 64", "92 24 5a", "90 40 50", "82 24 00", "b0 07 40",
                        "92 26 5a", "80 3c 00", "82 26 00",       # the chord's first note ends
                        "80 40 00", "b0 7b 00",                   # all notes off: 64 cut short
                        "90 43 46", "80 43 00"], out
    # stop: all notes off on every channel each output used (ports flush in any order), and
    # the same again JACK_STOP_REPEATS times (a client in an xrun would have missed it)
    stop = got[13:]
    assert sorted(set(stop)) == ["b0 7b 00", "b2 7b 00"], out
    assert [stop.count(m) for m in sorted(set(stop))] == [1 + midi_ports.JACK_STOP_REPEATS] * 2, out
    frames = {data: f for f, data in events}
    rate = 48000
    # each note-off follows its note-on by about the note's own duration (the order above
    # already pins every event between its neighbours in time). How precisely JACK delivers
    # (a period, 5.3 ms here, on a quiet machine) is a figure bench/bench_midi.py measures, not
    # something a test asserts: a loaded machine wakes the view's thread late (55 ms seen with
    # six test suites running at once), so this check only catches a grossly wrong schedule
    assert abs((frames["80 3c 00"] - frames["90 3c 64"]) / rate - 0.30) < 0.1
    assert abs((frames["82 24 00"] - frames["92 24 5a"]) / rate - 0.10) < 0.1
    assert abs((frames["80 40 00"] - frames["90 3c 64"]) / rate - 0.35) < 0.1


@pytest.mark.integration
def test_a_port_whose_jack_server_dies_is_reopened_when_it_comes_back(jack_server, monkeypatch):
    monkeypatch.setenv("STAGE_MIDI_API", "jack")
    api, _ = choose_api()
    port = PortSink("keys", api, "stage", existing=False)
    try:
        assert port.state()["connected"] and port.check() is None
        # the JACK server is killed (stop_jackd) mid-show: the port is lost, sends are counted
        proc = jack_server_processes.pop()
        stop_jackd(proc)
        change = port.check()
        assert change is not None and "JACK server is gone" in change
        port.send(bytes((0x90, 60, 64)))
        state = port.state()
        assert not state["connected"] and state["reconnecting"] and state["dropped"] == 1
        assert port.check() is None                       # still gone: nothing new
        # it comes back: the port is reopened and notes reach a synth connected to it
        jack_server_processes.append(start_dummy_jackd(jack_server, 256, 48000))
        change = port.check()
        assert change is not None and "is back" in change and port.state()["reconnects"] == 1
        dump, lines, reader = start_midi_dump()
        try:
            done = subprocess.run(["jack_connect", "stage:keys", "dump:input"],
                                  capture_output=True, text=True)
            assert done.returncode == 0, done.stderr
            port.send(bytes((0x90, 60, 64)))
            time.sleep(0.3)
        finally:
            dump.terminate()
            dump.wait(timeout=5)
            reader.join(timeout=5)
        assert "90 3c 40" in "".join(lines)
    finally:
        port.close()


def _sounding(events: list[str]) -> dict[tuple[int, int], int]:
    """(channel, pitch) -> notes on and not yet ended after ``events`` (hex lines as
    jack_midi_dump prints them; note-off, note-on velocity 0 and all-notes-off end notes)."""
    on: dict[tuple[int, int], int] = {}
    for data in events:
        b = [int(x, 16) for x in data.split()]
        kind, channel = b[0] & 0xF0, b[0] & 0x0F
        if kind == 0x90 and b[2] > 0:
            on[(channel, b[1])] = on.get((channel, b[1]), 0) + 1
        elif kind == 0x80 or kind == 0x90:
            if on.get((channel, b[1])):
                on[(channel, b[1])] -= 1
        elif kind == 0xB0 and b[1] == 123:
            on = {k: v for k, v in on.items() if k[0] != channel}
    return {k: v for k, v in on.items() if v}


@pytest.mark.integration
def test_a_performer_stopping_mid_phrase_leaves_no_note_sounding_on_jack(jack_server,
                                                                         monkeypatch):
    """`stage play` on a real JACK MIDI port, SIGTERM while a phrase sounds: what a synth
    connected to the port received ends every note (the stop's all-notes-off arrives)."""
    monkeypatch.setenv("STAGE_MIDI_API", "jack")
    dump, lines, reader = start_midi_dump()
    piece = str(Path(__file__).resolve().parents[1] / "pieces" / "liminal.yaml")
    proc = subprocess.Popen([sys.executable, "-m", "stage.cli", "play", piece, "--sim",
                             "--seed", "1"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        deadline = time.monotonic() + 30
        while "stage:cello" not in subprocess.run(["jack_lsp"], capture_output=True,
                                                  text=True).stdout:
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.05)
        done = subprocess.run(["jack_connect", "stage:cello", "dump:input"],
                              capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        # stop while the synth has a note sounding (as jack_midi_dump saw it)
        while not _sounding(dump_events(lines)):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.01)
        proc.send_signal(signal.SIGTERM)
        before = dump_events(lines)
        out, err = proc.communicate(timeout=20)
        # (jack_midi_dump prints from a thread a loaded machine wakes late: wait for the
        # stop's all-notes-off, after what it had printed at the signal)
        quiet = time.monotonic() + 5
        while "b0 7b 00" not in dump_events(lines)[len(before):] and time.monotonic() < quiet:
            time.sleep(0.05)
    finally:
        if proc.poll() is None:
            proc.kill()
        dump.terminate()
        dump.wait(timeout=5)
        reader.join(timeout=5)
    assert proc.returncode == 130, err
    events = dump_events(lines)
    # a note was sounding when the performer stopped; it ended (its own note-off, due while
    # the show stopped, or the stop's all-notes-off), and the stop's all-notes-off came last
    assert _sounding(before), events
    assert _sounding(events) == {}, events
    assert events[-1] == "b0 7b 00", events
