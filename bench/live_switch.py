"""A change to the live server's path measured inside one running server, burst by burst.

On this project's shared VMs the same tree reads +1.04 to +1.53 ms over the relay at in-step
6x6 from one ``bench_engine.py`` run to the next (issue 10, stop 56): a change worth a tenth
of a millisecond cannot be told from the noise by A/B runs minutes apart. Here one server
runs both ways at once: a wrapper around the real CLI for ``bench_engine.py --server-cmd``
(as ``live_parts.py``) switches the change on and off at each burst (a datagram read more
than 4 ms after the one before begins a burst: with sensors in step, one frame's datagrams;
spread, each datagram), and splits the engine's own per-skeleton latency (arrival of the
datagram -> its person's skeleton sent, what ``bench_engine.py`` reports) by the state the
switch had when the datagram arrived. Both halves share the machine's state to the second;
the relay ``bench_engine.py`` measures in the same run stays the outside reference.

The changes (``--switch``; each is built here, by wrapping the engine's methods, so that
it can be measured before it is written properly):

- ``decode-on-engine``: the receiver hands a datagram over undecoded once its source has
  named its client, and the engine thread decodes it when it comes to it, instead of the
  receiver decoding every datagram before it queues it.
- ``observers-after-burst``: the live calibrator's frame observer is called for a burst's
  frames after its last datagram, as its hand votes are, instead of as each frame is
  applied (built since: ``Engine.late_frame_observers``; off moves it back).
- ``fold-nogil``: the native core's fold kernel (some 45 us of a 6x6 datagram) lets the GIL
  go while it runs, so that the receiver can decode the next datagrams meanwhile.
- ``send-keeps-gil``: the engine's sends keep the GIL (libc ``sendto`` through
  ``ctypes.PyDLL``), so the receiver cannot take it at each of a datagram's six sends.
- ``receiver-prepares``: the receiver also computes a datagram's frames in stage space
  (``People.computed_frames``: transform, swapped limbs, variances; one compiled call) before
  it queues it; the engine takes them where the sensor's transform is still the one used,
  and computes them itself otherwise (built since: ``Engine.prepare_on_receipt``).

Run (the table is written every 3 s; the first 4 s of the server's emissions are left out)::

    STAGE_LIVE_SWITCH=/tmp/switch.txt python bench/bench_engine.py --configs 6x6 \\
        --modes aligned --no-offline --duration 20 --live \\
        --server-cmd "python bench/live_switch.py decode-on-engine serve"
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import live_parts  # noqa: E402

#: a datagram read this long after the one before begins a burst (in step: 33 ms apart)
BURST_GAP_S = 0.004
#: the server's first emissions left out (compiling, persons being found)
SETTLE_S = 4.0


class Switch:
    """The switch's state per burst, the state each arrival saw, and the latency samples."""

    def __init__(self) -> None:
        self.on = False
        self.last = 0.0
        self.seen: dict[float, bool] = {}
        self.samples: dict[bool, list[float]] = {False: [], True: []}
        self.started: float | None = None
        self.engine = None           # receiver-prepares: the engine, for its counts

    def arrival(self, t: float) -> bool:
        if t - self.last > BURST_GAP_S:
            self.on = not self.on
        self.last = t
        if len(self.seen) > 200_000:
            self.seen.clear()
        self.seen[t] = self.on
        return self.on

    def table(self, name: str) -> str:
        lines = [f"switch {name}; engine latency per skeleton (arrival -> skeleton sent), ms"]
        for state in (False, True):
            s = np.array(self.samples[state]) * 1e3
            if len(s):
                lines.append(f"  {'on ' if state else 'off'}: n {len(s)}  p50 "
                             f"{np.percentile(s, 50):.3f}  p90 {np.percentile(s, 90):.3f}  "
                             f"p99 {np.percentile(s, 99):.3f}  mean {s.mean():.3f}")
        if name == "receiver-prepares" and self.engine is not None:
            counts = self.engine.counts
            lines.append(f"  datagrams whose frames the engine took from the receiver: "
                         f"{counts['prepared']}; computed again (stale): "
                         f"{counts['prepared_stale']}")
        return "\n".join(lines) + "\n"


