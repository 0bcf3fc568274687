"""Who holds the engine off: a traced ``stage serve`` for bench_engine.py ``--trace DIR``.

Issue 10 saw the engine stall for about a second at aligned 6x6 (every sensor "silent for
1.0 s") and a p99 tail of tens to hundreds of ms. This module records, in one run, what is
needed to attribute such a wait, without changing the code measured:

- in the server (``_serve``, a wrapper that runs the real CLI): every cyclic garbage
  collection (``gc.callbacks``: start on the monotonic clock, duration, generation, objects
  collected); every latency sample the engine records (emission time, arrival -> emission);
  a census of the objects the collector tracks, by type, on SIGUSR1 (sent by the bench
  after its window, so that the census's own pause is not measured); the server's thread names;
- in a sampler process (``_sample``; a process, not a thread, so that it does not need the
  server's GIL and is not delayed by what it is looking for): every 10 ms, each thread's
  CPU time and run-queue wait (``/proc/PID/task/TID/schedstat``, ns) for the server and
  the bench process (its generator and view), and the machine's busy time (/proc/stat);
- in the bench (``bench_engine.py``): each datagram's send time and how late it was.

``python bench/stalltrace.py DIR`` prints the attribution: the collector's pauses by
generation, the tracked heap, and for the worst latency samples which pauses, which threads'
CPU and which run-queue waits fall in their wait. All arrays are in the files
DIR/<mode>-<config>.{trace.npz,trace.json,sched.npy,gen.npy}.
"""

from __future__ import annotations

import argparse
import array
import collections
import gc
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

SAMPLE_S = 0.010
PAGE = os.sysconf("SC_PAGE_SIZE")


# ------------------------------------------------------------------ the traced server
def traced_serve(argv: list[str]) -> int:
    """``stalltrace.py _serve PREFIX --port P --rig R``; SIGUSR1 takes the heap census."""
    parser = argparse.ArgumentParser()
    parser.add_argument("prefix")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--rig", required=True)
    parser.add_argument("--play", metavar="YAML", help="run `stage play YAML` instead of serve")
    parser.add_argument("--midi-file", help="with --play: where its MIDI goes")
    args = parser.parse_args(argv)
    mono = time.monotonic
    # array.array: not tracked by the collector, so tracing adds nothing to what it walks
    gc_t, gc_d = array.array("d"), array.array("d")
    gc_g, gc_n = array.array("i"), array.array("i")
    started = [0.0]

    def on_gc(phase: str, info: dict) -> None:
        if phase == "start":
            started[0] = mono()
        else:
            gc_t.append(started[0])
            gc_d.append(mono() - started[0])
            gc_g.append(info["generation"])
            gc_n.append(info["collected"])

    gc.callbacks.append(on_gc)
    lat_t, lat_v = array.array("d"), array.array("d")
    from stage.engine import engine as engine_module

    original_init = engine_module.Engine.__init__

    def init(self, *a, **k):
        original_init(self, *a, **k)
        add = self.latency.add

        def traced_add(seconds: float) -> None:
            lat_t.append(mono())
            lat_v.append(seconds)
            add(seconds)
        self.latency.add = traced_add
        self.people.latency = self.latency

    engine_module.Engine.__init__ = init
    # each engine batch and each calibrator poll: start, wall and own CPU (thread_time), s;
    # wall - CPU - run-queue wait is time the thread waited for the GIL or a lock
    eng_rec, cal_rec = array.array("d"), array.array("d")

    def timed(fn, rec):
        def wrapper(*a, **k):
            t0, c0 = mono(), time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                rec.extend((t0, mono() - t0, time.thread_time() - c0))
        return wrapper

    # a burst taken from the queue (older trees: each batch)
    batch = "process_taken" if hasattr(engine_module.Engine, "process_taken") else "process"
    setattr(engine_module.Engine, batch, timed(getattr(engine_module.Engine, batch), eng_rec))
    from stage.calibration import healing
    healing.LiveCalibrator._poll = timed(healing.LiveCalibrator._poll, cal_rec)
    # with --play: each call of the piece on the engine thread (one a burst)
    piece_rec = array.array("d")
    from stage.piece import runtime as runtime_module
    runtime_module.PieceRuntime.on_frame = timed(runtime_module.PieceRuntime.on_frame, piece_rec)
    meta: dict = {"pid": os.getpid(), "census": None, "threads": {}}

    def census() -> None:
        objs = gc.get_objects()
        t0 = mono()
        by_type = collections.Counter(type(o).__name__ for o in objs)
        meta["census"] = {"at": mono(), "tracked": len(objs),
                          "per_generation": [len(gc.get_objects(g)) for g in range(3)],
                          "count": gc.get_count(), "threshold": gc.get_threshold(),
                          "frozen": gc.get_freeze_count(), "stats": gc.get_stats(),
                          "top_types": by_type.most_common(25),
                          "census_s": mono() - t0}
        del objs
        meta["threads"].update(_thread_names())

    # SIGUSR1 (sent by the bench after its window): the census, on the main thread
    signal.signal(signal.SIGUSR1, lambda *_: census())
    sampler = _start_sampler(args.prefix, [os.getpid(), os.getppid()])
    from stage.cli.main import main as stage_main
    try:
        where = ["--port", str(args.port), "--rig", args.rig]
        if args.play:
            return stage_main(["--quiet", "play", args.play, *where]
                              + (["--midi-file", args.midi_file] if args.midi_file else []))
        return stage_main(["--quiet", "serve", *where])
    finally:
        meta["threads"].update(_thread_names())
        meta["end"] = mono()
        sampler.send_signal(signal.SIGTERM)
        sampler.wait(timeout=5)
        np.savez(f"{args.prefix}.trace.npz", gc_t=np.array(gc_t), gc_d=np.array(gc_d),
                 gc_g=np.array(gc_g), gc_n=np.array(gc_n), lat_t=np.array(lat_t),
                 lat_v=np.array(lat_v), eng=np.array(eng_rec).reshape(-1, 3),
                 cal=np.array(cal_rec).reshape(-1, 3), piece=np.array(piece_rec).reshape(-1, 3))
        Path(f"{args.prefix}.trace.json").write_text(json.dumps(meta, default=str))


