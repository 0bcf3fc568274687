"""Why a firing of bench_anticipation.py is false: the anatomy of its false triggers.

``python bench/bench_anticipation.py --why`` classifies every false trigger (a firing
with no unmatched true crossing from 200 ms before it to 100 ms after it) of the
no-forecast reference and of ``anticipate`` at 50 ms, by what the firing was and what
the truth (the motion capture, in engine time) did around it:

- **a, contradicted**: fired on a prediction the measurements never made (the runtime
  counted it contradicted) and the truth did not cross either;
- **b, second firing**: the truth's crossing it belongs to was matched by another
  firing of the same trigger and joint: an earlier one (the truth has not fallen back
  behind the border by the hysteresis since), or a later one (the crossing lies within
  200 ms before to 300 ms after this firing, and no free crossing does): one movement
  fired twice;
- **c, noise**: the measurements crossed (a measured firing, or an anticipated one the
  measurements then confirmed) where the truth did not: sensor noise, which the
  no-forecast reference has too;
- **d, window**: a true crossing that no firing took lies within 300 ms before to
  200 ms after the firing: the movement was real but the firing came more than 100 ms
  before it or more than 200 ms after it, outside the bench's match window (false by
  the issue's definition: the truth did not cross within 100 ms of what it claimed).

Each record also says whether the reference has a false trigger of the same trigger and
joint within ``SHARED_S`` (``shared``: the forecast did not add it), and the truth's
margin past the border and its speed towards it at the firing (engine time), and the
largest margin the truth reached from 300 ms before to 200 ms after it, and the largest
the fused (measured) joint reached then (how near the measurements came to firing).
"""

from __future__ import annotations

import numpy as np

CLASSES = {"a": "contradicted prediction", "b": "second firing for one crossing",
           "c": "measured where the truth did not cross (noise)",
           "d": "near a crossing the window missed"}
#: a reference false trigger this close (s, same trigger and joint) makes one "shared"
SHARED_S = 0.3
#: how far around a firing (s) an unmatched true crossing makes it a window artefact (d)
NEAR_BEFORE, NEAR_AFTER = 0.3, 0.2


def match(firings: list[tuple], crossings: list[float], before: float, after: float,
          settle: float) -> list[int | None]:
    """For firings of one trigger and joint, sorted by time: the index of the true crossing
    each one matched (the first unmatched crossing from ``before`` s before the firing to
    ``after`` s after it), None for a false trigger; -1 for firings before ``settle``."""
    used = [False] * len(crossings)
    out: list[int | None] = []
    for f in firings:
        tf = f[2]
        if tf < settle:
            out.append(-1)
            continue
        k = next((i for i, c in enumerate(crossings)
                  if not used[i] and c - after <= tf <= c + before), None)
        if k is not None:
            used[k] = True
        out.append(k)
    return out


