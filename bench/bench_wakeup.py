"""What a call costs when the thread has been away for a while, beside the same call back to back.

Live, the engine's threads wake once per sensor datagram: every 5.5 ms at 6 sensors x 30
Hz, every 33 ms at one sensor. ``bench_engine_inproc.py --paced`` showed that a datagram then
costs about twice its back-to-back CPU (issue 10, stops 20 and 31), and stop 31 found that a
busy wait costs as much as a sleep. This bench measures that penalty on a ladder of calls,
from one that does nothing to a whole engine datagram, so that the cost of a design (how
many threads wake per datagram, how much code and data a datagram touches) can be judged
on the machine at hand. One row calls, in turn, every compiled kernel a 6 x 6 datagram
calls in the engine (the scanner, frames, association distances, the IMM step, settling,
hand votes, encoding), each with the arguments it had there, captured from a replay: what a
datagram's arithmetic costs without the engine's Python between the calls, about what a
native per-datagram path would keep of the engine row (a little more: it still dispatches
each call from Python, which the native path would do once). The row after it makes the
same calls, with the same arguments, to a compiled function that does nothing: numba's
dispatch alone.

- ``b2b``: the call repeated back to back (the reference, measured in the same run);
- ``sleep 5.5``/``sleep 33``: after ``time.sleep`` of 5.5 ms / 33 ms;
- ``spin 5.5``: after 5.5 ms of a busy wait (a ``perf_counter`` loop: the thread never idle).

Each figure is the median over the calls of the thread's CPU time (``time.thread_time_ns``)
for the call alone; the modes are alternated in rounds so that a change in the machine's
load falls on all of them. The engine rows replay ``bench_engine_inproc``'s 6 x 6 datagrams
through one engine on an injected clock, each mode taking the next datagrams in turn.

Then the same question for the live server's two threads. Live, a sensor datagram wakes the
receiver thread (which decodes it) and then the engine thread (which fuses it): two threads
come back from sleep for each datagram. ``--threads`` replays 6 x 6 datagrams at their real
spacing both ways, alternated in rounds: one thread that sleeps, decodes and fuses; and a
receiver thread that sleeps, decodes and puts the datagram's messages on a queue that an
engine thread waits on, as ``stage serve`` does. Printed: each thread's CPU per datagram
(median) and their sum.

Run: python bench/bench_wakeup.py [--calls 200] [--rounds 2] [--threads] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

MODES = (("b2b", 0.0, False), ("sleep 5.5", 0.0055, False), ("spin 5.5", 0.0055, True),
         ("sleep 33", 0.033, False))


def _spin(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def _measure(call, n: int, gap: float, spin: bool) -> list[int]:
    out = []
    for i in range(n):
        if gap:
            if spin:
                _spin(gap)
            else:
                time.sleep(gap)
        c = time.thread_time_ns()
        call(i)
        out.append(time.thread_time_ns() - c)
    return out


def _engine_after(poses, data: list, warm: int):
    """(engine, its clock, an iterator over the rest of ``data``) after the first ``warm``
    datagrams, in which the persons are found (``handle_datagram``: from 127.0.0.1:0)."""
    import bench_engine_inproc as inproc
    engine, clock = inproc.make_engine(poses)
    feed = iter(data)
    for _ in range(warm):
        t, d = next(feed)
        clock.set(t)
        engine.handle_datagram(d)
    return engine, clock, feed


def _captured_kernels(poses, data: list) -> list[list[tuple]]:
    """For each datagram of ``data`` replayed through a new engine, the compiled calls it
    made, in order: (name, kernel, its arguments copied before the call). The kernels are
    the engine's (``jit``), the receiver's scanner and the hand votes' (``handbank``)."""
    import bench_engine_inproc as inproc
    from stage.engine import handbank, jit
    from stage.sensors import protocol
    engine, clock = inproc.make_engine(poses)
    per_datagram: list[list[tuple]] = []

    def recorder(name, kernel):
        def record(*a):
            per_datagram[-1].append((name, kernel, tuple(_copy(x) for x in a)))
            return kernel(*a)
        return record

    saved_jit = dict(jit._compiled)
    saved_hands = dict(handbank._K)
    scanner = protocol._scanner
    try:
        for name, kernel in saved_jit.items():
            if callable(kernel) and name != "scan":
                jit._compiled[name] = recorder(name, kernel)
        for name, kernel in saved_hands.items():
            handbank._K[name] = recorder("hands." + name, kernel)
        if scanner is not None:
            protocol.use_scanner(recorder("scan", scanner))
        for t, d in data:
            per_datagram.append([])
            clock.set(t)
            engine.handle_datagram(d)
    finally:
        jit._compiled.clear()
        jit._compiled.update(saved_jit)
        handbank._K.clear()
        handbank._K.update(saved_hands)
        protocol.use_scanner(scanner)
    return per_datagram


def _copy(x):
    """An argument as it was at the call: arrays copied, read-only ones kept read-only (a
    kernel compiled for a read-only array takes no other)."""
    if not isinstance(x, np.ndarray):
        return x
    c = x.copy()
    c.flags.writeable = x.flags.writeable
    return c


