"""The native core beside the engine's Python path, on the same datagrams (issue 10, stop 41).

The engine processes every datagram as always. For each one, the views its fusion path
made of the datagram's frames are also folded by a ``native.NativeCore`` holding the same
persons (``stage.testing.native_shadow``): one compiled call that folds, settles and
encodes them. For every datagram the core accepts, the bench compares its encoded
skeletons and kept state with the engine's (``mismatches``: must be 0) and times, in the
same process and on the same datagram (thread CPU):

- ``python``: what the core replaces, the engine's fold and settle (``People._fold``) and
  its encoding of the skeletons (``jit.view_joints``, the compiled encoder, with its
  Python wrapper);
- ``native``: the core's ``fold`` (its slot lookups and the one compiled call);
- ``whole``: the engine's whole datagram (``handle_datagram``), the core's time taken out:
  what is left of it shows what the core does not cover yet (decoding, frames,
  association, hand votes, sends, latency records).

The core's fold runs before the engine's on every other datagram and after it on the rest,
so neither always finds the caches the other warmed. ``--paced`` sleeps each datagram's real
spacing first (spread: 1 / (30 x sensors) s), as the live engine thread waits between
datagrams and finds its caches cold (stop 37).

Input: ``bench_engine_inproc.datagrams`` (P people on a grid, each seen by S simulated Kinects
with their errors), spread unless ``--aligned`` (then the core takes only the first
datagram of each instant: the rest are checked against each other, which it leaves to
Python). The first fifth (persons being found) is not timed.

Run: python bench/bench_native.py [--configs 1x1,3x3,6x6] [--seconds 20] [--paced] [--aligned]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from bench_engine_inproc import datagrams
from stage.testing.native_shadow import replay, shadow_engine


def run(n_sensors: int, n_people: int, seconds: float, paced: bool, aligned: bool) -> dict:
    poses, data = datagrams(n_sensors, n_people, seconds, aligned=aligned)
    shadow = shadow_engine(poses)
    skip = len(data) // 5
    replay(shadow, data[:skip])
    shadow.native_s.clear()
    shadow.python_s.clear()
    shadow.whole_s.clear()
    replay(shadow, data[skip:], pace=paced)
    nat = np.array(shadow.native_s) * 1e6
    py = np.array(shadow.python_s) * 1e6
    whole = np.array(shadow.whole_s) * 1e6
    return {"datagrams": len(data) - skip, "accepted": len(nat), "declined": shadow.declined,
            "mismatches": len(shadow.mismatches), "native": nat, "python": py, "whole": whole}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", default="1x1,3x3,6x6")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--paced", action="store_true")
    ap.add_argument("--aligned", action="store_true")
    a = ap.parse_args()
    mode = ("paced" if a.paced else "back to back") + (", aligned" if a.aligned else ", spread")
    print(f"native core vs the engine's fold + settle + encode, {mode}, {a.seconds:g} s of show; "
          "thread CPU us per accepted datagram, p50 / p90")
    print(f"{'config':<7}{'accepted':>14}{'mism.':>6}{'python':>16}{'native':>16}"
          f"{'ratio p50':>10}{'whole':>16}")
    bad = 0
    for cfg in a.configs.split(","):
        s, p = (int(x) for x in cfg.split("x"))
        t0 = time.time()
        r = run(s, p, a.seconds, a.paced, a.aligned)
        bad += r["mismatches"]
        nat, py, whole = r["native"], r["python"], r["whole"]
        if not len(nat):
            print(f"{cfg:<7}{'0/' + str(r['datagrams']):>14}   (nothing accepted)")
            continue
        ratio = np.median(nat / py)
        print(f"{cfg:<7}{str(r['accepted']) + '/' + str(r['datagrams']):>14}{r['mismatches']:>6}"
              f"{np.median(py):>9.1f} /{np.percentile(py, 90):>5.0f}"
              f"{np.median(nat):>9.1f} /{np.percentile(nat, 90):>5.0f}{ratio:>10.2f}"
              f"{np.median(whole):>9.1f} /{np.percentile(whole, 90):>5.0f}"
              f"   ({time.time() - t0:.0f} s)", flush=True)
    if bad:
        print(f"MISMATCHES: {bad} (the core must give the engine's bytes and floats)")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