def _split_latency(sw: Switch) -> None:
    """Each latency sample the engine records, also under the switch state of its arrival."""
    from stage.engine import people as people_mod
    send_joints = people_mod.People._send_joints

    def timed(self, new):
        order = []      # the arrivals whose latency the call records, in its order
        for pid, arrivals in self._dirty.items():
            person = self.persons.get(pid)
            if person is not None and person.centre is not None:
                order.extend(arrivals)
        got: list[float] = []
        window = self.latency
        add = window.add
        window.add = got.append
        try:
            return send_joints(self, new)
        finally:
            del window.add
            now = time.perf_counter()
            if sw.started is None:
                sw.started = now
            if now - sw.started > SETTLE_S and len(got) == len(order):
                for arrival, value in zip(order, got):
                    state = sw.seen.get(arrival)
                    if state is not None:
                        sw.samples[state].append(value)
            for value in got:
                add(value)

    people_mod.People._send_joints = timed


def _mark_bursts(sw: Switch) -> None:
    """Every datagram the receiver reads tells the switch its arrival (``Switch.arrival``)
    before anything else sees it."""
    from stage.sensors import receiver as receiver_mod
    handle = receiver_mod.Receiver.handle

    def receive(self, data, source, arrival):
        sw.arrival(arrival)
        handle(self, data, source, arrival)

    receiver_mod.Receiver.handle = receive


def _decode_on_engine(sw: Switch) -> None:
    from stage.engine import engine as engine_mod
    from stage.sensors import receiver as receiver_mod
    from stage.sensors.protocol import decode_datagram
    from stage.sensors.messages import Inbound

    class Raw:
        __slots__ = ("data", "source", "arrival", "named")

        def __init__(self, data, source, arrival, named):
            self.data, self.source, self.arrival, self.named = data, source, arrival, named

    handle = receiver_mod.Receiver.handle

    def receive(self, data, source, arrival):
        entry, host = self._sources.get(source), self._hosts.get(source[0])
        engine = self.submit.__self__
        if sw.on and entry is not None and entry[1] is not None and host is not None and (
                self.allow is None or self.allow.allows(source[0])):
            # (the receiver's checks, as ``handle`` makes them, then the datagram as it came)
            if not (entry[0].take(arrival) and host.take(arrival)):
                self.drops.add(entry[1], "flood")
                return
            engine.queue.put_nowait(Raw(data, source, arrival, entry))
            engine.idle.clear()
            return
        handle(self, data, source, arrival)

    def decode(engine, raw):
        decoded = decode_datagram(raw.data, f"{raw.source[0]}:{raw.source[1]}")
        for client, reason in decoded.drops:
            engine.drops.add(client, reason)
        return [Inbound(m, raw.arrival, raw.source, tt) for m, tt in decoded.messages]

    process_taken = engine_mod.Engine.process_taken

    def taken(self, batch):
        if not any(type(item) is Raw for item in batch):
            return process_taken(self, batch)
        chunks, run = [], []
        for item in batch:           # a raw datagram is a chunk alone
            if type(item) is Raw:
                if run:
                    chunks.extend(engine_mod._by_datagram(run))
                    run = []
                chunks.append(item)
            else:
                run.append(item)
        if run:
            chunks.extend(engine_mod._by_datagram(run))
        if len(chunks) > engine_mod.BACKLOG_DATAGRAMS:
            chunks = [[x for c in chunks for x in (decode(self, c) if type(c) is Raw else c)]]
        last = len(chunks) - 1
        for k, chunk in enumerate(chunks):
            self.process(decode(self, chunk) if type(chunk) is Raw else chunk, votes=k == last)

    receiver_mod.Receiver.handle = receive
    engine_mod.Engine.process_taken = taken


def _receiver_prepares(sw: Switch) -> None:
    """Built into the engine since stop 57 (``Engine.prepare_on_receipt``, on by default):
    the switch sets it at each datagram's arrival."""
    from stage.sensors import receiver as receiver_mod
    handle = receiver_mod.Receiver.handle

    def receive(self, data, source, arrival):
        engine = self.submit_batch.__self__
        engine.prepare_on_receipt = sw.on
        sw.engine = engine
        handle(self, data, source, arrival)

    receiver_mod.Receiver.handle = receive


