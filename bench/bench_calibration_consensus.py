"""Calibrations of real N-UCLA takes judged against the subject's own rig (``nucla_consensus``).

For every complete development triple (s01, s04, s05, s06, s07, s10; never the held-out
subjects), ``stage calibrate REC --json`` with each tolerance asked for; then every pair of
views the calibration placed, and every pairwise fit it made (used or not), is compared with
the reference of that subject and pair built from the OTHER takes' brute-force fits
(leave one out). The figure is the rms displacement of points where people stand (2-4 m in
front of the sensor) between the calibration and the reference, and the angle between them.

Bins: within ``--right-cm`` (default 15) of the reference: right; beyond ``--wrong-cm``
(default 30): wrong; between: off. A pair counts only where the reference exists (at least
``nucla_consensus.MIN_VOTES`` other takes agree) and neither view is a copy.

    python bench/bench_calibration_consensus.py bench/data/nucla                 # default tolerance
    python bench/bench_calibration_consensus.py bench/data/nucla --tolerance 0,0 --tolerance 2,5
    python bench/bench_calibration_consensus.py bench/data/nucla --every 3 --fits F --json OUT

The reference's fits cost ~1.5 s per pair of views (~15 min for the 243 triples, once):
``--fits F`` keeps them between runs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import nucla  # noqa: E402
import nucla_consensus as nc  # noqa: E402
from bench_calibration_real import (copied, import_and_calibrate, load_view,  # noqa: E402
                                    pair_transform)


def judge(m: np.ndarray, ref: nc.Reference) -> dict:
    return {"cm": round(100 * nc.displacement(m, ref.matrix), 2),
            "deg": round(nc.angle_deg(m, ref.matrix), 2), "votes": ref.votes}


def triple(sample: str, paths: list[str], tmp: str, fits: dict, tolerance: list[str]) -> dict:
    done = import_and_calibrate(sample, paths, tmp, tolerance)
    if isinstance(done, dict):
        return done
    code, result, seconds = done
    sensors = result["sensors"]
    views = [load_view(p) for p in paths]
    ids = [f"nucla-v{k}" for k in (1, 2, 3)]
    copies = {ids[k] for i in range(3) for k in range(i + 1, 3) if copied(views[i], views[k])}
    placed = {s for s, e in sensors.items() if e.get("matrix") is not None}
    flagged = {s for s, e in sensors.items() if e.get("identical_to")}
    row = {"sample": sample, "exit": code, "seconds": seconds, "pairs": [], "overlaps": [],
           "success": all((s in placed) if s not in copies else (s in flagged) for s in ids),
           "reference": result.get("reference"), "copies": sorted(copies)}
    subject = nc.subject_of(sample)
    for i in range(3):
        for k in range(i + 1, 3):
            a, b = ids[i], ids[k]
            if a in copies or b in copies:
                continue
            ref = nc.consensus(fits.get((subject, i + 1, k + 1), {}), leave_out=sample)
            entry = {"a": a, "b": b, "with_reference": row["reference"] in (a, b),
                     "has_reference": ref is not None, "placed": False}
            found = pair_transform(sensors, a, b)
            if found is not None:
                entry["placed"] = True
                if ref is not None:
                    entry.update(judge(found[0], ref))
            for o in result.get("overlaps", []):
                if (o["a"], o["b"]) == (a, b) and o.get("matrix") is not None:
                    ov = {"a": a, "b": b, "used": o["used"], "reason": o.get("reason"),
                          "uncertainty": o.get("uncertainty"), "median_m": o.get("median_m"),
                          "paired": o.get("paired"), "poses": o.get("poses"),
                          "matrix": o["matrix"]}
                    if ref is not None:
                        ov.update(judge(np.array(o["matrix"]), ref))
                    row["overlaps"].append(ov)
            row["pairs"].append(entry)
    return row


def summarise(rows: list[dict], right_cm: float, wrong_cm: float) -> dict:
    good = [r for r in rows if "error" not in r]
    pairs = [p for r in good for p in r["pairs"] if p["has_reference"]]
    placed = [p for p in pairs if p["placed"]]

    def bins(items):
        cm = np.array([p["cm"] for p in items])
        return {"right": int((cm <= right_cm).sum()),
                "off": int(((cm > right_cm) & (cm <= wrong_cm)).sum()),
                "wrong": int((cm > wrong_cm).sum())}
    # a triple's rig is right when every pair it placed that has a reference is right, and
    # it placed every view that is not a copy
    judged = [r for r in good if any(p["has_reference"] for p in r["pairs"])]
    rig_right = sum(r["success"] and all(p.get("cm", np.inf) <= right_cm for p in r["pairs"]
                                         if p["has_reference"]) for r in judged)
    rig_wrong = sum(any(p.get("cm", 0) > wrong_cm for p in r["pairs"] if p["has_reference"])
                    for r in judged)
    cm = np.array([p["cm"] for p in placed])
    return {"triples": len(good), "success": sum(r["success"] for r in good),
            "judged_triples": len(judged), "rig_right": rig_right, "rig_with_a_wrong_pair": rig_wrong,
            "pairs_with_reference": len(pairs), "pairs_placed": len(placed), **bins(placed),
            "placed_cm_p50": float(np.median(cm)) if len(cm) else None,
            "placed_cm_p90": float(np.percentile(cm, 90)) if len(cm) else None,
            "seconds_per_triple_p50": float(np.median([r["seconds"] for r in good]))
            if good else None}


def gate_table(rows: list[dict], right_cm: float, wrong_cm: float) -> list[str]:
    """Every pairwise fit with a reference and a measured spread: how well would each spread
    tolerance separate right fits from wrong ones (fits only; the rig's placement is above)."""
    ovs = [o for r in rows if "error" not in r for o in r["overlaps"] if "cm" in o]
    lines = [f"pairwise fits with a reference: {len(ovs)}; right (<= {right_cm:g} cm) "
             f"{sum(o['cm'] <= right_cm for o in ovs)}, wrong (> {wrong_cm:g} cm) "
             f"{sum(o['cm'] > wrong_cm for o in ovs)}",
             "  spread tolerance (deg, cm at 4.5 m)   passes  right  off  wrong   (no spread: "
             "counted as failing)"]
    for deg, cm in ((0, 0), (10, 50), (5, 15), (3, 8), (2, 5)):
        def ok(o):
            u = o.get("uncertainty") or {}
            if deg == 0:
                return True
            return (u.get("rot_deg") is not None and u.get("far_m") is not None
                    and u["rot_deg"] <= deg and u["far_m"] * 100 <= cm)
        sel = [o for o in ovs if ok(o)]
        lines.append(f"  {'off' if deg == 0 else f'{deg:g} deg, {cm:g} cm':<36} {len(sel):>6} "
                     f"{sum(o['cm'] <= right_cm for o in sel):>6} "
                     f"{sum(right_cm < o['cm'] <= wrong_cm for o in sel):>4} "
                     f"{sum(o['cm'] > wrong_cm for o in sel):>6}")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folder")
    ap.add_argument("--every", type=int, default=1, help="every Nth triple (the reference "
                    "always uses all of a subject's takes)")
    ap.add_argument("--tolerance", action="append", default=None, metavar="DEG,CM",
                    help="stage calibrate's spread tolerance (repeatable; default: the "
                    "product's default only; 0,0 = not judged)")
    ap.add_argument("--fits", default=None, help="cache of the reference's per-take fits (JSON)")
    ap.add_argument("--right-cm", type=float, default=15.0)
    ap.add_argument("--wrong-cm", type=float, default=30.0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    found = nucla.triples(args.folder)
    if not found:
        print(f"no complete development triples in {args.folder} (docs/datasets.md)")
        return 2
    started = time.perf_counter()
    fits = nc.take_fits(found, load_view, copied, args.fits)
    print(f"reference: {sum(len(v) for v in fits.values())} per-take fits of "
          f"{len(found)} triples in {time.perf_counter() - started:.0f} s")
    for (subject, i, k), f in sorted(fits.items()):
        ref = nc.consensus(f)
        print(f"  {subject} v{i}-v{k}: " + ("no reference" if ref is None else
              f"{ref.votes} of {ref.of} takes agree, scatter {100 * ref.scatter_m:.1f} cm, "
              f"{ref.scatter_deg:.1f} deg"))
    chosen = found[::args.every]
    settings = args.tolerance or [None]
    report = {}
    with tempfile.TemporaryDirectory() as tmp:
        for setting in settings:
            extra = [] if setting is None else ["--tolerance-deg", setting.split(",")[0],
                                                "--tolerance-cm", setting.split(",")[1]]
            rows = [triple(s, p, tmp, fits, extra) for s, p in chosen]
            summary = summarise(rows, args.right_cm, args.wrong_cm)
            name = "default" if setting is None else setting
            report[name] = {"summary": summary, "rows": rows}
            s = summary
            print(f"\n-- tolerance {name}: {len(chosen)} triples (every {args.every})")
            print(f"success (every view placed, copies flagged): {s['success']}/{s['triples']}")
            print(f"rigs right (every view placed, every judged pair within {args.right_cm:g} cm "
                  f"of the reference): {s['rig_right']}/{s['judged_triples']}; rigs with a pair "
                  f"over {args.wrong_cm:g} cm: {s['rig_with_a_wrong_pair']}")
            print(f"pairs with a reference {s['pairs_with_reference']}, placed "
                  f"{s['pairs_placed']}: right {s['right']}, off {s['off']}, wrong {s['wrong']}"
                  + ("" if s["placed_cm_p50"] is None else
                     f"; displacement p50 {s['placed_cm_p50']:.1f} cm, p90 "
                     f"{s['placed_cm_p90']:.1f} cm"))
            print(f"time per triple p50 {s['seconds_per_triple_p50']:.2f} s")
            for line in gate_table(rows, args.right_cm, args.wrong_cm):
                print(line)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(report, f, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
