"""``stage calibrate --plot``: what the calibration did, as a picture.

One row per calibrated sensor (up to four): seen from above (x-z) and from
the side (z-y), the reference's points, the sensor's raw points (in its own
space) and the same points calibrated into the reference's space; then the
fitness of every method on that sensor's pairs over time, as the paper's
Figure 5 (time in frames of 1/30 s). matplotlib is optional: imported here,
with a one-line error when it is missing (pip install 'stage-kuatro[plot]').
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .. import install_hint
from ..errors import CalibrationError, StageError
from ..joints import JOINT_INDEX
from .fitness import per_frame_fitness
from ..geometry import apply
from .methods import METHODS, calibrate
from .offline import RigCalibration
from .pairs import pair_streams
from .streams import Stream

_COLOURS = {"rigid": "#1b6ca8", "regression": "#d1495b", "ga": "#2e933c", "ga3d": "#7a9e3c",
            "trajectory": "#edae49", "floor": "#6d3b8e"}


def plot_calibration(path: str, result: RigCalibration, streams: dict[str, Stream],
                     methods: list[str] | None = None, max_sensors: int = 4, seed: int = 0,
                     ) -> dict[str, dict[str, float]]:
    """Write the PNG; returns per sensor the mean fitness of each method plotted."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise StageError(f"--plot needs matplotlib: {install_hint('plot')}") from None
    ref = result.reference
    rows = [s for s, c in result.sensors.items() if s != ref and c.matrix is not None]
    rows = rows[:max_sensors]
    if not rows:
        raise StageError("nothing to plot: no sensor besides the reference was calibrated")
    final = {s: c.matrix for s, c in result.sensors.items() if c.matrix is not None}
    fig, axes = plt.subplots(len(rows), 3, figsize=(16, 4.6 * len(rows)), squeeze=False,
                             gridspec_kw={"width_ratios": [1, 1, 1.6]})
    summary: dict[str, dict[str, float]] = {}
    for row, sid in zip(axes, rows):
        near = result.sensors[sid].path[-2]
        lag = result.sensors[sid].lag_s - result.sensors[near].lag_s
        full = pair_streams(streams[near], streams[sid], lag)
        fit_on = result.pair_sets.get((near, sid)) or result.pair_sets.get((sid, near))
        if fit_on is None or fit_on.ref_id != near:
            fit_on = full.evenly(300)
        _points(row[0], row[1], full, final[near], final[sid], sid, ref)
        summary[sid] = _fitness(row[2], full, fit_on, methods or list(METHODS), sid, near, seed)
    fig.suptitle(f"stage calibrate: {len(rows)} sensor(s) into {ref}'s space", fontsize=13)
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=100)
    except OSError as exc:
        raise StageError(f"{path}: cannot write the plot: {exc.strerror or exc}") from None
    finally:
        plt.close(fig)
    return summary


def _points(top: Any, side: Any, pairs: Any, near_to_ref: np.ndarray, to_ref: np.ndarray,
            sid: str, ref: str) -> None:
    sub = pairs.evenly(120)
    w = sub.weight > 0
    reference = apply(near_to_ref, sub.ref)[w]
    raw = sub.other[w]
    calibrated = apply(to_ref, sub.other)[w]
    hips = JOINT_INDEX["SpineBase"]
    track = apply(near_to_ref, pairs.ref[:, hips])
    for ax, (i, j), title in ((top, (0, 2), "from above (x, z)"), (side, (2, 1), "from the side (z, y)")):
        ax.scatter(raw[:, i], raw[:, j], s=2, c="#f2b134", alpha=0.35,
                   label=f"{sid} raw (its own space)")
        ax.scatter(calibrated[:, i], calibrated[:, j], s=3, c="#19a7ce", alpha=0.35,
                   label=f"{sid} calibrated")
        ax.scatter(reference[:, i], reference[:, j], s=1, c="#333333", alpha=0.3,
                   label=f"reference ({ref})")
        ax.plot(track[:, i], track[:, j], lw=0.6, c="#222222", alpha=0.6, label="hip path")
        ax.set_title(f"{sid}: {title}", fontsize=10)
        ax.set_xlabel({0: "x (m)", 2: "z (m)"}[i])
        ax.set_ylabel({2: "z (m)", 1: "y (m)"}[j])
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    top.legend(fontsize=7, markerscale=4, loc="best")


def _fitness(ax: Any, full: Any, fit_on: Any, methods: list[str], sid: str, near: str,
             seed: int) -> dict[str, float]:
    frames = (full.t - full.t[0]) * 30.0
    out: dict[str, float] = {}
    lows = [0.8]
    skipped = []
    for method in methods:
        options = {"seed": seed} if method in ("ga", "ga3d") else {}
        try:
            res = calibrate(fit_on, method, **options)
        except CalibrationError as exc:
            skipped.append(f"{method}: {exc}")
            continue
        f = per_frame_fitness(res.matrix, full.other, full.ref, full.weight)
        out[method] = float(np.nanmean(f))
        lows.append(float(np.nanpercentile(f, 1)))
        ax.plot(frames, f, lw=0.8, c=_COLOURS.get(method), label=f"{method} (mean {out[method]:.3f})")
    ax.set_ylim(max(0.0, min(lows) - 0.05), 1.0)
    ax.set_title(f"{sid} -> {near}: fitness per frame, each method (paper, Figure 5)",
                 fontsize=10)
    ax.set_xlabel("time (frames of 1/30 s)")
    ax.set_ylabel("fitness")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    if skipped:
        ax.text(0.99, 0.02, "\n".join(skipped), transform=ax.transAxes, ha="right", va="bottom",
                fontsize=6, color="#777777")
    return out
