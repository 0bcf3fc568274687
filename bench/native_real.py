"""The native core on real multi-view recordings: N-UCLA's three Kinects through two engines,
the core on and off, compared datagram by datagram.

The core's tests and benches feed it the simulator's Kinects (tests/test_native.py,
bench_native.py, bench_engine_ab.py), whose errors are our own model of a Kinect. This
bench feeds it three real Kinect v1 sensors filming one person at once (N-UCLA, the
development subjects only: ``nucla.triples`` selects files by name before any is read;
never the held-out subjects; views with copied frames are skipped, as
bench_calibration_real.py does). For each chosen take:

- views v02 and v03 are calibrated onto v01 (the reference, stage space) by the
  brute-force rigid-with-lag optimum (``optimum.py``), the transform put into both
  engines (as a re-calibration would be) and the view's frames shifted by its lag, so that
  the views of one moment carry about the same capture time;
- every frame of every view is one sensor datagram (a bundle stamped with its capture
  time, as a live client sends it), all in capture-time order, the next take three
  seconds after the last one's end (its person lost, a new one found).

Both engines (``fusion.native`` true and false, otherwise the default rig) get every
datagram in turn. Printed: per take the optimum's median residual (how well the views
overlap once calibrated) and the core's share; then the totals: datagrams, views fused,
what the core folded, replayed, declined and gave back, and whether every datagram sent
and every fold statistic were the same on both paths. A difference names the first
datagram where the sent bytes differ.

    python bench/native_real.py bench/data/nucla              # every 4th clean triple
    python bench/native_real.py bench/data/nucla --every 1    # every clean triple
    python bench/native_real.py bench/data/nucla --limit 10

docs/datasets.md says how to fetch the files into bench/data/nucla (never committed).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time

import numpy as np

import nucla
from bench_calibration_real import copied, load_view
from optimum import optimum

from stage.clock import ManualClock
from stage.engine.engine import Engine
from stage.rig import Rig, set_calibration
from stage.sensors.importers.nucla import to_kinect2
from stage.sensors.protocol import encode_bundle, encode_client_joints
from stage.testing.native_shadow import Recorder

#: the bundles' timetags are Unix times; the engines' clocks start at 0
EPOCH = 1.7e9
FPS = 30.0
GAP_S = 3.0
SENSORS = ("nucla-v1", "nucla-v2", "nucla-v3")


def take(views: list[np.ndarray]) -> dict | None:
    """A triple calibrated onto its first view: per view (to_stage 4x4, lag s, frames), and
    the optimum's median residual per other view; None if a view cannot be calibrated."""
    out = {"to_stage": [np.eye(4)], "lag": [0.0], "median_m": []}
    for other in views[1:]:
        best = optimum(views[0], other, FPS)
        if best is None:
            return None
        out["to_stage"].append(best.matrix)
        out["lag"].append(best.lag_s)
        out["median_m"].append(best.median_m)
    return out


def datagrams(views: list[np.ndarray], lags: list[float], start: float) -> tuple[list, float]:
    """(capture time, sensor index, datagram) of every frame of every view, in capture-time
    order, from ``start`` on; and the end of the take. Frame j of a view whose optimum lag
    is L was captured at j / FPS - L on the reference's time line."""
    items = []
    for s, (skel, lag) in enumerate(zip(views, lags)):
        for j, frame in enumerate(skel):
            joints, conf = to_kinect2(frame)
            if not conf.any():
                continue
            items.append((j / FPS - lag, s, joints, conf))
    first = min(i[0] for i in items)
    out = []
    for t, s, joints, conf in sorted(items, key=lambda i: (i[0], i[1])):
        at = start + (t - first)
        msg = encode_client_joints(SENSORS[s], 0, joints, conf)
        out.append((at, s, encode_bundle([msg], EPOCH + at)))
    return out, out[-1][0]