def _thread_names() -> dict[str, str]:
    return {str(t.native_id): t.name for t in threading.enumerate() if t.native_id is not None}


def _start_sampler(prefix: str, pids: list[int]):
    import subprocess
    return subprocess.Popen([sys.executable, os.path.abspath(__file__), "_sample", prefix,
                             *map(str, pids)])


def sample(argv: list[str]) -> int:
    """``stalltrace.py _sample PREFIX PID...``: every SAMPLE_S, each thread's schedstat
    (CPU ns, run-queue wait ns) of each PID, the machine's busy ticks, and each second the
    first PID's resident memory, until SIGTERM. Rows: t, pid, tid, cpu_ns, wait_ns (pid 0,
    tid 0: the machine, cpu = busy ticks; tid -1: resident bytes in cpu)."""
    prefix, pids = argv[0], [int(p) for p in argv[1:]]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    rows = array.array("d")
    mono, listdir = time.monotonic, os.listdir
    next_t = mono()
    n = 0
    while not stop.is_set():
        t = mono()
        for pid in pids:
            try:
                tasks = listdir(f"/proc/{pid}/task")
            except FileNotFoundError:
                continue
            for tid in tasks:
                try:
                    with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                        run, wait, _ = f.read().split()
                except (FileNotFoundError, ProcessLookupError, ValueError):
                    continue
                rows.extend((t, pid, int(tid), int(run), int(wait)))
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        rows.extend((t, 0, 0, sum(v[:8]) - v[3] - v[4], 0))
        if n % 100 == 0:   # each second: the server's resident memory (tid -1, bytes)
            try:
                with open(f"/proc/{pids[0]}/statm") as f:
                    rows.extend((t, pids[0], -1, int(f.read().split()[1]) * PAGE, 0))
            except (FileNotFoundError, ProcessLookupError):
                pass
        n += 1
        next_t += SAMPLE_S
        stop.wait(max(0.0, next_t - mono()))
    np.save(f"{prefix}.sched.npy", np.array(rows).reshape(-1, 5))
    return 0


# ------------------------------------------------------------------ analysis
def _cpu_between(sched: np.ndarray, tid: int, a: float, b: float) -> tuple[float, float]:
    """(CPU s, run-queue wait s) of thread ``tid`` between times a and b (nearest samples)."""
    rows = sched[sched[:, 2] == tid]
    if len(rows) < 2:
        return 0.0, 0.0
    i = max(np.searchsorted(rows[:, 0], a, side="right") - 1, 0)
    j = min(np.searchsorted(rows[:, 0], b, side="left"), len(rows) - 1)
    return (rows[j, 3] - rows[i, 3]) / 1e9, (rows[j, 4] - rows[i, 4]) / 1e9


