"""Where an engine datagram's CPU goes, part by part, timed where it runs (not alone).

py-spy's samples say which lines are hot; they do not say how long a call takes inside the
engine, where caches are cold and every part pays for the others'. Here the engine's main
functions are wrapped with ``time.thread_time_ns`` and a replay of ``bench_engine_inproc``'s
datagrams (P people, each seen by S simulated Kinects) is run in process on an injected
clock; each part's CPU per datagram and calls per datagram are printed, nested parts
included in their callers. The same replay unwrapped, run first, is the reference: the
difference is what the wrappers themselves cost (about 1 us a call). The first fifth of
the datagrams (persons being found) is left out of both.

Issue 10's stop 36 found this way that the filter step's Python around its kernel cost 29 us
a 6x6 datagram where a microbenchmark gave 5; a third of it was a rejected row's numpy
path, taken on a quarter of the datagrams (docs/reports/issue-10.md).

``--paced`` replays the timed datagrams at their real spacing, sleeping between them as the
engine thread does live: each part then also pays for what it finds cold after the sleep
(issue 10, stop 37: a 6x6 datagram then costs 2.0-2.2 times its back-to-back CPU here,
2.4 times in bench_wakeup.py), and the table shows where that goes. ``--spin`` waits for
each datagram's time in a busy loop instead of asleep: what is left of the difference from
back to back is not the CPU's idle state (stop 56: spread 6x6, asleep 288-375 us a datagram,
spinning 276-313, back to back 222; in step, spinning gave nothing back).

Run: python bench/bench_engine_parts.py [--config 6x6] [--seconds 60] [--tree DIR] [--paced]
     [--spin] [--aligned]
     (DIR: a directory holding stage/, e.g. a `git archive` of another commit)
"""

from __future__ import annotations

import argparse
import collections
import functools
import sys
import time
from pathlib import Path

#: (module, object in it or None, function, label): the parts timed
PARTS = (
    ("stage.engine.engine", "Engine", "process", "process (one datagram)"),
    ("stage.sensors.protocol", None, "decode_datagram", "decode"),
    ("stage.engine.engine", "Engine", "_prepare_frames", "prepare frames"),
    ("stage.engine.people", "People", "frame", "frame (each)"),
    ("stage.engine.tracking", "Tracker", "associate", "  associate"),
    ("stage.engine.tracking", "Person", "distance", "    a person's distance"),
    ("stage.engine.people", "People", "_offset", "  view offset"),
    ("stage.engine.people", "People", "_fold", "fold and settle"),
    ("stage.engine.people", "People", "_offsets_held", "  view offsets (core)"),
    ("stage.engine.people", "People", "_fold_native", "  native core's persons"),
    ("stage.engine.native", "NativeCore", "fold", "    core fold"),
    ("stage.engine.jit", "_compiled", "_native_fold", "      its kernel"),
    ("stage.engine.fuser", "Fuser", "fold", "  fold"),
    ("stage.engine.fuser", "Fuser", "_fold_plain", "    plain wave"),
    ("stage.engine.kalman", None, "step_folded", "      filter step"),
    ("stage.engine.jit", None, "step_rows", "        its kernel"),
    ("stage.engine.fuser", "Fuser", "_trim", "    history trim"),
    ("stage.engine.fuser", "Fuser", "_agrees", "    instant: a view agrees"),
    ("stage.engine.fuser", "Fuser", "_choose", "    instant: which views agree"),
    ("stage.engine.fuser", "Fuser", "_replay", "    replay"),
    ("stage.engine.people", "People", "_update", "  settle"),
    ("stage.engine.people", "People", "_emit", "emit"),
    ("stage.engine.output", None, "_encode_joints", "  encode a skeleton"),
    ("stage.engine.people", "People", "_give_reports", "  hand reports to voters"),
    ("stage.engine.handbank", "ArrayHandVoter", "add_frame", "    a frame's hands"),
    ("stage.engine.handbank", "ArrayHandVoter", "update", "  a person's hand vote"),
    ("stage.engine.engine", "Engine", "tick", "tick"),
)