def engine(native: bool) -> tuple[Engine, Recorder]:
    rig = Rig(reference=SENSORS[0], views=[("127.0.0.1", 9)])
    rig.fusion = dataclasses.replace(rig.fusion, native=native)
    recorder = Recorder()
    return Engine(rig, ManualClock(0.0), recorder), recorder


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", help="the N-UCLA all_sqe files (docs/datasets.md)")
    parser.add_argument("--every", type=int, default=4, help="every k-th clean triple (4)")
    parser.add_argument("--limit", type=int, default=0, help="at most this many takes")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)     # (a sensor going silent between takes)
    found = nucla.triples(args.folder)          # development subjects only, by file name
    if not found:
        print(f"no complete triples in {args.folder}: see docs/datasets.md", file=sys.stderr)
        return 2
    chosen = []
    for sample, paths in found:
        views = [load_view(p) for p in paths]
        if any(copied(a, b) for k, a in enumerate(views) for b in views[k + 1:]):
            continue
        chosen.append((sample, views))
    chosen = chosen[::args.every]
    if args.limit:
        chosen = chosen[:args.limit]
    print(f"N-UCLA, {len(found)} complete development triples, {len(chosen)} chosen "
          f"(no copied views, every {args.every}); each through two engines, the native core "
          f"on and off", flush=True)
    (on, sent_on), (off, sent_off) = engine(True), engine(False)
    rig_of = {id(on): on, id(off): off}
    cursor, total, first_diff = 0.0, 0, None
    cpu = {True: [], False: []}
    skipped, medians = 0, []
    print(f"{'take':>12} {'median mm':>12} {'datagrams':>9} {'core folded':>11} "
          f"{'declined':>8} {'replayed':>8}")
    for sample, views in chosen:
        cal = take(views)
        if cal is None:
            skipped += 1
            continue
        medians += cal["median_m"]
        for e in rig_of.values():           # a re-calibration, as the live calibrator makes
            for s, m in enumerate(cal["to_stage"][1:], start=1):
                set_calibration(e.rig, SENSORS[s], m, "bench")
                e.set_calibration(SENSORS[s], m)
        data, end = datagrams(views, cal["lag"], cursor)
        before = (on.people.core.folded, on.people.core.declined, on.people.core.replayed)
        last_tick = cursor
        for n, (t, _, d) in enumerate(data):
            pair = ((on, sent_on, True), (off, sent_off, False))
            for e, rec, native in (pair if n % 2 == 0 else pair[::-1]):
                e.clock.set(t)
                c0 = time.thread_time()
                e.handle_datagram(d, ("127.0.0.1", 7000), arrival=t)
                if t - last_tick >= 0.02:
                    e.tick(t)
                cpu[native].append(time.thread_time() - c0)
            if t - last_tick >= 0.02:
                last_tick = t
            if first_diff is None and sent_on.sent != sent_off.sent:
                first_diff = f"{sample}, datagram {n}"
            sent_on.sent.clear()
            sent_off.sent.clear()
        total += len(data)
        # the take's person lost before the next begins
        for k in range(1, int(GAP_S / 0.02) + 1):
            for e in rig_of.values():
                e.clock.set(end + 0.02 * k)
                e.tick(end + 0.02 * k)
        cursor = end + GAP_S
        core = on.people.core
        print(f"{sample:>12} {'/'.join(f'{1000 * m:.0f}' for m in cal['median_m']):>12} "
              f"{len(data):>9} {core.folded - before[0]:>11} {core.declined - before[1]:>8} "
              f"{core.replayed - before[2]:>8}", flush=True)
    core, st_on, st_off = on.people.core, on.people.stats(), off.people.stats()
    st_on.pop("native")
    same_stats = st_on == st_off
    same_counts = on.counts == off.counts
    print(f"\n{total} datagrams in {len(chosen) - skipped} takes ({skipped} not calibrated); "
          f"views fused {off.counts.get('fused_frames', 0)}, persons {on.people.tracker._next_id}")
    print(f"optimum median residual over the calibrated views: p50 "
          f"{1000 * np.median(medians):.1f} mm, max {1000 * max(medians):.1f} mm")
    print(f"the core folded {core.folded} datagrams, declined {core.declined}, gave back "
          f"{core.given_back}, replayed {core.replayed} views (the Python path's replays "
          f"{st_off['replays']}, instants' joints left out {st_off['joints_disagreeing']})")
    print(f"every datagram sent identical: {first_diff is None}"
          f"{'' if first_diff is None else ' (first difference: ' + first_diff + ')'}; "
          f"fold statistics identical: {same_stats}; engine counts identical: {same_counts}")
    a, b = np.array(cpu[True]) * 1e6, np.array(cpu[False]) * 1e6
    print(f"CPU a datagram, us, p50/p90: core {np.percentile(a, 50):.0f}/"
          f"{np.percentile(a, 90):.0f}, Python path {np.percentile(b, 50):.0f}/"
          f"{np.percentile(b, 90):.0f} (one person, one skeleton a datagram)")
    return 0 if first_diff is None and same_stats and same_counts else 1


if __name__ == "__main__":
    sys.exit(main())