def classify(firings: list[tuple], contradicted: set, truth: dict, series: tuple,
             hyst: float, before: float, after: float, settle: float,
             measured: tuple | None = None) -> list[dict]:
    """Every false trigger of one run and setting, classified (module docstring).

    firings: (trigger, joint, t, anticipated s); contradicted: {(trigger, joint, fired t)};
    truth: (trigger, joint) -> true crossing times; series: (t grid, (trigger, joint) ->
    the truth's margin past the border, m, > 0 past it); measured: the same for the fused
    bodies the piece saw (its peak near the firing: how close the measurements came)."""
    grid, margins = series
    out = []
    for key, crossings in truth.items():
        mine = sorted(f for f in firings if (f[0], f[1]) == key)
        matched = match(mine, crossings, before, after, settle)
        taken = {k for k in matched if k is not None and k >= 0}
        d = margins[key]
        for f, k in zip(mine, matched):
            if k is not None:
                continue
            tf = f[2]
            i = min(int(np.searchsorted(grid, tf)), len(grid) - 1)
            lo = max(0, i - 1)
            speed = float((d[min(i + 1, len(d) - 1)] - d[lo]) / (grid[min(i + 1, len(d) - 1)]
                                                                 - grid[lo]))
            near = (grid >= tf - NEAR_BEFORE) & (grid <= tf + NEAR_AFTER)
            rec = {"trigger": key[0], "joint": key[1], "t": tf, "anticipated": f[3] > 0,
                   "ahead_s": f[3],
                   "contradicted": (key[0], key[1], tf) in contradicted,
                   "margin_m": float(d[i]), "speed_m_s": speed,
                   "peak_m": float(d[near].max()) if near.any() else float("nan"),
                   "measured_peak_m": float("nan")}
            if measured is not None and len(measured[0]):
                mt, md = measured[0], measured[1][key]
                w = (mt >= tf - NEAR_BEFORE) & (mt <= tf + NEAR_AFTER) & ~np.isnan(md)
                if w.any():
                    rec["measured_peak_m"] = float(md[w].max())
            # the last true crossing at or before the firing (+ the early window)
            prev = [j for j, c in enumerate(crossings) if c <= tf + after]
            last = prev[-1] if prev else None
            near_c = [(j, c) for j, c in enumerate(crossings)
                      if tf - NEAR_AFTER <= c <= tf + NEAR_BEFORE]
            free = [c for j, c in near_c if j not in taken]
            took = [c for j, c in near_c if j in taken]
            if last is not None and last in taken and \
                    not (d[(grid > crossings[last]) & (grid < tf)] < -hyst).any():
                rec["class"], rec["crossing_dt"] = "b", tf - crossings[last]
            elif free:
                c = min(free, key=lambda c: abs(c - tf))
                rec["class"], rec["crossing_dt"] = "d", tf - c
            elif took:       # a crossing just after it, which a later firing took
                c = min(took, key=lambda c: abs(c - tf))
                rec["class"], rec["crossing_dt"] = "b", tf - c
            elif rec["contradicted"]:
                rec["class"], rec["crossing_dt"] = "a", None
            else:
                rec["class"], rec["crossing_dt"] = "c", None
            out.append(rec)
    return sorted(out, key=lambda r: r["t"])


def mark_shared(mine: list[dict], ref: list[dict]) -> None:
    """Set ``shared`` on each of ``mine``: the reference has a false trigger of the same
    trigger and joint within ``SHARED_S`` (each reference record pairs at most once)."""
    free = list(ref)
    for r in mine:
        k = next((i for i, x in enumerate(free) if (x["trigger"], x["joint"]) ==
                  (r["trigger"], r["joint"]) and abs(x["t"] - r["t"]) <= SHARED_S), None)
        r["shared"] = k is not None
        if k is not None:
            free.pop(k)


def report(name: str, records: list[dict]) -> None:
    """Print counts per class and kind, and each record, for one setting."""
    kinds = ("hand", "foot", "zone")
    print(f"-- false triggers of {name}: {len(records)} "
          f"({sum(not r.get('shared', True) for r in records)} not in the reference)")
    print(f"{'class':<50}" + "".join(f"{k:>6}" for k in kinds) + f"{'all':>6}{'new':>6}")
    for c, what in CLASSES.items():
        rs = [r for r in records if r["class"] == c]
        print(f"{c + ' ' + what:<50}" + "".join(
            f"{sum(r['trigger'] == k for r in rs):6d}" for k in kinds)
            + f"{len(rs):6d}{sum(not r.get('shared', True) for r in rs):6d}")
    early = [r for r in records if r["class"] == "d" and r["crossing_dt"] < 0
             and r["crossing_dt"] + r["ahead_s"] >= -0.1]
    if early:
        print(f"   of class d, {len(early)} fired on a prediction within 100 ms of the moment it "
              f"claimed (firing + ahead) but more than 100 ms before the firing itself")
    for r in records:
        dt = "" if r["crossing_dt"] is None else f" crossing {r['crossing_dt'] * 1e3:+.0f} ms"
        src = ("anticipated, contradicted" if r["contradicted"] else
               "anticipated, confirmed" if r["anticipated"] else "measured")
        print(f"  seed {r['seed']} {r['take']} {r['class']} {r['trigger']:<4} {r['joint']:<10}"
              f" t {r['t']:7.3f} {src:<26} truth margin {r['margin_m'] * 100:+5.1f} cm "
              f"speed {r['speed_m_s']:+5.2f} m/s peak {r['peak_m'] * 100:+5.1f} cm, measured "
              f"{r['measured_peak_m'] * 100:+5.1f} cm{dt}"
              + ("" if r.get("shared", True) else "  NEW"))
