"""MIDI at stop over JACK: do the last messages sent before a port closes arrive?

``stage play`` ends by sending all-notes-off on every channel it used and closing its
ports. python-rtmidi builds RtMidi without its semaphore, so RtMidi's own close
unregisters a JACK port without waiting for JACK's process callback to copy what was
just sent. ``PortSink.close`` therefore keeps a JACK port open until ``JACK_DRAIN_S``
after its last message. This bench opens ``--ports`` ports one after another on a dummy
JACK server, each connected to ``jack_midi_dump``, sends two control changes on each and
closes it, and counts what the dump received, for each drain time in ``--drains``
(0 is RtMidi's own close, the reference) and the shipped default. ``--load N`` runs N
busy loops meanwhile: the loss shows on a loaded machine, which a stage machine running
a video or a DAW is.

The second loss is the receiver's: a JACK client starved by the load misses whole periods
(an xrun) and the MIDI in them. So a JACK port sends the stop's silence again
(``JACK_STOP_REPEATS`` times, ``JACK_STOP_REPEAT_S`` apart) before it drains. ``--repeats``
compares repeat counts at the shipped drain (0: none, the reference). Each port's two
messages are note-offs that name it (key = port number, channels 0 and 1), so a message
counts as received when at least one copy of it arrived.

    python bench/bench_midi_stop.py                    # 30 ports, drains 0 and default, load 3
    python bench/bench_midi_stop.py --drains 0,0.02,0.05 --load 0
    python bench/bench_midi_stop.py --repeats 0,3 --load 6
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import rtmidi  # noqa: E402

import stage_plugins.midi.ports as ports  # noqa: E402
from stage.testing.jack import start_dummy_jackd, start_midi_dump, stop_jackd  # noqa: E402

#: a jack_midi_dump line: its frame time and the message's bytes (hex)
DUMP_LINE = re.compile(r"^\s*(\d+):((?: [0-9a-f]{2})+)(?= |$)")


def run(drain: float, n: int, repeats: int = 0) -> tuple[int, int]:
    """(sent, received) for n ports closed ``drain`` s after their last message, having
    sent their two messages again ``repeats`` times at close (received: distinct messages
    that arrived at least once)."""
    dump, lines, reader = start_midi_dump()
    saved = ports.JACK_DRAIN_S, ports.JACK_STOP_REPEATS
    ports.JACK_DRAIN_S, ports.JACK_STOP_REPEATS = drain, repeats
    try:
        for i in range(n):
            sink = ports.PortSink(f"p{i}", rtmidi.API_UNIX_JACK, client=f"stop{i}",
                                  existing=False)
            subprocess.run(["jack_connect", f"stop{i}:p{i}", "dump:input"], check=True)
            time.sleep(0.02)
            mine = [bytes((0x80, i % 128, 0)), bytes((0x81, i % 128, 0))]
            for data in mine:
                sink.send(data)
                sink.again_at_close(data)
            sink.close()
    finally:
        ports.JACK_DRAIN_S, ports.JACK_STOP_REPEATS = saved
    time.sleep(1.0)
    dump.terminate()
    dump.wait(timeout=5)
    reader.join(timeout=5)
    got = {m.group(2).strip() for m in map(DUMP_LINE.match, lines) if m}
    return 2 * n, sum(f"{0x80 | c:02x} {i % 128:02x} 00" in got for i in range(n) for c in (0, 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ports", type=int, default=30)
    parser.add_argument("--drains", default=f"0,{ports.JACK_DRAIN_S}",
                        help="drain times in s, comma-separated (0: RtMidi's own close)")
    parser.add_argument("--repeats", default="0",
                        help="repeat counts at close, comma-separated, each at the shipped "
                             f"drain (0: none; shipped: {ports.JACK_STOP_REPEATS})")
    parser.add_argument("--load", type=int, default=3, help="busy loops running meanwhile")
    parser.add_argument("--rounds", type=int, default=2, help="each drain this many times")
    args = parser.parse_args()
    for tool in ("jackd", "jack_midi_dump", "jack_connect", "jack_lsp"):
        if shutil.which(tool) is None:
            raise SystemExit(f"{tool} not found: apt-get install jackd2")
    name = f"stage-bench-stop-{os.getpid()}"
    os.environ["JACK_DEFAULT_SERVER"] = name
    server = start_dummy_jackd(name, 256, 48000)
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(args.load)]
    try:
        print(f"{args.ports} ports x 2 messages, dummy JACK 256 frames at 48 kHz, "
              f"{args.load} busy loop(s) on {os.cpu_count()} cores")
        drains = [float(d) for d in args.drains.split(",")]
        repeats = [int(k) for k in args.repeats.split(",")]
        configs = [(d, 0) for d in drains] + [(ports.JACK_DRAIN_S, k) for k in repeats if k]
        for r in range(args.rounds):
            for drain, again in configs:   # alternating, so a slow phase hits every one
                sent, got = run(drain, args.ports, again)
                label = "RtMidi's close" if drain == 0 else f"drain {drain * 1000:.0f} ms"
                if again:
                    label += f", {again} repeats"
                print(f"round {r + 1}  {label:>28}: sent {sent}, received {got}, "
                      f"lost {sent - got}", flush=True)
    finally:
        for p in busy:
            p.kill()
        stop_jackd(server)


if __name__ == "__main__":
    main()
