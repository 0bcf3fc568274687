"""The IMM filter's step over all rows at once, fused (``kalman.step`` calls it).

``kalman`` keeps the filter's pure functions (``mix``, ``predict``, ``gate_distance``,
``update``), each tested against filterpy; ``fused_update`` strings the same operations
together over one stacked array per state, so that a step of 25 rows (one person) or 150
(six) is about 75 numpy calls instead of 120 and no intermediate array is gathered with
``np.array``. A numpy call on a few hundred floats costs about the same whatever its size,
so the number of calls is the step's cost.
"""

from __future__ import annotations

import numpy as np

from ..settings import KalmanSettings

M = 2  # modes: 0 quiet, 1 fast
_MU_FLOOR = 1e-300


_CONSTANTS: dict[int, tuple] = {}


def _constants(s: KalmanSettings) -> tuple[np.ndarray, np.ndarray]:
    """(the modes' acceleration variances (M, 1, 1), minus the switching rates (2, 1)),
    read-only: shared by every step with these settings. Kept by the settings object's
    identity (hashing a frozen dataclass of ten fields costs more than a numpy call)."""
    entry = _CONSTANTS.get(id(s))
    if entry is None or entry[0] is not s:
        q = np.array([s.quiet_noise, s.fast_noise])[:, None, None]
        rates = -np.array([[s.quiet_to_fast_per_s], [s.fast_to_quiet_per_s]])
        q.setflags(write=False)
        rates.setflags(write=False)
        if len(_CONSTANTS) > 64:
            _CONSTANTS.clear()
        entry = _CONSTANTS[id(s)] = (s, q, rates)     # s kept: its id is not reused meanwhile
    return entry[1], entry[2]


def fused_update(S: np.ndarray, dt: np.ndarray, z: np.ndarray, r: np.ndarray, s: KalmanSettings,
           q_scale: np.ndarray | None, gate2: float) -> tuple[np.ndarray, np.ndarray]:
    """``kalman.mix``, ``predict``, ``gate_distance`` and ``update`` of every row in one pass
    over the stacked state ``S`` (6, M, N, 3) [x; P; mu] (see ``kalman``): the same
    operations in the same order, so the same floats (tests/test_kalman.py checks it bit for
    bit), on whole blocks where components share an operation, into arrays made once.

    dt: (N,) s >= 0; z: (N, 3) m; r: (N,) per-axis variance m^2; q_scale: (N,) or None;
    gate2: the gate's squared distance. Returns (the updated stack (6, M, N, 3), the squared
    Mahalanobis distance d2 (N,) of each measurement from the prediction); the measurement
    variance used is r grown by d2 / gate2 beyond the gate. Rows without a state or a
    measurement give junk, which the caller discards.
    """
    n = S.shape[2]
    q, rates = _constants(s)
    if q_scale is not None:
        q = q * np.asarray(q_scale, dtype=float)[None, :, None]
    dtc = dt[:, None]                                        # (N, 1)
    # --- mix (``mix``): T = [[1 - p01, p01], [p10, 1 - p10]], e = expm1(-rate dt) = -p
    e = np.expm1(rates * dt)[:, :, None]                     # (2 [from], N, 1)
    T = np.empty((2, 2, n, 1))                               # [stay, switch] x [from]
    np.add(e, 1.0, out=T[0])
    np.negative(e, out=T[1])
    prod = T * S[5]                                          # (2, 2, N, 3): T[i, .] mu_i
    cbar = prod[0] + prod[1, ::-1]                           # (2 [to], N, 3)
    w1 = prod[::-1, 1] / cbar                                # weight of mode 1 in each mixture
    X = S[:5]
    d = X[:, 1] - X[:, 0]                                    # (5, N, 3) mode 1 minus mode 0
    X0 = np.multiply(w1, d[:, None])                         # (5, M, N, 3)
    np.add(X[:, 0, None], X0, out=X0)
    spread = np.empty((3, n, 3))                             # d d^T of [position, velocity]
    np.multiply(d[0], d[0:2], out=spread[0:2])
    np.multiply(d[1], d[1], out=spread[2])
    ww = 1.0 - w1
    np.multiply(w1, ww, out=ww)
    X0[2:5] += ww * spread[:, None]
    # --- predict (``predict``), in place
    qdt2 = q * (dtc * dtc)                                   # (M, N, 1)
    np.multiply(X0[1], dtc, out=d[0:2])                      # d is free now: scratch
    np.add(d[0:2], X0[0], out=X0[0])
    a, b, c = X0[2], X0[3], X0[4]
    pv = c + 0.5 * qdt2
    pv *= dtc
    pv += b
    np.add(b, pv, out=b)
    b *= dtc
    np.add(b, a, out=a)
    a -= (0.25 * qdt2) * (dtc * dtc)
    X0[3] = pv
    np.add(c, qdt2, out=c)
    # --- the gate (``gate_distance``): the mixture's predicted position, weighted by cbar
    w = cbar[1]
    p0 = X0[0, 0]
    dp = X0[0, 1] - p0
    var = X0[2, 1] - X0[2, 0]
    var += (1.0 - w) * dp * dp
    var *= w
    var += X0[2, 0]
    r3 = r[:, None]
    var += r3
    y = z - p0
    y -= w * dp
    y *= y
    y /= var
    d2 = y[:, 0] + y[:, 1]                                   # .sum(axis=1), cheaper
    d2 += y[:, 2]
    # --- update (``update``) with the variance beyond the gate grown by d^2 / gate^2
    r3 = (r * np.maximum(d2 / gate2, 1.0))[:, None]
    out = np.empty_like(S)
    y = z - X0[0]                                            # (M, N, 3)
    sv = X0[2] + r3
    inv = np.divide(1.0, sv)
    k = X0[2:4] * inv                                        # [a / s, b / s]
    g = r3 * inv                                             # 1 - k0 without cancellation
    np.multiply(k, y, out=out[0:2])
    np.add(X0[0:2], out[0:2], out=out[0:2])
    np.multiply(X0[2:4], g, out=out[2:4])
    np.multiply(k[1], X0[3], out=out[4])
    np.subtract(X0[4], out[4], out=out[4])
    y *= y
    y *= inv
    log_l = np.log(sv)
    log_l += y
    log_l *= -0.5
    log_l -= np.maximum(log_l[0], log_l[1])
    np.exp(log_l, out=log_l)
    np.multiply(cbar, log_l, out=log_l)
    np.maximum(log_l, _MU_FLOOR, out=log_l)
    np.divide(log_l, log_l[0] + log_l[1], out=out[5])
    return out, d2