def analyze(prefix: str, worst: int = 8, tail_ms: float = 20.0) -> None:
    z = np.load(f"{prefix}.trace.npz")
    meta = json.loads(Path(f"{prefix}.trace.json").read_text())
    sched = np.load(f"{prefix}.sched.npy") if os.path.exists(f"{prefix}.sched.npy") else None
    gen = np.load(f"{prefix}.gen.npy") if os.path.exists(f"{prefix}.gen.npy") else None
    names = {int(k): v for k, v in meta["threads"].items()}
    print(f"== {os.path.basename(prefix)}")
    gc_t, gc_d, gc_g = z["gc_t"], z["gc_d"] * 1e3, z["gc_g"]
    for g in range(3):
        d = gc_d[gc_g == g]
        if len(d):
            print(f"  gc gen{g}: {len(d)} collections, p50 {np.median(d):.2f} ms, max "
                  f"{d.max():.2f} ms, total {d.sum():.0f} ms, collected {z['gc_n'][gc_g == g].sum()}")
    c = meta.get("census")
    if c:
        print(f"  tracked objects at census: {c['tracked']} (gen0/1/2 {c['per_generation']}, "
              f"frozen {c['frozen']}), census took {1e3 * c['census_s']:.0f} ms")
        print("  top types:", ", ".join(f"{n} {k}" for n, k in c["top_types"][:12]))
    lat_t, lat_v = z["lat_t"], z["lat_v"] * 1e3
    if gen is not None and len(gen):
        window = (lat_t >= gen[0, 0] + 2.0) & (lat_t <= gen[-1, 0])   # after the warm-up
    else:
        window = np.ones(len(lat_t), bool)
    lt, lv = lat_t[window], lat_v[window]
    if not len(lv):
        print("  no latency samples")
        return
    print(f"  latency (all after 2 s): n {len(lv)}, p50 {np.percentile(lv, 50):.2f}, p99 "
          f"{np.percentile(lv, 99):.2f}, max {lv.max():.2f} ms")
    if gen is not None and len(gen):
        late = gen[:, 1] * 1e3
        print(f"  generator late: p50 {np.median(late):.3f}, p99 {np.percentile(late, 99):.2f}, "
              f"max {late.max():.2f} ms")
    # how much of the tail waited through a collection, against how much of the time
    # collections cover
    arrival = lt - lv / 1e3
    ends = gc_t + gc_d / 1e3
    span = lt[-1] - lt[0]
    in_span = (gc_t >= lt[0]) & (gc_t <= lt[-1])
    covered = (gc_d[in_span] / 1e3).sum() / span
    tail = lv > tail_ms
    k = np.searchsorted(ends, arrival)           # first collection ending after the arrival
    overlap = (k < len(gc_t)) & (gc_t[np.minimum(k, len(gc_t) - 1)] < lt) if len(gc_t) else \
        np.zeros(len(lt), bool)
    print(f"  collections cover {100 * covered:.2f} % of the time; samples > {tail_ms:g} ms: "
          f"{tail.sum()} ({100 * tail.mean():.2f} %), of them {overlap[tail].sum()} waited "
          f"through a collection; samples <= {tail_ms:g} ms that did: "
          f"{100 * overlap[~tail].mean():.2f} %")
    for key, what in (("eng", "engine batches"), ("cal", "calibrator polls"),
                      ("piece", "piece calls")):
        rec = z[key] if key in z else np.zeros((0, 3))
        if len(rec):
            wall, cpu = rec[:, 1] * 1e3, rec[:, 2] * 1e3
            print(f"  {what}: {len(rec)}, wall p50/p99/max {np.median(wall):.2f}/"
                  f"{np.percentile(wall, 99):.2f}/{wall.max():.1f} ms, CPU p50/p99/max "
                  f"{np.median(cpu):.2f}/{np.percentile(cpu, 99):.2f}/{cpu.max():.1f} ms, "
                  f"wall - CPU p99/max {np.percentile(wall - cpu, 99):.2f}/"
                  f"{(wall - cpu).max():.1f} ms, CPU total {cpu.sum() / 1e3:.2f} s")
    if sched is None:
        return
    server_pid = meta["pid"]
    owner = {int(r[2]): int(r[1]) for r in sched if r[2] > 0}
    rss = sched[sched[:, 2] == -1]
    if len(rss) > 1:
        ok = (rss[:, 0] >= lt[0]) & (rss[:, 0] <= lt[-1])
        r = rss[ok] if ok.sum() > 1 else rss
        slope = np.polyfit(r[:, 0] - r[0, 0], r[:, 3] / 2**20, 1)[0] * 60 if len(r) > 2 else 0.0
        print(f"  server RSS over the window: {r[0, 3] / 2**20:.1f} -> {r[-1, 3] / 2**20:.1f} MiB "
              f"(max {r[:, 3].max() / 2**20:.1f}; fitted slope {slope:+.2f} MiB/min)")
    label = {tid: (names.get(tid, str(tid)) if pid == server_pid else f"bench:{tid}")
             for tid, pid in owner.items()}
    _bins(lt, lv, gc_t, gc_d, sched, label, tail_ms)
    # episodes: the worst samples, one per 200 ms
    order = np.argsort(-lv)
    chosen: list[int] = []
    for i in order:
        if all(abs(lt[i] - lt[j]) > 0.2 for j in chosen):
            chosen.append(i)
        if len(chosen) >= worst:
            break
    machine = sched[sched[:, 1] == 0]
    print("  worst waits (one per 200 ms): thread CPU/run-queue wait in ms during the wait")
    for i in sorted(chosen, key=lambda i: lt[i]):
        a, b = arrival[i], lt[i]
        gcs = [f"+{1e3 * (s - a):.0f} ms gen{g} {d:.1f} ms" for s, d, g in
               zip(gc_t, gc_d, gc_g) if s < b and s + d / 1e3 > a]
        parts = []
        for tid in sorted(label):
            cpu, wait = _cpu_between(sched, tid, a, b)
            if cpu > 0.002 or wait > 0.002:
                parts.append(f"{label[tid]} {1e3 * cpu:.0f}/{1e3 * wait:.0f}")
        busy = 0.0
        if len(machine) > 1:
            i0 = max(np.searchsorted(machine[:, 0], a, side="right") - 1, 0)
            i1 = min(np.searchsorted(machine[:, 0], b), len(machine) - 1)
            busy = (machine[i1, 3] - machine[i0, 3]) / os.sysconf("SC_CLK_TCK")
        polls = []
        if "cal" in z:
            for s0, w, c in z["cal"]:
                if s0 < b and s0 + w > a:
                    polls.append(f"+{1e3 * (s0 - a):.0f} ms {1e3 * w:.0f}/{1e3 * c:.0f}")
        if polls:
            parts.append("calibrator polls (start, wall/CPU ms) " + ", ".join(polls))
        late = ""
        if gen is not None and len(gen):
            m = (gen[:, 0] >= a - 0.1) & (gen[:, 0] <= b)
            if m.any():
                late = f"; generator late max {1e3 * gen[m, 1].max():.1f} ms"
        print(f"   t {b - lt[0]:6.2f} s waited {lv[i]:6.1f} ms | gc {', '.join(gcs) or '-'} | "
              f"{', '.join(parts) or '-'} | machine busy {1e3 * busy:.0f} ms{late}")