def _wrap(acc: collections.Counter, calls: collections.Counter, parts=PARTS, key=None,
          when=None) -> None:
    """Each of ``parts`` timed: its CPU ns into ``acc`` and its calls into ``calls`` under
    ``key(label)`` (the label itself by default); where ``when()`` is false (another thread:
    live_parts.py), the call runs untimed."""
    import importlib
    for module, owner, name, label in parts:
        try:
            mod = importlib.import_module(module)
        except ImportError:     # an older tree without this module: its parts not shown
            continue
        obj = getattr(mod, owner, None) if owner else mod
        table = isinstance(obj, dict)   # jit._compiled: kernels called out of the table
        if table:
            if not obj:                 # (compiled on the engine's first datagram)
                getattr(mod, "ready", lambda: None)()
            fn = obj.get(name)
        else:
            fn = getattr(obj, name, None)
        if fn is None:          # an older tree without this part: not shown
            continue

        def timed(*a, _fn=fn, _label=label, **k):
            if when is not None and not when():
                return _fn(*a, **k)
            at = _label if key is None else key(_label)
            c = time.thread_time_ns()
            try:
                return _fn(*a, **k)
            finally:
                acc[at] += time.thread_time_ns() - c
                calls[at] += 1
        if table:
            obj[name] = timed
            continue
        setattr(obj, name, functools.wraps(fn)(timed))
        # callers that imported the function by name (fuser: step_folded)
        if owner is None:
            for other in list(sys.modules.values()):
                if (getattr(other, "__name__", "").startswith("stage.")
                        and getattr(other, name, None) is fn):
                    setattr(other, name, getattr(obj, name))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="6x6", help="SxP: sensors x people")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--tree", help="a directory holding stage/ (default: this checkout)")
    parser.add_argument("--paced", action="store_true",
                        help="the timed datagrams at their real spacing, asleep in between")
    parser.add_argument("--spin", action="store_true",
                        help="with --paced: wait in a busy loop instead of asleep")
    parser.add_argument("--aligned", action="store_true",
                        help="sensors in step: a frame's S datagrams at one instant (a burst)")
    opt = parser.parse_args()
    if opt.tree:
        sys.path.insert(0, str(Path(opt.tree).resolve()))
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_engine_inproc as inproc
    s, p = map(int, opt.config.split("x"))
    poses, data = inproc.datagrams(s, p, opt.seconds, aligned=opt.aligned)
    skip = len(data) // 5

    def replay() -> float:
        engine, clock = inproc.make_engine(poses)
        for t, d in data[:skip]:
            clock.set(t)
            engine.handle_datagram(d)
            engine.tick()
        acc.clear()
        calls.clear()
        spent = 0
        start = time.perf_counter() - data[skip][0]
        for t, d in data[skip:]:
            if opt.paced and opt.spin:
                while time.perf_counter() < start + t:
                    pass
            elif opt.paced:
                inproc.sleep_until(start, t)
            clock.set(t)
            c = time.thread_time_ns()
            engine.handle_datagram(d)
            engine.tick()
            spent += time.thread_time_ns() - c
        return spent / (len(data) - skip) / 1e3

    acc: collections.Counter = collections.Counter()
    calls: collections.Counter = collections.Counter()
    import stage
    plain = replay()
    _wrap(acc, calls)
    wrapped = replay()
    n = len(data) - skip
    print(f"{opt.config} {'aligned' if opt.aligned else 'spread'}, {opt.seconds:g} s of show, {n} datagrams timed "
          f"{'at their real spacing' if opt.paced else 'back to back'}"
          f"{' (spinning)' if opt.paced and opt.spin else ''}; stage from "
          f"{Path(stage.__file__).parent}")
    print(f"CPU a datagram: {plain:.0f} us unwrapped (the reference), {wrapped:.0f} us wrapped")
    print(f"{'part':28s} {'us/datagram':>12s} {'calls/datagram':>15s}")
    for _, _, _, label in PARTS:
        if calls[label]:
            print(f"{label:28s} {acc[label] / n / 1e3:12.1f} {calls[label] / n:15.2f}")


if __name__ == "__main__":
    main()