def _call(captured: tuple) -> None:
    captured[1](*captured[2])


def _call_all(calls: list[tuple]) -> None:
    """One datagram's compiled calls, in turn, from Python: what a datagram's arithmetic
    costs without the engine's Python between the calls (each call still dispatched from
    Python; a native path would make one)."""
    for _, kernel, args in calls:
        kernel(*args)


def _as_no_ops(steady: list[list[tuple]]) -> list[list[tuple]]:
    """The same calls with the same arguments to a compiled function that does nothing:
    what numba's dispatch of them costs (typing and unboxing every argument), compiled
    here for each kernel's argument types before it is timed."""
    from stage.engine import jit

    @jit.numba.njit
    def no_op(*args):
        return 0

    calls = [[(name, no_op, args) for name, _, args in datagram] for datagram in steady]
    for datagram in calls:      # every argument-type tuple compiled once, before any timing
        _call_all(datagram)
    return calls


def _in_place_rows(imm: list[tuple]) -> list:
    """The IMM kernel writing its new state over the old one (the kernel reads a row whole
    before writing it, so that is safe), and the same after copying the old state into
    one of 36 ring entries first: what keeping the state before each step for a replay
    costs when the state is updated in place (the person bank's plan, issue 10 stop 35).
    The wave row above writes each step into other arrays, as the engine does: one more
    block of memory for each step while the history holds the old one."""
    shape = imm[0][2][0].shape
    # their own copies of the captures (the ring's entries fit these): stepping in place
    # must not change what the other rows are given
    imm = [(name, kernel, tuple(_copy(x) for x in args)) for name, kernel, args in imm
           if args[0].shape == shape]
    ring = [tuple(np.empty_like(x) for x in imm[0][2][:4]) for _ in range(36)]

    def in_place(i):
        _, kernel, a = imm[i % len(imm)]
        # ``jit._step_rows``' arguments: a[0:4] the state (S, st, held_z, held_t), a[4:12]
        # the measurements and settings, a[12:16] where the new state goes (here: the old
        # state's own arrays), a[16:] outcome, used, counts, pos, vel
        kernel(*a[:12], a[0], a[1], a[2], a[3], *a[16:])

    def ring_then_in_place(i):
        entry = ring[i % len(ring)]
        for dst, src in zip(entry, imm[i % len(imm)][2][:4]):
            np.copyto(dst, src)
        in_place(i)

    return [("IMM kernel, in place", in_place),
            ("IMM in place + ring copy", ring_then_in_place)]


def _kernel_counts(steady: list[list[tuple]]) -> dict[str, float]:
    """How many calls of each kernel a datagram made, on average."""
    counts: dict[str, int] = {}
    for calls in steady:
        for name, *_ in calls:
            counts[name] = counts.get(name, 0) + 1
    return {name: n / len(steady) for name, n in counts.items()}