def _bins(lt, lv, gc_t, gc_d, sched, label, tail_ms, width=0.1) -> None:
    """Per 100 ms bin: the worst latency emitted in it and each thread's CPU and run-queue
    wait; printed as the mean over the bins with a tail sample against the others."""
    edges = np.arange(lt[0], lt[-1], width)
    if len(edges) < 3:
        return
    worst = np.full(len(edges) - 1, 0.0)
    k = np.searchsorted(edges, lt, side="right") - 1
    ok = (k >= 0) & (k < len(worst))
    np.maximum.at(worst, k[ok], lv[ok])
    hit = worst > tail_ms
    gc_in = np.zeros(len(worst))
    for s, d in zip(gc_t, gc_d / 1e3):
        j = np.searchsorted(edges, s, side="right") - 1
        if 0 <= j < len(worst):
            gc_in[j] += d
    print(f"  per {1e3 * width:.0f} ms bin: {hit.sum()} of {len(worst)} bins emitted a sample "
          f"> {tail_ms:g} ms; mean ms per bin, those bins | the others:")
    rows = [("gc", gc_in)]
    for tid in sorted(label):
        rows_t = sched[sched[:, 2] == tid]
        if len(rows_t) < 2:
            continue
        run = np.interp(edges, rows_t[:, 0], rows_t[:, 3]) / 1e9
        wait = np.interp(edges, rows_t[:, 0], rows_t[:, 4]) / 1e9
        rows.append((f"{label[tid]} cpu", np.diff(run)))
        rows.append((f"{label[tid]} runq", np.diff(wait)))
    machine = sched[sched[:, 1] == 0]
    if len(machine) > 1:
        busy = np.interp(edges, machine[:, 0], machine[:, 3]) / os.sysconf("SC_CLK_TCK")
        rows.append(("machine busy", np.diff(busy)))
    for name, v in rows:
        a = 1e3 * v[hit].mean() if hit.any() else float("nan")
        b = 1e3 * v[~hit].mean() if (~hit).any() else float("nan")
        if max(a, b) >= 0.5:
            print(f"    {name:>24}: {a:6.1f} | {b:6.1f}")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "_serve":
        return traced_serve(argv[1:])
    if argv and argv[0] == "_sample":
        return sample(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", help="the --trace DIR of a bench_engine.py run")
    parser.add_argument("--worst", type=int, default=8)
    parser.add_argument("--tail-ms", type=float, default=20.0)
    args = parser.parse_args(argv)
    for path in sorted(Path(args.dir).glob("*.trace.npz")):
        analyze(str(path)[:-len(".trace.npz")], args.worst, args.tail_ms)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
