"""Live calibration of real three-Kinect recordings: `stage serve` fed by `stage replay --loop`.

    python bench/bench_calibration_live_real.py bench/data/nucla             # 6 triples
    python bench/bench_calibration_live_real.py bench/data/nucla --quick     # 2 triples
    python bench/bench_calibration_live_real.py bench/data/nucla --samples a01_s01_e00,...

For each chosen triple of the DEVELOPMENT subjects (s01, s04, s05, s06, s07,
s10; bench/nucla.py selects by file name before reading; never the held-out
ones), the views are imported (`stage import nucla`) into a recording, a rig
with only the reference (nucla-v1) is written, and two real processes run:
`stage serve --rig RIG --port P` and `stage replay REC --to 127.0.0.1:P --loop`
(real time, real UDP). The rig file is read every 0.25 s until both other
sensors have a calibration saved in it (or --timeout). Reported per triple:
the seconds from the replay's start until each sensor's calibration was in
the rig, and, for every pair of views, the median joint residual of the
rig's transforms (at the lag that suits them best, one frame apart over
+-1 s; also on the optimum's own grid: then a tenth of a frame apart around
the three best) against the brute-force rigid-with-lag optimum (bench/optimum.py,
numpy only), computed in the same run. Targets (issue 11): both calibrated
within 15 s, within 20 % of the optimum.

Triples are chosen deterministically: every k-th complete triple of the
development subjects with no copied view (bit-identical views are a dataset
defect the copy check flags; they cannot calibrate).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))
import nucla  # noqa: E402
import optimum  # noqa: E402

from stage.rig import Rig, load_rig  # noqa: E402

STAGE = [sys.executable, "-m", "stage.cli.main"]
IDS = ("nucla-v1", "nucla-v2", "nucla-v3")


def load_view(path: str) -> np.ndarray:
    with open(path, encoding="utf-8") as f:
        return np.asarray(json.load(f)["skeletons"], dtype=float)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def choose(folder: str, count: int, names: list[str] | None) -> list[tuple[str, list[str]]]:
    found = nucla.triples(folder)
    if names:
        return [t for t in found if t[0] in names]
    clean = []
    for sample, paths in found:
        views = [load_view(p) for p in paths]
        if any(a.shape == b.shape and np.array_equal(a, b)
               for i, a in enumerate(views) for b in views[i + 1:]):
            continue
        clean.append((sample, paths))
    step = max(1, len(clean) // count)
    return clean[::step][:count]


def best_lag_median(m: np.ndarray, ref: np.ndarray, other: np.ndarray, fine: bool = False,
                    ) -> tuple[float, float]:
    """The rig transform's median residual at the lag that suits it best (m, s): one frame
    apart over +-1 s; ``fine``: then a tenth of a frame apart around the three best, the
    grid the brute-force optimum searches (the rig stores no lag; the optimum's own lag is
    sub-frame, so on whole frames alone a transform fitted at a sub-frame lag is judged on
    a coarser grid than its yardstick: on short takes that alone moves the ratio 5-15 %)."""
    found = {}
    for k in range(-30, 31):
        lag = k / 30.0
        try:
            med, _, frames = optimum.median_residual(m, ref, other, lag)
        except Exception:  # noqa: BLE001 - too little overlap at this lag
            continue
        if frames >= 0.6 * min(len(ref), len(other)) and np.isfinite(med):
            found[lag] = med
    if not found:
        return float("inf"), 0.0
    if fine:
        for centre in sorted(found, key=found.get)[:3]:
            for lag in centre + np.arange(-10, 11) / 300.0:
                lag = float(round(lag, 9))
                if lag in found or abs(lag) > 1.0 + 1e-9:
                    continue
                med, _, frames = optimum.median_residual(m, ref, other, lag)
                if frames >= 0.6 * min(len(ref), len(other)) and np.isfinite(med):
                    found[lag] = med
    lag = min(found, key=found.get)
    return found[lag], lag


def run_triple(sample: str, paths: list[str], tmp: str, timeout: float) -> dict:
    rec = os.path.join(tmp, f"{sample}.stagerec")
    subprocess.run([*STAGE, "--quiet", "import", "nucla", *paths, "--out", rec], check=True,
                   stdout=subprocess.DEVNULL)
    port = free_port()
    rig_path = os.path.join(tmp, f"{sample}.rig.yaml")
    Rig(reference="nucla-v1", port=port).save(rig_path)
    log_path = os.path.join(tmp, f"{sample}.serve.log")
    with open(log_path, "w", encoding="utf-8") as log:
        serve = subprocess.Popen([*STAGE, "serve", "--rig", rig_path, "--port", str(port),
                                  "--host", "127.0.0.1", "--no-plugins"],
                                 stdout=log, stderr=subprocess.STDOUT)
        time.sleep(1.5)   # the server binds its port
        started = time.monotonic()
        replay = subprocess.Popen([*STAGE, "--quiet", "replay", rec, "--to",
                                   f"127.0.0.1:{port}", "--loop"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        when: dict[str, float] = {}
        rig = None
        try:
            while time.monotonic() - started < timeout and len(when) < 2:
                time.sleep(0.25)
                try:
                    rig = load_rig(rig_path)
                except Exception:  # noqa: BLE001 - caught mid-rewrite (it is atomic, but)
                    continue
                for sid in IDS[1:]:
                    sc = rig.sensors.get(sid)
                    if sid not in when and sc is not None and sc.calibration is not None:
                        when[sid] = time.monotonic() - started
        finally:
            for p in (replay, serve):
                p.send_signal(signal.SIGINT)
            for p in (replay, serve):
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    rig = load_rig(rig_path)
    views = [load_view(p) for p in paths]
    row: dict = {"sample": sample, "frames": [len(v) for v in views],
                 "calibrated_after_s": {s: when.get(s) for s in IDS[1:]},
                 "methods": {s: (rig.sensors[s].calibration.method
                                 if s in rig.sensors and rig.sensors[s].calibration else None)
                             for s in IDS[1:]},
                 "pairs": []}
    for i in range(3):
        for k in range(i + 1, 3):
            a, b = IDS[i], IDS[k]
            ta, tb = rig.transform_for(a), rig.transform_for(b)
            best = optimum.optimum(views[i], views[k])
            entry = {"a": a, "b": b, "optimum_median_m": best.median_m if best else None}
            if ta is not None and tb is not None and best is not None:
                med, lag = best_lag_median(np.linalg.inv(ta) @ tb, views[i], views[k])
                entry.update(median_m=med, lag_s=lag, ratio=med / best.median_m)
                med, lag = best_lag_median(np.linalg.inv(ta) @ tb, views[i], views[k], True)
                entry.update(fine_median_m=med, fine_lag_s=lag, fine_ratio=med / best.median_m)
            row["pairs"].append(entry)
    with open(log_path, encoding="utf-8") as f:
        row["log_tail"] = [ln.rstrip() for ln in f if "calibrat" in ln][-6:]
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("data_dir", metavar="DATA_DIR")
    parser.add_argument("--count", type=int, default=6, help="triples (default 6)")
    parser.add_argument("--samples", help="comma-separated samples instead (aXX_sYY_eZZ)")
    parser.add_argument("--timeout", type=float, default=30.0)
    parser.add_argument("--quick", action="store_true", help="2 triples")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    names = args.samples.split(",") if args.samples else None
    if names and any(n.split("_")[1] in nucla.HELD_OUT for n in names):
        parser.error("held-out subjects are not used here")
    chosen = choose(args.data_dir, 2 if args.quick else args.count, names)
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        rows = [run_triple(s, p, tmp, args.timeout) for s, p in chosen]
    load1 = os.getloadavg()[0]
    if args.json:
        print(json.dumps({"rows": rows, "load": [load0, load1]}, indent=2, default=float))
        return 0
    print(f"live: stage serve <- stage replay --loop, {len(rows)} development triples "
          f"(machine load {load0:.1f} -> {load1:.1f})")
    both, in_time, ratios = 0, 0, []
    for r in rows:
        t = r["calibrated_after_s"]
        done = all(v is not None for v in t.values())
        both += done
        in_time += done and max(t.values()) <= 15.0
        pr = [p.get("ratio") for p in r["pairs"]]
        ratios += [x for x in pr if x is not None]
        times = ", ".join(f"{s[-2:]} {'-' if v is None else f'{v:.1f} s'}" for s, v in t.items())
        rs = ", ".join(f"{p['a'][-2:]}-{p['b'][-2:]} "
                       + ("-" if p.get("ratio") is None else
                          f"{p['median_m'] * 100:.1f}/{p['optimum_median_m'] * 100:.1f} cm "
                          f"({p['ratio']:.2f})") for p in r["pairs"])
        print(f"  {r['sample']} {r['frames']}: calibrated {times}; rig vs optimum {rs}")
    to_ref = [p["ratio"] for r in rows for p in r["pairs"]
              if p["a"] == IDS[0] and p.get("ratio") is not None]
    fine_ref = [p["fine_ratio"] for r in rows for p in r["pairs"]
                if p["a"] == IDS[0] and p.get("fine_ratio") is not None]
    fine_all = [p["fine_ratio"] for r in rows for p in r["pairs"]
                if p.get("fine_ratio") is not None]
    print(f"  both other sensors calibrated and saved: {both}/{len(rows)}, within 15 s: "
          f"{in_time}/{len(rows)}")
    for label, rs in (("each sensor to the reference", to_ref), ("every pair", ratios),
                      ("each sensor to the reference, lags on the optimum's grid", fine_ref),
                      ("every pair, lags on the optimum's grid", fine_all)):
        print(f"  {label}: within 20 % of the optimum {sum(x <= 1.2 for x in rs)}/{len(rs)} "
              f"(ratio p50 {np.median(rs) if rs else float('nan'):.3f}, max "
              f"{max(rs) if rs else float('nan'):.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