def _workloads(calls: int):
    """(name, call(i)) from the smallest to a whole engine datagram; ``calls``: how many
    times the engine row is called in all (each call takes the next datagram)."""
    import bench_engine_inproc as inproc
    from stage.engine import jit
    from stage.sensors.protocol import decode_datagram
    jit.warm()
    small = np.ones(4096)                          # 32 KB, 512 cache lines
    warm = 360                                     # 2 s of 6 x 6: persons found
    poses, data = inproc.datagrams(6, 6, (warm + calls) / 180.0 + 1.0)
    datagrams = [d for _, d in data]

    # every compiled call a datagram makes, with its own arguments, captured from a replay
    steady = _captured_kernels(poses, data[: len(data) // 2])
    steady = steady[len(steady) // 2:]
    imm = [c for calls in steady for c in calls if c[0] == "_step_rows"]

    # one engine for the engine rows: each call takes the next datagram, at its own time
    engine, clock, feed = _engine_after(poses, data, warm)

    def engine_datagram(_i):
        t, d = next(feed)
        clock.set(t)
        engine.handle_datagram(d)

    rows = [
        ("a Python call that returns", lambda i: i + 1),
        ("np.empty(10)", lambda i: np.empty(10)),
        ("sum of 32 KB (512 lines)", lambda i: small.sum()),
        ("decode one 6x6 datagram", lambda i: decode_datagram(datagrams[i % len(datagrams)])),
    ]
    if imm:
        rows.append(("IMM kernel, one 6x6 wave", lambda i: _call(imm[i % len(imm)])))
        rows += _in_place_rows(imm)
        kernels = _kernel_counts(steady)
        print("a 6x6 datagram's compiled calls: " + ", ".join(
            f"{name} {n:.1f}" for name, n in kernels.items()), file=sys.stderr)
        rows.append((f"its kernels in turn ({sum(kernels.values()):.0f} calls)",
                     lambda i: _call_all(steady[i % len(steady)])))
        dispatch = _as_no_ops(steady)
        rows.append(("the same calls to a no-op", lambda i: _call_all(dispatch[i % len(dispatch)])))
    rows.append(("engine: one 6x6 datagram", engine_datagram))
    return rows


def _threads(rounds: int, per_round: int) -> dict:
    """CPU per 6 x 6 datagram at the sensors' real spacing: decoded and fused on one thread,
    or decoded on a receiver thread and fused on an engine thread (a queue between)."""
    import queue
    import threading

    import bench_engine_inproc as inproc
    from stage.engine import jit
    from stage.sensors.protocol import Inbound, decode_datagram
    jit.warm()
    warm = 360
    poses, data = inproc.datagrams(6, 6, (warm + 2 * rounds * per_round) / 180.0 + 1.0)
    engine, clock, feed = _engine_after(poses, data, warm)
    source = ("127.0.0.1", 0)          # handle_datagram's: the clients' source stays the same
    spacing = 1.0 / 180.0
    out: dict[str, list[int]] = {"one thread": [], "receiver": [], "engine": [], "two threads": []}

    def decode(t, d):
        clock.set(t)
        decoded = decode_datagram(d, "127.0.0.1:0")
        return [Inbound(m, t, source, tt) for m, tt in decoded.messages]

    drops_before = sum(sum(v.values()) for v in engine.drops.snapshot().values())
    for _ in range(rounds):
        for _ in range(per_round):              # one thread: sleep, decode, fuse
            time.sleep(spacing)
            t, d = next(feed)
            c = time.thread_time_ns()
            engine.process(decode(t, d))
            out["one thread"].append(time.thread_time_ns() - c)
        q: queue.SimpleQueue = queue.SimpleQueue()
        rx: list[int] = []
        eng: list[int] = []

        def engine_thread():
            while True:
                batch = q.get()
                if batch is None:
                    return
                c = time.thread_time_ns()
                engine.process(batch)
                eng.append(time.thread_time_ns() - c)

        worker = threading.Thread(target=engine_thread)
        worker.start()
        for _ in range(per_round):              # two threads: the receiver hands over
            time.sleep(spacing)
            t, d = next(feed)
            c = time.thread_time_ns()
            q.put(decode(t, d))
            rx.append(time.thread_time_ns() - c)
        q.put(None)
        worker.join()
        out["receiver"] += rx
        out["engine"] += eng
        out["two threads"] += [a + b for a, b in zip(rx, eng)]
    result = {k: float(np.median(v)) / 1e3 for k, v in out.items()}
    # a check that every datagram was fused: none dropped (a wrong source would be), six
    # persons at the end
    result["drops"] = sum(sum(v.values()) for v in engine.drops.snapshot().values()) - drops_before
    result["persons"] = len(engine.persons)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=200, help="calls per mode and round")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--threads", action="store_true",
                        help="only the one-thread against two-thread replay (see above)")
    parser.add_argument("--json", action="store_true")
    opt = parser.parse_args()
    if opt.threads:
        r = _threads(opt.rounds, opt.calls)
        if opt.json:
            print(json.dumps(r, indent=1))
            return
        print("6x6 datagrams at their real spacing (5.5 ms), CPU per datagram, median us")
        print(f"  one thread (sleep, decode, fuse):       {r['one thread']:8.1f}")
        print(f"  two threads: receiver (sleep, decode)   {r['receiver']:8.1f}")
        print(f"               engine (wait, fuse)        {r['engine']:8.1f}")
        print(f"               sum                        {r['two threads']:8.1f}"
              f"  (x{r['two threads'] / r['one thread']:.2f} the one thread)")
        print(f"  (check: {r['drops']} messages dropped, {r['persons']} persons at the end)")
        return
    rows = _workloads(opt.calls * opt.rounds * len(MODES))
    results = {}
    for name, call in rows:
        samples: dict[str, list[int]] = {m: [] for m, _, _ in MODES}
        for _ in range(opt.rounds):
            for mode, gap, spin in MODES:
                s = _measure(call, opt.calls, gap, spin)
                samples[mode] += s[opt.calls // 10:]      # the first calls of a round: out
        results[name] = {m: float(np.median(v)) / 1e3 for m, v in samples.items()}
    if opt.json:
        print(json.dumps(results, indent=1))
        return
    print("CPU per call, median us (ratio to back to back)")
    print(f"{'call':30s}" + "".join(f"{m:>18s}" for m, _, _ in MODES))
    for name, r in results.items():
        b = r["b2b"]
        cells = [f"{b:10.1f}        "] + [f"{r[m]:10.1f} (x{r[m] / b:4.1f})" for m, _, _ in MODES[1:]]
        print(f"{name:30s}" + "".join(f"{c:>18s}" for c in cells))
    line = results["sum of 32 KB (512 lines)"]
    extra = line["sleep 5.5"] - line["b2b"]
    print(f"sum of 32 KB after 5.5 ms asleep: +{extra:.1f} us, {extra / 512 * 1e3:.0f} ns a "
          f"cache line it reads")


if __name__ == "__main__":
    main()
