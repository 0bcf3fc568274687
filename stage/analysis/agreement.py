"""Agreement between two measurement methods, as seed 003 reports it (Tables 1-3).

Seed 003 compares its Kinect system with VICON by Pearson's correlation,
Bland-Altman's bias, reproducibility coefficient (RPC) and coefficient of
variation (CV), and the intraclass correlation for absolute agreement,
ICC(A,1). Definitions used here, as in seed 003's tables:

* bias: mean of (measured - truth);
* RPC: 1.96 x the standard deviation of the differences (the tables'
  caption: "reproducibility coefficient (1.96*SD)");
* CV: the standard deviation of the differences over the mean of all
  measurements, in percent;
* ICC(A,1): two-way model, absolute agreement, single measures (McGraw and
  Wong 1996, case A,1; Shrout and Fleiss's ICC(2,1)):
  (MSR - MSE) / (MSR + (k - 1) MSE + k (MSC - MSE) / n) for n subjects
  (steps) measured by k methods, with MSR, MSC, MSE the mean squares of
  rows, columns and error of the two-way ANOVA. Seed 003 classes it (after
  its reference 21) as poor (< 0.4), fair (0.4-0.59), good (0.6-0.74) and
  excellent (>= 0.75).
"""

from __future__ import annotations

import math

import numpy as np


def icc_a1(ratings: np.ndarray) -> float:
    """ICC(A,1) of an (n subjects, k raters) array; NaN when it is undefined."""
    y = np.asarray(ratings, dtype=float)
    if y.ndim != 2 or y.shape[0] < 2 or y.shape[1] < 2 or not np.isfinite(y).all():
        return math.nan
    n, k = y.shape
    grand = y.mean()
    rows = y.mean(axis=1)
    cols = y.mean(axis=0)
    msr = k * float(((rows - grand) ** 2).sum()) / (n - 1)
    msc = n * float(((cols - grand) ** 2).sum()) / (k - 1)
    resid = y - rows[:, None] - cols[None, :] + grand
    mse = float((resid ** 2).sum()) / ((n - 1) * (k - 1))
    den = msr + (k - 1) * mse + k * (msc - mse) / n
    return (msr - mse) / den if den > 0 else math.nan


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    if len(a) < 3 or a.std() == 0 or b.std() == 0:
        return math.nan
    return float(np.corrcoef(a, b)[0, 1])


def category(icc: float) -> str:
    """Seed 003's words for an ICC(A,1)."""
    if not math.isfinite(icc):
        return "n/a"
    return "poor" if icc < 0.4 else "fair" if icc < 0.6 else "good" if icc < 0.75 else "excellent"


def agreement(measured: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Seed 003's agreement statistics of paired values (same units as the inputs).

    Keys: n, mean, sd (measured), truth_mean, truth_sd, r, bias, rpc, cv
    (percent), icc (ICC(A,1)), rmse. The ICC (and r) compare variation between
    steps with the measuring error; when the truth hardly varies (s.d. under
    1 % of its mean: a gait set in the simulator) they say nothing and are NaN.
    """
    m, t = np.asarray(measured, float), np.asarray(truth, float)
    ok = np.isfinite(m) & np.isfinite(t)
    m, t = m[ok], t[ok]
    n = len(m)
    nan = math.nan
    if n == 0:
        return {"n": 0, "mean": nan, "sd": nan, "truth_mean": nan, "truth_sd": nan, "r": nan,
                "bias": nan, "rpc": nan, "cv": nan, "icc": nan, "rmse": nan}
    diff = m - t
    sd_diff = float(diff.std(ddof=1)) if n > 1 else nan
    both = float(np.concatenate([m, t]).mean())
    truth_sd = float(t.std(ddof=1)) if n > 1 else nan
    varies = n > 1 and truth_sd > 0.01 * abs(float(t.mean()))
    return {"n": n, "mean": float(m.mean()), "sd": float(m.std(ddof=1)) if n > 1 else nan,
            "truth_mean": float(t.mean()), "truth_sd": truth_sd,
            "r": pearson(m, t) if varies else nan, "bias": float(diff.mean()),
            "rpc": 1.96 * sd_diff, "cv": 100.0 * sd_diff / abs(both) if both else nan,
            "icc": icc_a1(np.column_stack([m, t])) if varies else nan,
            "rmse": float(np.sqrt((diff ** 2).mean()))}