def _observers_after_burst(sw: Switch) -> None:
    """Built into the engine since stop 57 (``Engine.late_frame_observers``): off, the
    threaded calibrator's observer is moved back among the plain frame observers, called as
    each frame comes, as before."""
    from stage.engine import engine as engine_mod

    process_taken = engine_mod.Engine.process_taken
    moved: list = []

    def taken(self, batch):
        late, plain = self.late_frame_observers, self.frame_observers
        if not moved:
            moved.extend(late)
        for fn in moved:
            src, dst = (plain, late) if sw.on else (late, plain)
            if fn in src:
                src.remove(fn)
                dst.append(fn)
        return process_taken(self, batch)

    engine_mod.Engine.process_taken = taken


def _fold_nogil(sw: Switch) -> None:
    """The native core's fold kernel compiled a second time, letting the GIL go while it
    runs (``jit._NOGIL`` keeps it: see there why), used while the switch is on."""
    import numba
    from stage.engine import jit, native
    if not jit.warm_native():
        raise SystemExit("live_switch: the native core's kernel is unavailable here")
    name = "_native_fold"
    held = jit._compiled[name]
    free = numba.njit(jit._NATIVE_SIGNATURES[name], cache=False, nogil=True)(
        jit._PYTHON_NATIVE[name])
    fold = native.NativeCore.fold

    def switched(self, *args, **kwargs):
        jit._compiled[name] = free if sw.on else held
        return fold(self, *args, **kwargs)

    native.NativeCore.fold = switched


def _send_keeps_gil(sw: Switch) -> None:
    """The engine's sends through libc's ``sendto`` called with the GIL held (``ctypes.PyDLL``,
    ``MSG_DONTWAIT``; the socket's own ``sendto`` where it fails), so that the receiver does
    not take the GIL at each send and hold it while the engine waits to go on."""
    import ctypes
    import socket
    import struct
    from stage.sensors import receiver as receiver_mod

    libc = ctypes.PyDLL(None)
    sendto = libc.sendto
    sendto.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_size_t, ctypes.c_int,
                       ctypes.c_char_p, ctypes.c_uint32]
    sendto.restype = ctypes.c_ssize_t
    dontwait = getattr(socket, "MSG_DONTWAIT", 0x40)
    addresses: dict = {}
    plain = receiver_mod.UdpTransport.send

    def send(self, data, address):
        if not sw.on:
            return plain(self, data, address)
        raw = addresses.get(address)
        if raw is None:
            raw = addresses[address] = struct.pack("=H", socket.AF_INET) + struct.pack(
                "!H", address[1]) + socket.inet_aton(address[0]) + bytes(8)
        if sendto(self.sock.fileno(), data, len(data), dontwait, raw, len(raw)) < 0:
            return plain(self, data, address)   # (it raises what a send raises)

    receiver_mod.UdpTransport.send = send


#: the changes by name: each installs its wrappers, reading the burst's state from ``sw.on``
SWITCHES = {"decode-on-engine": _decode_on_engine, "receiver-prepares": _receiver_prepares,
            "observers-after-burst": _observers_after_burst, "fold-nogil": _fold_nogil,
            "send-keeps-gil": _send_keeps_gil}


def main() -> int:
    if len(sys.argv) < 2 or sys.argv[1] not in SWITCHES:
        print(f"usage: live_switch.py {{{','.join(SWITCHES)}}} serve|play ...", file=sys.stderr)
        return 2
    name = sys.argv[1]
    sw = Switch()
    _split_latency(sw)
    SWITCHES[name](sw)
    _mark_bursts(sw)       # (last: its wrapper runs first, before the change's own)
    return live_parts.run_cli(lambda: sw.table(name),
                              os.environ.get("STAGE_LIVE_SWITCH", "/tmp/stage-live-switch.txt"),
                              "live-switch", sys.argv[2:])


if __name__ == "__main__":
    sys.exit(main())
