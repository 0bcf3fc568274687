"""`stage play`: a piece performed by a show (``stage.app.show``), with what a performer sees.

The show assembles the source (real sensors, ``--sim``, ``--replay``), the
engine, the calibrator, the piece runtime and the views; this module adds
the performer's side: the banner, the operator's safety (console keys and an
OSC port that force a section) and the closing summary. ``offline=True``
runs the simulator or the recording in-process on a manual clock, as fast as
the machine goes (tests, rendering a rehearsal to a MIDI file); the events
are the same as in real time for the same seed.

On stop -- Ctrl-C, SIGTERM, the end of ``--duration`` or of the source --
pending notes are cancelled, every sounding note gets its note-off and the
outputs are flushed.
"""

from __future__ import annotations

import logging
import socket
import sys
import threading
from typing import Callable, TextIO

from ..errors import ConfigError
from ..piece.narrator import Narrator
from .show import PIECE_SCENARIO, Show, ShowOptions, ShowResult, _soon

log = logging.getLogger("stage.piece.play")

#: `stage play`'s options are a show's options (the piece is required)
PlayOptions = ShowOptions
#: and its result a show's result (piece, runtime, recorded events, views, seconds)
PlayResult = ShowResult


class Player:
    """One performance. ``run()`` blocks until the end and returns a PlayResult."""

    def __init__(self, opts: PlayOptions, out: TextIO | None = None,
                 stop_event: threading.Event | None = None) -> None:
        if not opts.piece:
            raise ConfigError("stage play needs a piece")
        self.show = Show(opts, out, stop_event)
        self.opts, self.piece, self.seed = opts, self.show.piece, self.show.seed
        self.stop_event = self.show.stop_event

    def run(self) -> PlayResult:
        show = self.show
        show.start()
        try:
            narrator = show.narrator
            assert narrator is not None and self.piece is not None
            self._banner(narrator)
            if not self.opts.offline and show.engine is not None and show.runtime is not None:
                for closer in self._safety(show, narrator):
                    show.add_closer(closer)
            interrupted = show.wait()
        except BaseException:
            show.stop()
            raise
        result = show.stop(interrupted)
        self._finish(narrator, result)
        return result

    def _banner(self, narrator: Narrator) -> None:
        p, show = self.piece, self.show
        narrator.say(f"stage play: \"{p.title}\"" + (f" ({p.composer})" if p.composer else "")
                     + f" -- {len(p.sections)} sections, seed {self.seed}; source: "
                     + show.describe_source())
        if show.host is not None:
            for line in show.host.summary():
                narrator.say(f"  view {line}")
        if show.events_file is not None:
            narrator.say(f"  events -> {show.events_file.path}")

    def _finish(self, narrator: Narrator, result: PlayResult) -> None:
        runtime = result.runtime
        assert runtime is not None
        c = runtime.counts
        seen = list(dict.fromkeys(runtime.visited))
        cuts = [f"{c[k]} {word}" for k, word in (("cancelled", "cancelled before they sounded"),
                                                  ("shortened", "cut short")) if c[k]]
        narrator.say(f"stage play: stopped after {result.seconds:.1f} s"
                     + (" (the piece has ended)" if runtime.ended else "")
                     + f"; sections reached: {len(seen)}/{len(self.piece.sections)} "
                     f"({', '.join(seen)}); {c['fired']} triggers fired, {c['notes']} notes "
                     f"sounded" + (f" ({', '.join(cuts)})" if cuts else "")
                     + (f", {c['skipped']} phrase{'s' if c['skipped'] != 1 else ''} not "
                        "played" if c["skipped"] else "")
                     + (f", {c['errors']} runtime errors (see log)" if c["errors"] else ""))
        for line in result.views:
            narrator.say(f"  view {line}")

    # ------------------------------------------------------------ safety
    def _safety(self, show: Show, console: Narrator) -> list[Callable[[], None]]:
        """The cellist's / operator's way to force a section: console keys and an OSC port."""
        closers: list[Callable[[], None]] = []
        s = self.piece.safety
        engine, runtime = show.engine, show.runtime

        def force(target: str, cause: str) -> None:
            _soon(engine, lambda e: runtime.goto(target, e.clock.now(), cause))

        if s.keys and sys.stdin is not None and sys.stdin.isatty():
            console.say("  safety: type n + Enter for the next section, p + Enter for the "
                        "previous, or a section's number or name")
            names = [sec.name for sec in self.piece.sections]

            def keys() -> None:
                for line in sys.stdin:
                    word = line.strip()
                    if self.stop_event.is_set():
                        return
                    if word in ("n", "next"):
                        force("next", "operator")
                    elif word in ("p", "previous"):
                        force("previous", "operator")
                    elif word.isdigit() and 1 <= int(word) <= len(names):
                        force(names[int(word) - 1], "operator")
                    elif word in names:
                        force(word, "operator")
                    elif word:
                        console.say(f"  safety: '{word}'? n, p, 1-{len(names)} or a section name")
            threading.Thread(target=keys, name="stage-safety-keys", daemon=True).start()
        if s.osc_port is not None:
            closers.append(osc_safety(s.osc_port, [sec.name for sec in self.piece.sections],
                                      force, self.stop_event, console))
        return closers


def osc_safety(port: int, names: list[str], force: Callable[[str, str], None],
               stop: threading.Event, console: Narrator) -> Callable[[], None]:
    """Listen on UDP ``port`` for ``/stage/section next|previous|NAME|NUMBER``; returns a closer.

    NUMBER counts from 1 in the piece's order.
    """
    from pythonosc.osc_message import OscMessage
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind(("0.0.0.0", port))
    except OSError as exc:  # the show goes on without it; the console keys may still work
        sock.close()
        log.warning("cannot listen for the safety on udp port %d (%s): no OSC safety this time",
                    port, exc.strerror)
        return lambda: None
    sock.settimeout(0.2)
    console.say(f"  safety: send /stage/section next|previous|NAME to udp port {port}")

    def run() -> None:
        while not stop.is_set():
            try:
                data, _ = sock.recvfrom(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            try:
                msg = OscMessage(data)
            except Exception:
                log.warning("safety port: a datagram that is not OSC was ignored")
                continue
            if msg.address == "/stage/section" and msg.params:
                arg = msg.params[0]
                if isinstance(arg, int) and 1 <= arg <= len(names):
                    arg = names[arg - 1]
                force(str(arg), "operator (OSC)")
            else:
                log.warning("safety port: ignored %s (expected /stage/section next|previous|NAME)",
                            msg.address)
    thread = threading.Thread(target=run, name="stage-safety-osc", daemon=True)
    thread.start()

    def close() -> None:
        stop.set()
        thread.join(timeout=1.0)
        sock.close()
    return close


def play(opts: PlayOptions, out: TextIO | None = None,
         stop_event: threading.Event | None = None) -> PlayResult:
    """Run one performance (see module docstring)."""
    return Player(opts, out, stop_event).run()


__all__ = ["PlayOptions", "PlayResult", "Player", "play", "PIECE_SCENARIO"]
