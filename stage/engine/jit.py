"""Compiled kernels for the engine's hottest loops (numba), the numpy code as reference.

Profiled per datagram at six sensors and six people (docs/reports/issue-10.md, stop
25), the engine's CPU was spread over many numpy calls on a few hundred floats each, and
a numpy call costs about the same whatever its size. The loops that are arithmetic are
compiled here by numba, each the same operations in the same order as the numpy code it
replaces, which stays as reference and fallback:

- ``_step_rows``: ``kalman.step``'s usual path (``imm.fused_update`` and what the step
  keeps); rows rejected, restarted or started stay in Python; ``_step_views`` runs it for
  a replay's views of one person in turn (``kalman.step_views``);
- ``_prior`` and ``_consistent``: an instant's IMM prediction (``fuser.prior_of``) and
  which of its views agree (``fusion.consistent_views``), for sensors in step;
- ``_forecast``: a body predicted ahead for a piece or a view that asked
  (``forecast.Forecaster.predict``: the IMM prediction, the speed limits, the bones);
- ``_settle``: each updated person's output skeleton (``people.People._update``), with
  ``_carry`` (``fusion.carry_untracked``); ``_settle_many`` runs it for a batch of persons
  in one call, on the arrays of ``bank.PersonBank``;
- ``_frame``: a frame's transform and ``fusion.unswap_limbs``; ``_frame_r`` adds its joints'
  measurement variances; ``_frame_r_many`` does that for a datagram's frames in one call;
- ``_distance``: ``tracking.Person.distance``;
- ``_offsets``: ``offsets.learn``, a view's learned offset taken off its joints;
  ``_native_offsets`` does it for a batch's frames of the native core's persons, on its
  rows (compiled with the core's kernel, ``warm_native``);
- ``_gate``: ``calibration.gate.JumpGate.check_many``, without the GIL;
- ``_view_joints``: ``sensors.encode.encode_view_joints``, the fused skeleton sent to the
  views (the same bytes);
- ``sensors.scan.scan``: a sensor bundle's skeletons and hand states read in one pass
  (given to ``sensors.protocol.use_scanner``; the receiver decodes with it);
- ``handbank``: the hand votes (``hands.HandVoter``) on one array per person (given to
  ``handbank.use_kernels``; ``handbank.ArrayHandVoter`` calls them).

The results are the numpy code's up to the last bit of exp, log and expm1, which come from
another library than numpy's (tests/test_jit.py and tests/test_kalman.py compare them; on a
CPU with AVX-512 numpy's own differ from the C library's for many inputs, so where a test
holds a kernel to its reference to the bit, the reference runs with the C library's:
tests/libm.py).

numba is a dependency; should it fail to import or to compile on some machine, or with
``STAGE_JIT=0`` in the environment, the engine logs one line and runs the numpy code
(``ENABLED`` says which). The kernels are compiled when the engine is built
(``warm``), never in the middle of a show, and cached on disk by numba, so only the
first start after an install pays the compilation (a few seconds).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import types

import numpy as np

from ..joints import JOINT_INDEX, JOINTS
from ..sensors import protocol, scan
from ..sensors.encode import _NAME_BYTES
from ..settings import KalmanSettings
from . import handbank
from .offsets import CAP_M as _OFFSET_CAP_M
from .imm import _MU_FLOOR, _constants

log = logging.getLogger("stage.engine")
_OFFSET_CAP2 = _OFFSET_CAP_M * _OFFSET_CAP_M

#: numba, imported by ``warm`` (importing it takes about 0.4 s: ``stage --help`` and the
#: commands that build no engine do not pay it)
numba = None
#: whether the compiled kernels are used (False: ``STAGE_JIT=0``, numba missing or broken)
ENABLED = os.environ.get("STAGE_JIT", "1").strip().lower() not in ("0", "false", "no", "off")
_WHY_NOT = "" if ENABLED else "STAGE_JIT=0"


def _import() -> bool:
    """Import numba once; False (after one logged line) if it cannot be."""
    global numba, ENABLED, _WHY_NOT
    if numba is not None:
        return True
    try:
        import numba as imported
    except Exception as exc:  # ImportError, or numba's own errors on an unsupported machine
        ENABLED = False
        _WHY_NOT = f"{type(exc).__name__}: {exc}"
        log.warning("compiled kernels unavailable (%s); the engine runs its numpy code",
                    _WHY_NOT.splitlines()[0])
        return False
    numba = imported
    return True


def _row_predicted(S, st, t, i, pos, vel):  # pragma: no cover (compiled)
    """``FilterState.estimate``, then ``.predicted(t)``, of row ``i`` of the state S (6, 2, N,
    3) with row times st (N,), into pos[i] and vel[i]: never backwards (NaN stays NaN)."""
    ahead = t - st[i]
    if not (ahead > 0.0 or ahead != ahead):
        ahead = 0.0
    for j in range(3):
        w1 = S[5, 1, i, j]
        p = S[0, 0, i, j] + w1 * (S[0, 1, i, j] - S[0, 0, i, j])
        v = S[1, 0, i, j] + w1 * (S[1, 1, i, j] - S[1, 0, i, j])
        pos[i, j] = p + ahead * v
        vel[i, j] = v


def _step_rows(S, st, held_z, held_t, t, z, r, q, q_scale, rates, gate2, reject2,
               out, out_t, out_held_z, out_held_t, outcome, used, counts, pos,
               vel):  # pragma: no cover
    """``kalman.step``'s usual path, row by row: the IMM update of ``imm.fused_update``
    (mix, predict, gate, update with the variance grown beyond the gate) of every row that
    has a state and a valid measurement, and what ``step`` keeps of it.

    S (6, 2, N, 3) [x pos, x vel, P pp, P pv, P vv, mu], st (N,), held_z (N, 3), held_t
    (N,): the state; t (N,), z (N, 3), r (N,): the measurements; q (2,) the modes' noise,
    q_scale (N,) or empty, rates (2,) minus the switching rates. Writes the new state (out,
    out_t, out_held_z, out_held_t), outcome (N,) int8 -- NOT_MEASURED 0, STARTED 1 (a
    valid measurement of a row without a state: for the caller to start), ACCEPTED 2,
    DOWNWEIGHTED 3, REJECTED 4 (beyond reject2, none held: the row keeps its state and
    holds the measurement), RESTARTED 5 (beyond reject2 with one held already: the row
    keeps its state and its held measurement, for the caller to restart) -- used (N,)
    bool (ACCEPTED or DOWNWEIGHTED), counts [rows to restart, rows to start, rows
    downweighted, rows rejected and held]; and each row's position and velocity at t as
    ``FilterState.predicted`` gives them from the new state (pos, vel (N, 3); valid for
    the caller only where no row is to restart or to start: those change the state after).
    A first rejection is held here, not by the caller: on the simulator at 6 x 6 a quarter
    of the steps have one, and holding them in numpy after the kernel cost about 10 us a
    datagram (issue 10, stop 36)."""
    n = S.shape[2]
    X = np.empty((5, 2, 3))
    cb = np.empty((2, 3))
    d = np.empty(5)
    lik = np.empty(2)
    new = np.empty((6, 2, 3))
    scaled = q_scale.shape[0] > 0
    counts[0] = 0
    counts[1] = 0
    counts[2] = 0
    counts[3] = 0
    # a person's rows usually share dt (one frame, one state time): their mode transitions
    # are computed once (the same floats), and exp(0) = 1 of each axis's likelier mode is
    # not computed at all: transcendentals were most of the kernel's time
    last_dt = -1.0
    e0 = e1 = 0.0
    for i in range(n):
        ti = t[i]
        check = z[i, 0] + z[i, 1] + z[i, 2] + ti + 0.0 * r[i]   # NaN or inf anywhere
        valid = (not math.isnan(check)) and (not math.isinf(check)) and r[i] > 0.0
        known = st[i] == st[i]
        keep = True
        hold = False
        if valid and known:
            dt = ti - st[i]
            if dt < 0.0:
                dt = 0.0
            if dt != last_dt:
                e0 = math.expm1(rates[0] * dt)
                e1 = math.expm1(rates[1] * dt)
                last_dt = dt
            stay0 = e0 + 1.0
            stay1 = e1 + 1.0
            sw0 = -e0
            sw1 = -e1
            tt = dt * dt
            if scaled:
                qd0 = (q[0] * q_scale[i]) * tt
                qd1 = (q[1] * q_scale[i]) * tt
            else:
                qd0 = q[0] * tt
                qd1 = q[1] * tt
            acc = 0.0
            for j in range(3):
                mu0 = S[5, 0, i, j]
                mu1 = S[5, 1, i, j]
                c0 = stay0 * mu0 + sw1 * mu1      # cbar: each mode's probability after mixing
                c1 = stay1 * mu1 + sw0 * mu0
                cb[0, j] = c0
                cb[1, j] = c1
                for c in range(5):
                    d[c] = S[c, 1, i, j] - S[c, 0, i, j]
                s0 = d[0] * d[0]
                s1 = d[0] * d[1]
                s2 = d[1] * d[1]
                for m in range(2):
                    if m == 0:
                        w1 = (sw1 * mu1) / c0         # weight of mode 1 in each mixture
                        qd = qd0
                    else:
                        w1 = (stay1 * mu1) / c1
                        qd = qd1
                    x0 = S[0, 0, i, j] + w1 * d[0]
                    x1 = S[1, 0, i, j] + w1 * d[1]
                    ww = w1 * (1.0 - w1)
                    a = (S[2, 0, i, j] + w1 * d[2]) + ww * s0
                    b = (S[3, 0, i, j] + w1 * d[3]) + ww * s1
                    cc = (S[4, 0, i, j] + w1 * d[4]) + ww * s2
                    # predict: constant velocity, white-noise acceleration
                    X[0, m, j] = x1 * dt + x0
                    X[1, m, j] = x1
                    pv = (cc + 0.5 * qd) * dt + b
                    X[2, m, j] = ((b + pv) * dt + a) - (0.25 * qd) * tt
                    X[3, m, j] = pv
                    X[4, m, j] = cc + qd
                # the gate: the mixture's predicted position, weighted by cbar
                w = c1
                p0 = X[0, 0, j]
                dp = X[0, 1, j] - p0
                var = X[2, 1, j] - X[2, 0, j]
                var += (1.0 - w) * dp * dp
                var *= w
                var += X[2, 0, j]
                var += r[i]
                y = z[i, j] - p0
                y -= w * dp
                y *= y
                y /= var
                acc = y if j == 0 else acc + y
            g = acc / gate2
            r3 = r[i] * (g if g > 1.0 else 1.0)
            for j in range(3):
                for m in range(2):
                    y = z[i, j] - X[0, m, j]
                    sv = X[2, m, j] + r3
                    inv = 1.0 / sv
                    k0 = X[2, m, j] * inv
                    k1 = X[3, m, j] * inv
                    gm = r3 * inv
                    new[0, m, j] = X[0, m, j] + k0 * y
                    new[1, m, j] = X[1, m, j] + k1 * y
                    new[2, m, j] = X[2, m, j] * gm
                    new[3, m, j] = X[3, m, j] * gm
                    new[4, m, j] = X[4, m, j] - k1 * X[3, m, j]
                    lik[m] = (math.log(sv) + (y * y) * inv) * -0.5
                # (NaN as numpy's maximum gives it)
                top = lik[0] if (lik[0] > lik[1] or lik[0] != lik[0]) else lik[1]
                for m in range(2):
                    if lik[m] == top and math.isfinite(top):   # exp(0) is 1 exactly
                        v = cb[m, j]
                    else:
                        v = cb[m, j] * math.exp(lik[m] - top)
                    lik[m] = v if (v > _MU_FLOOR or v != v) else _MU_FLOOR
                tot = lik[0] + lik[1]
                new[5, 0, j] = lik[0] / tot
                new[5, 1, j] = lik[1] / tot
            if acc <= reject2:
                keep = False
                for c in range(6):
                    for m in range(2):
                        for j in range(3):
                            out[c, m, i, j] = new[c, m, j]
                out_t[i] = ti if ti > st[i] else st[i]
                for j in range(3):
                    out_held_z[i, j] = held_z[i, j]
                out_held_t[i] = np.nan
                used[i] = True
                if acc > gate2:
                    outcome[i] = 3
                    counts[2] += 1
                else:
                    outcome[i] = 2
            elif held_t[i] != held_t[i]:       # the first rejection: held
                hold = True
                outcome[i] = 4
                used[i] = False
                counts[3] += 1
            else:                              # the second: for the caller to restart
                outcome[i] = 5
                used[i] = False
                counts[0] += 1
        elif valid:
            outcome[i] = 1
            used[i] = False
            counts[1] += 1
        else:
            outcome[i] = 0
            used[i] = False
        if keep:
            for c in range(6):
                for m in range(2):
                    for j in range(3):
                        out[c, m, i, j] = S[c, m, i, j]
            out_t[i] = st[i]
            if hold:
                for j in range(3):
                    out_held_z[i, j] = z[i, j]
                out_held_t[i] = ti
            else:
                for j in range(3):
                    out_held_z[i, j] = held_z[i, j]
                out_held_t[i] = held_t[i]
        _row_predicted(out, out_t, ti, i, pos, vel)


def _step_views(S, st, held_z, held_t, t, z, r, q, q_scale, rates, gate2, reject2, out,
                out_t, out_held_z, out_held_t, outcome, used, counts, pos, vel, tg,
                start):  # pragma: no cover (compiled)
    """``_step_rows`` for G measurement sets of the same N rows in turn (a replay's views of one
    person): set g at time t[g], z[g] (N, 3), r[g] (N,), from the state after set g - 1,
    written to out[g] (6, 2, N, 3), out_t[g], out_held_z[g], out_held_t[g] and its outcome,
    used, counts, pos and vel at [g]. Sets ``start`` ... G - 1 are stepped, the first from
    S, st, held_z, held_t; tg (N,) is scratch. Returns G, or the first set after which a row
    is to restart or to start (its state written as ``_step_rows`` leaves it): the caller
    fixes that state and calls again from the set after it."""
    G = t.shape[0]
    for g in range(start, G):
        for i in range(tg.shape[0]):
            tg[i] = t[g]
        if g == start:
            _step_rows(S, st, held_z, held_t, tg, z[g], r[g], q, q_scale, rates, gate2, reject2,
                       out[g], out_t[g], out_held_z[g], out_held_t[g], outcome[g], used[g],
                       counts[g], pos[g], vel[g])
        else:
            _step_rows(out[g - 1], out_t[g - 1], out_held_z[g - 1], out_held_t[g - 1], tg, z[g],
                       r[g], q, q_scale, rates, gate2, reject2, out[g], out_t[g],
                       out_held_z[g], out_held_t[g], outcome[g], used[g], counts[g], pos[g],
                       vel[g])
        if counts[g, 0] != 0 or counts[g, 1] != 0:
            return g
    return G


def _carry(joints, reported, tracked, offsets, parents, children, carried):  # pragma: no cover
    """``fusion.carry_untracked`` for one body (bones parents first); writes ``carried``."""
    carried[:] = False
    for k in range(children.shape[0]):
        c = children[k]
        p = parents[k]
        if not (reported[c] and reported[p]):
            continue
        if tracked[c]:
            continue
        if math.isnan(offsets[c, 0]):
            continue
        for a in range(3):
            joints[c, a] = joints[p, a] + offsets[c, a]
        carried[c] = True
    # the offsets of tracked joints from their (reported) parents, after the moves: a
    # tracked child of a carried parent takes its offset from where the parent was put
    for k in range(children.shape[0]):
        c = children[k]
        p = parents[k]
        if reported[c] and reported[p] and tracked[c]:
            for a in range(3):
                offsets[c, a] = joints[c, a] - joints[p, a]


def _settle(pos, vel, row_t, t, stale, recent_conf, recent_t, prev, known, tracked, hold,
            carry_on, hold_back, inferred, parents, children, torso, joints_out, vel_out,
            conf_out, known_out, carried_out, centre_out):  # pragma: no cover (compiled)
    """``people.People._update`` for one person: the output skeleton from the filter's
    estimate ``pos``/``vel`` (25, 3) at ``t``; see there. ``tracked`` and ``hold`` are the
    person's own, updated in place as there; the rest goes to the ``*_out`` arrays.
    Returns how many torso joints are known (0: the caller finds the centre otherwise).
    ``recent_conf``/``recent_t`` are the person's views' latest confidences and their times
    (``Person.remember``): a joint's confidence is the best among the views of the last
    ``stale`` s, 0 without one (``People._recent_conf``)."""
    n = pos.shape[0]
    rows = recent_t.shape[0]
    for k in range(n):
        c = -np.inf
        found = False
        for v in range(rows):
            if not (t - recent_t[v] > stale):
                found = True
                x = recent_conf[v, k]
                if x > c or x != x:            # NaN wins, as in numpy's maximum
                    c = x
        if not found:
            c = 0.0
        seen = c > 0.0 and t - row_t[k] <= stale
        if seen:
            for a in range(3):
                if math.isnan(pos[k, a]) or math.isinf(pos[k, a]):
                    seen = False
        for a in range(3):
            joints_out[k, a] = pos[k, a] if seen else prev[k, a]
            v = vel[k, a]
            vel_out[k, a] = v if not (math.isnan(v) or math.isinf(v)) else 0.0
        known_out[k] = known[k] or seen
        conf_out[k] = (c if c < 1.0 else 1.0) if seen else 0.0
        if conf_out[k] > inferred:
            tracked[k] = True
    if carry_on:
        reported = np.empty(n, dtype=np.bool_)
        now = np.empty(n, dtype=np.bool_)
        for k in range(n):
            reported[k] = conf_out[k] > 0.0
            now[k] = conf_out[k] > inferred
        _carry(joints_out, reported, now, hold, parents, children, carried_out)
    if hold_back:
        for k in range(n):
            if not tracked[k]:
                conf_out[k] = 0.0
    count = 0
    for a in range(3):
        centre_out[a] = 0.0
    for k in range(torso.shape[0]):
        j = torso[k]
        if known_out[j]:
            count += 1
            for a in range(3):
                centre_out[a] += joints_out[j, a]
    if count:
        for a in range(3):
            centre_out[a] /= count
    return count


def _settle_many(slots, pos, vel, row_t, t, stale, recent_conf, recent_t, joints, velocity,
                 conf, known, carried, tracked, hold, centre, carry_on, hold_back, inferred,
                 parents, children, torso, counts):  # pragma: no cover (compiled)
    """``_settle`` for P persons in one call, on the person bank (``bank.PersonBank``):
    person i's estimate is row i of ``pos``, ``vel`` (P, 25, 3), ``row_t`` (P, 25) and
    ``t`` (P,); everything else of it is row ``slots[i]`` of the bank's arrays, read and
    updated in place (its output is written over its previous output, which ``_settle``
    reads joint by joint before it writes the same joint). ``counts[i]``: ``_settle``'s
    count of torso joints known."""
    for i in range(slots.shape[0]):
        s = slots[i]
        counts[i] = _settle(pos[i], vel[i], row_t[i], t[i], stale, recent_conf[s], recent_t[s],
                            joints[s], known[s], tracked[s], hold[s], carry_on, hold_back,
                            inferred, parents, children, torso, joints[s], velocity[s], conf[s],
                            known[s], carried[s], centre[s])


def _frame(matrix, joints, conf, unswap, look_l, look_r, arm_l, arm_r, leg_l, leg_r, margin,
           joints_out, conf_out):  # pragma: no cover (compiled)
    """``apply_transform`` then, with ``unswap``, ``fusion.unswap_limbs`` (see there) of
    one sensor frame, into ``joints_out``/``conf_out``; returns the traded bit mask."""
    n = joints.shape[0]
    for k in range(n):
        x, y, z = joints[k, 0], joints[k, 1], joints[k, 2]
        for a in range(3):
            joints_out[k, a] = (x * matrix[a, 0] + y * matrix[a, 1] + z * matrix[a, 2]
                                + matrix[a, 3])
        conf_out[k] = conf[k]
    if not unswap:
        return 0
    c = np.empty(6)
    diff = np.empty((6, 3))
    for p in range(6):
        cl, cr = conf_out[look_l[p]], conf_out[look_r[p]]
        c[p] = cl if cl < cr else cr                   # both seen?
        for a in range(3):
            diff[p, a] = joints_out[look_l[p], a] - joints_out[look_r[p], a]   # left - right
    if c[0] < 1.0 and c[1] < 1.0:                      # no girdle tracked
        return 0
    traded = 0
    for k in range(2):                                 # arm (shoulders), leg (hips)
        if not (c[2 + 2 * k] > 0.0 and c[3 + 2 * k] > 0.0):
            continue
        g = k if c[k] >= 1.0 else 1 - k
        ax, ay, az = diff[g, 0], diff[g, 1], diff[g, 2]
        size = math.sqrt(ax * ax + ay * ay + az * az)
        if size < 0.05:                                # shoulders or hips on one point
            continue
        p0, p1 = 2 + 2 * k, 3 + 2 * k
        a0 = (diff[p0, 0] * ax + diff[p0, 1] * ay + diff[p0, 2] * az) / size
        a1 = (diff[p1, 0] * ax + diff[p1, 1] * ay + diff[p1, 2] * az) / size
        if a0 < -margin and a1 < -margin:
            left = arm_l if k == 0 else leg_l
            right = arm_r if k == 0 else leg_r
            for m in range(left.shape[0]):
                jl, jr = left[m], right[m]
                for a in range(3):
                    v = joints_out[jl, a]
                    joints_out[jl, a] = joints_out[jr, a]
                    joints_out[jr, a] = v
                v = conf_out[jl]
                conf_out[jl] = conf_out[jr]
                conf_out[jr] = v
            traded |= 1 << k
    return traded


#: the trunk's ends (``tracking.body_size``)
_NECK, _BASE = JOINT_INDEX["Neck"], JOINT_INDEX["SpineBase"]


def _frame_r(matrix, joints, conf, unswap, look_l, look_r, arm_l, arm_r, leg_l, leg_r, margin,
             sqrt_noise, per_m, inferred, inferred_var, joints_out, conf_out,
             r_out, size_out):  # pragma: no cover (compiled)
    """``_frame``, then each joint's measurement variance into ``r_out`` as
    ``people.People._fold`` computes it (``kalman.measurement_variance`` at the joint's
    distance from the sensor, whose stage position is the transform's translation; NaN
    where the joint is not seen) and the trunk's length into ``size_out[0]``
    (``tracking.body_size``; NaN for its None), and how many joints it sees (confidence
    above 0) into ``size_out[1]``; returns the traded bit mask."""
    bits = _frame(matrix, joints, conf, unswap, look_l, look_r, arm_l, arm_r, leg_l, leg_r,
                  margin, joints_out, conf_out)
    if conf_out[_NECK] <= 0.0 or conf_out[_BASE] <= 0.0:
        size_out[0] = np.nan
    else:
        dx = joints_out[_NECK, 0] - joints_out[_BASE, 0]
        dy = joints_out[_NECK, 1] - joints_out[_BASE, 1]
        dz = joints_out[_NECK, 2] - joints_out[_BASE, 2]
        size_out[0] = math.sqrt(dx * dx + dy * dy + dz * dz)
    tx, ty, tz = matrix[0, 3], matrix[1, 3], matrix[2, 3]
    seen = 0
    for k in range(conf_out.shape[0]):
        c = conf_out[k]
        if not c > 0.0:
            r_out[k] = np.nan
            continue
        seen += 1
        ox = joints_out[k, 0] - tx
        oy = joints_out[k, 1] - ty
        oz = joints_out[k, 2] - tz
        d2 = ox * ox + oy * oy
        d2 += oz * oz
        e = math.sqrt(d2) - 1.0
        sd = sqrt_noise + per_m * (e if e > 0.0 or e != e else 0.0)     # np.maximum(e, 0)
        guess = 1.0 / c - 1.0 if c <= inferred else 0.0
        r_out[k] = sd * sd / c + guess * inferred_var
    size_out[1] = seen
    return bits


def _frame_r_many(matrix, joints, conf, unswap, look_l, look_r, arm_l, arm_r, leg_l, leg_r,
                  margin, sqrt_noise, per_m, inferred, inferred_var, joints_out, conf_out,
                  r_out, size_out, bits_out):  # pragma: no cover (compiled)
    """``_frame_r`` for K frames of one sensor in one call: frame k is row k of ``joints``
    (K, 25, 3) and ``conf`` (K, 25); its results row k of the ``*_out`` arrays and
    ``bits_out[k]``."""
    for k in range(joints.shape[0]):
        bits_out[k] = _frame_r(matrix, joints[k], conf[k], unswap, look_l, look_r, arm_l, arm_r,
                               leg_l, leg_r, margin, sqrt_noise, per_m, inferred, inferred_var,
                               joints_out[k], conf_out[k], r_out[k], size_out[k])


def _distance(joints, conf, person_joints, velocity, known, dt, torso):  # pragma: no cover
    """``tracking.Person.distance`` (see there) with ``dt`` already bounded; NaN for None:
    over the torso joints both have, or over every joint both have if they share none."""
    on_torso = False
    for k in range(torso.shape[0]):
        if conf[torso[k]] > 0.0 and known[torso[k]]:
            on_torso = True
    total = 0.0
    count = 0
    for m in range(torso.shape[0] if on_torso else joints.shape[0]):
        j = torso[m] if on_torso else m
        if conf[j] > 0.0 and known[j]:
            s = 0.0
            for a in range(3):
                d = joints[j, a] - person_joints[j, a] - velocity[j, a] * dt
                s = d * d if a == 0 else s + d * d
            total += math.sqrt(s)
            count += 1
    return total / count if count else np.nan


def _offsets(z, conf, joints, velocity, known, dt, offsets, live, row, alpha, tracked,
             cap2):  # pragma: no cover (compiled)
    """``offsets.learn`` (see there), joint by joint; ``cap2`` is ``offsets.CAP_M`` squared."""
    n = 0
    for k in range(offsets.shape[0]):
        if live[k] != -np.inf:
            n += 1
    for j in range(z.shape[0]):
        # the innovation of the joint as the sensor saw it (scalars: no array per call)
        d0 = z[j, 0] - (joints[j, 0] + velocity[j, 0] * dt)
        d1 = z[j, 1] - (joints[j, 1] + velocity[j, 1] * dt)
        d2 = z[j, 2] - (joints[j, 2] + velocity[j, 2] * dt)
        if conf[j] > 0.0:
            for a in range(3):
                # the mean as learn sums it: the first live row, then the others in turn
                first = True
                mean = 0.0
                for k in range(offsets.shape[0]):
                    if live[k] != -np.inf:
                        mean = offsets[k, j, a] if first else mean + offsets[k, j, a]
                        first = False
                mean /= n
                z[j, a] -= offsets[row, j, a] - mean
        if conf[j] > tracked and known[j] and d0 * d0 + d1 * d1 + d2 * d2 <= cap2:
            offsets[row, j, 0] += alpha * (d0 - offsets[row, j, 0])
            offsets[row, j, 1] += alpha * (d1 - offsets[row, j, 1])
            offsets[row, j, 2] += alpha * (d2 - offsets[row, j, 2])


def _prior(S, st, t, q, rates, mean, var):  # pragma: no cover (compiled)
    """``fuser.prior_of``: the IMM prediction of each row of the state S (6, 2, N, 3)
    [x pos, x vel, P pp, P pv, P vv, mu] with row times st (N,) for the time t (``kalman.mix``,
    ``predict`` with the modes' noise q (2,) unscaled, ``combine``); writes mean (N, 3) and
    var (N,), the position variance's mean over the three axes. The same operations in the
    same order as the numpy code (dt NaN, a row never measured: 0, and the row stays NaN)."""
    n = S.shape[2]
    pp = np.empty(3)
    for i in range(n):
        dt = _since(t, st[i])
        e0 = math.expm1(rates[0] * dt)
        e1 = math.expm1(rates[1] * dt)
        for j in range(3):
            mean[i, j], _, pp[j] = _imm_axis(S, i, j, e0, e1, dt, q)
        var[i] = ((pp[0] + pp[1]) + pp[2]) / 3.0


def _since(t, row_t):  # pragma: no cover (compiled)
    """``t - row_t`` s, 0 where that is negative or NaN (a row never measured): the dt of the
    numpy code (``np.maximum(t - st, 0)``, NaN made 0)."""
    dt = t - row_t
    if dt != dt or dt < 0.0:
        return 0.0
    return dt


def _imm_axis(S, i, j, e0, e1, h, q):  # pragma: no cover (compiled)
    """Row ``i``, axis ``j`` of the state S (6, 2, N, 3): the IMM prediction ``h`` s ahead
    (``kalman.mix`` with the switching chances -e0 and -e1, ``predict``, ``combine``) as
    (position, velocity, position variance); the operations of the numpy code, in order."""
    stay0 = e0 + 1.0
    stay1 = e1 + 1.0
    sw0 = -e0
    sw1 = -e1
    tt = h * h
    mu0 = S[5, 0, i, j]
    mu1 = S[5, 1, i, j]
    c0 = stay0 * mu0 + sw1 * mu1
    c1 = stay1 * mu1 + sw0 * mu0
    d0 = S[0, 1, i, j] - S[0, 0, i, j]
    d1 = S[1, 1, i, j] - S[1, 0, i, j]
    d2 = S[2, 1, i, j] - S[2, 0, i, j]
    d3 = S[3, 1, i, j] - S[3, 0, i, j]
    d4 = S[4, 1, i, j] - S[4, 0, i, j]
    s0 = d0 * d0
    s1 = d0 * d1
    s2 = d1 * d1
    xp0 = 0.0
    vp0 = 0.0
    pp0 = 0.0
    for m in range(2):
        if m == 0:
            w1 = _div(sw1 * mu1, c0)
        else:
            w1 = _div(stay1 * mu1, c1)
        qd = q[m] * tt
        x0 = S[0, 0, i, j] + w1 * d0
        x1 = S[1, 0, i, j] + w1 * d1
        ww = w1 * (1.0 - w1)
        a = (S[2, 0, i, j] + w1 * d2) + ww * s0
        b = (S[3, 0, i, j] + w1 * d3) + ww * s1
        cc = (S[4, 0, i, j] + w1 * d4) + ww * s2
        px = x1 * h + x0
        pv = (cc + 0.5 * qd) * h + b
        ppm = ((b + pv) * h + a) - (0.25 * qd) * tt
        if m == 0:
            xp0 = px
            vp0 = x1
            pp0 = ppm
        else:
            dx = px - xp0
            return (xp0 + c1 * dx, vp0 + c1 * (x1 - vp0),
                    (pp0 + c1 * (ppm - pp0)) + (c1 * (1.0 - c1)) * (dx * dx))
    return xp0, vp0, pp0     # (not reached: two modes)


def _forecast(S, st, target, horizon, q, rates, memory, limits, joints, seen, tol, bones,
              out, vel, sd, counts):  # pragma: no cover (compiled)
    """``forecast.Forecaster.predict`` of one body: its state S (6, 2, N, 3) with row times
    st (N,) predicted to ``target`` (``kalman.mix`` over dt, ``predict``, ``combine``; the
    vertical axis of rows with a velocity memory predicted over their effective horizon),
    each row's move from ``joints`` (N, 3) capped at its speed limit times ``horizon``, then
    the bones mended (``forecast._keep_bones``). Writes out (N, 3), vel (N, 3), sd (N,) as
    the Forecast's; counts (4,) float: joints capped, joints moved by the bones, the sum and
    the number of the predicted joints' s.d. The same operations in the same order as the
    numpy code."""
    n = S.shape[2]
    pos = np.empty((n, 3))
    raw = np.empty(n)                  # the s.d. of every row (the bones compare them)
    ok = np.empty(n, np.bool_)
    capped = 0
    for i in range(n):
        dt = _since(target, st[i])
        e0 = math.expm1(rates[0] * dt)
        e1 = math.expm1(rates[1] * dt)
        k = dt
        if memory[i] > 0.0:            # forecast.effective_horizon
            k = memory[i] * _SQRT_HALF_PI * math.erf(dt / (memory[i] * _SQRT2))
        p0, vel[i, 0], v0 = _imm_axis(S, i, 0, e0, e1, dt, q)
        p1, vel[i, 1], v1 = _imm_axis(S, i, 1, e0, e1, k, q)     # (vertical: forecast.UP)
        p2, vel[i, 2], v2 = _imm_axis(S, i, 2, e0, e1, dt, q)
        pos[i, 0] = p0
        pos[i, 1] = p1
        pos[i, 2] = p2
        raw[i] = math.sqrt(((v0 + v1) + v2) / 3.0)
        ok[i] = seen[i] and p0 - p0 == 0.0 and p1 - p1 == 0.0 and p2 - p2 == 0.0
        if ok[i]:                      # the speed limit
            m0 = pos[i, 0] - joints[i, 0]
            m1 = pos[i, 1] - joints[i, 1]
            m2 = pos[i, 2] - joints[i, 2]
            dist = math.sqrt((m0 * m0 + m1 * m1) + m2 * m2)
            cap = limits[i] * horizon
            if dist > cap:
                f = cap / dist
                m0 *= f
                m1 *= f
                m2 *= f
                capped += 1
            out[i, 0] = joints[i, 0] + m0
            out[i, 1] = joints[i, 1] + m1
            out[i, 2] = joints[i, 2] + m2
        else:
            for j in range(3):
                out[i, j] = joints[i, j] + 0.0
    fixed = 0                          # the bones: inwards, the less certain parent moves
    for b in range(bones.shape[0] - 1, -1, -1):
        parent, child = bones[b, 0], bones[b, 1]
        if ok[parent] and ok[child] and raw[parent] > raw[child]:
            fixed += _mend_bone(out, joints, parent, child, tol, False)
    for b in range(bones.shape[0]):    # then outwards, every child still out of range
        parent, child = bones[b, 0], bones[b, 1]
        if ok[parent] and ok[child]:
            fixed += _mend_bone(out, joints, parent, child, tol, True)
    total = 0.0
    count = 0
    for i in range(n):
        if ok[i]:
            if not (vel[i, 0] - vel[i, 0] == 0.0):
                vel[i, 0] = 0.0
            if not (vel[i, 1] - vel[i, 1] == 0.0):
                vel[i, 1] = 0.0
            if not (vel[i, 2] - vel[i, 2] == 0.0):
                vel[i, 2] = 0.0
            sd[i] = raw[i]
            if raw[i] == raw[i]:
                total += raw[i]
                count += 1
        else:
            vel[i, 0] = 0.0
            vel[i, 1] = 0.0
            vel[i, 2] = 0.0
            sd[i] = np.nan
    counts[0] = capped
    counts[1] = fixed
    counts[2] = total
    counts[3] = count


def _forecast_many(S, st, target, horizon, q, rates, memory, limits, joints, seen, tol, bones,
                   out, vel, sd, counts):  # pragma: no cover (compiled)
    """``_forecast`` of B bodies in one call: body b's state S[b] (6, 2, N, 3), row times
    st[b], predicted to target[b], from joints[b] and seen[b]; writes out[b], vel[b], sd[b]
    and counts[b] as ``_forecast`` writes them (one dispatch for a frame's bodies instead of
    one each)."""
    for b in range(S.shape[0]):
        _forecast(S[b], st[b], target[b], horizon, q, rates, memory, limits, joints[b], seen[b],
                  tol, bones, out[b], vel[b], sd[b], counts[b])


def _div(a, b):  # pragma: no cover (compiled)
    """a / b as numpy divides (a zero divisor gives inf or NaN, no exception)."""
    if b == 0.0:
        if a == 0.0 or a != a:
            return np.nan
        return math.copysign(np.inf, a) * math.copysign(1.0, b)
    return a / b


def _mend_bone(pred, now, parent, child, tol, move_child):  # pragma: no cover (compiled)
    """``forecast._mend``: the bone parent-child of ``pred`` brought within ``tol`` of its
    length in ``now`` by moving one end along it; 1 if it moved, else 0."""
    r0 = now[child, 0] - now[parent, 0]
    r1 = now[child, 1] - now[parent, 1]
    r2 = now[child, 2] - now[parent, 2]
    length = math.sqrt((r0 * r0 + r1 * r1) + r2 * r2)
    if length <= 0.0:
        return 0
    b0 = pred[child, 0] - pred[parent, 0]
    b1 = pred[child, 1] - pred[parent, 1]
    b2 = pred[child, 2] - pred[parent, 2]
    got = math.sqrt((b0 * b0 + b1 * b1) + b2 * b2)
    lo = length * (1.0 - tol)
    hi = length * (1.0 + tol)
    if lo <= got and got <= hi:
        return 0
    if got > 1e-9:
        u0 = b0 / got
        u1 = b1 / got
        u2 = b2 / got
    else:
        u0 = r0 / length
        u1 = r1 / length
        u2 = r2 / length
    span = min(max(got, lo), hi)
    if move_child:
        pred[child, 0] = pred[parent, 0] + u0 * span
        pred[child, 1] = pred[parent, 1] + u1 * span
        pred[child, 2] = pred[parent, 2] + u2 * span
    else:
        pred[parent, 0] = pred[child, 0] - u0 * span
        pred[parent, 1] = pred[child, 1] - u1 * span
        pred[parent, 2] = pred[child, 2] - u2 * span
    return 1


_SQRT2 = math.sqrt(2.0)
_SQRT_HALF_PI = math.sqrt(math.pi / 2.0)


def _consistent(z, r, prior, prior_var, bias_var, chi2, tracked, with_tracked,
                used):  # pragma: no cover (compiled)
    """``fusion.consistent_views`` (see there) for G >= 2 views: z (G, J, 3), r (G, J), prior
    (J, 3), prior_var (J,), tracked (G, J) (read only if ``with_tracked``); writes used (G,
    J). The same operations in the same order as the numpy code."""
    G = z.shape[0]
    J = z.shape[1]
    seen = np.empty(G, dtype=np.bool_)
    rs = np.empty(G)
    agree = np.empty((G, G), dtype=np.bool_)
    votes = np.empty(G)
    support = np.empty(G)
    for j in range(J):
        n_seen = 0
        for g in range(G):
            rg = r[g, j]
            seen[g] = (not math.isnan(rg)) and (not math.isinf(rg)) and rg > 0.0
            rs[g] = rg if seen[g] else np.inf
            if seen[g]:
                n_seen += 1
        for u in range(G):
            for v in range(G):
                a = z[u, j, 0] - z[v, j, 0]
                b = z[u, j, 1] - z[v, j, 1]
                c = z[u, j, 2] - z[v, j, 2]
                d2 = ((a * a + b * b) + c * c) / ((rs[u] + rs[v]) + 2.0 * bias_var)
                agree[u, v] = (d2 <= chi2) and seen[u] and seen[v]
        top = 0.0
        any_tracked = False
        if with_tracked:
            for g in range(G):
                if seen[g] and tracked[g, j]:
                    any_tracked = True
        for u in range(G):
            a = z[u, j, 0] - prior[j, 0]
            b = z[u, j, 1] - prior[j, 1]
            c = z[u, j, 2] - prior[j, 2]
            dp2 = ((a * a + b * b) + c * c) / ((rs[u] + prior_var[j]) + bias_var)
            count = 0
            sup = 0.0
            for v in range(G):
                if agree[u, v]:
                    count += 1
                info = 1.0 / rs[v] if seen[v] else 0.0
                sup += (1.0 if agree[u, v] else 0.0) * info
            votes[u] = count + (0.5 if (dp2 <= chi2 and seen[u]) else 0.0)
            support[u] = sup
            if u == 0 or sup > top:
                top = sup
        top = top if top > 1e-300 else 1e-300
        best = 0
        for u in range(G):
            vu = votes[u] + (0.25 * support[u]) / top
            if with_tracked and any_tracked and seen[u] and not tracked[u, j]:
                vu = -0.5
            if not seen[u]:
                vu = -1.0
            votes[u] = vu
            if vu > votes[best]:
                best = u
        for g in range(G):
            used[g, j] = agree[best, g] or (seen[g] and n_seen == 1)


def _gate(rows, t, points, tracked, T, X, Mk, V, owner, trusted, links, own, n, min_joints,
          agree_m, gate_m, link_s, valid, d, jumped, dmax):  # pragma: no cover (compiled)
    """``calibration.gate.JumpGate.check_many`` (see there) of k views of sensor ``own`` at
    ``t``: points (k, P, 3) stage space, tracked (k, P); the gate's arrays (T, X, Mk, V,
    owner, trusted, links; n views) are updated in place as there. Writes valid, d and
    jumped (k, n) and dmax (k,) (the largest distance among the views it jumped from);
    valid (k, n) is scratch."""
    k, p = tracked.shape
    for r in range(k):                                   # record (``_record``)
        i = rows[r]
        dt = t - T[i]
        count = 0
        for q in range(p):
            if tracked[r, q] and Mk[i, q]:
                count += 1
        v0 = v1 = v2 = 0.0
        if dt > 0.0 and dt <= 0.2 and count > 0:
            for q in range(p):
                if tracked[r, q] and Mk[i, q]:
                    v0 += points[r, q, 0] - X[i, q, 0]
                    v1 += points[r, q, 1] - X[i, q, 1]
                    v2 += points[r, q, 2] - X[i, q, 2]
            den = count * dt
            v0, v1, v2 = v0 / den, v1 / den, v2 / den
            speed = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            if speed > 3.0:                              # a jump is not a velocity
                f = 3.0 / speed
                v0, v1, v2 = v0 * f, v1 * f, v2 * f
        V[i, 0], V[i, 1], V[i, 2] = v0, v1, v2
        T[i] = t
        for q in range(p):
            Mk[i, q] = tracked[r, q]
            for a in range(3):
                X[i, q, a] = points[r, q, a] if tracked[r, q] else 0.0
    for r in range(k):                                   # distances (``_distances``)
        i = rows[r]
        for j in range(n):
            dtj = t - T[j]
            ok = abs(dtj) <= 0.1 and trusted[owner[j]] and owner[j] != own
            count = 0
            m0 = m1 = m2 = 0.0
            if ok:
                for q in range(p):
                    if tracked[r, q] and Mk[j, q]:
                        count += 1
                        m0 += X[j, q, 0] - X[i, q, 0]
                        m1 += X[j, q, 1] - X[i, q, 1]
                        m2 += X[j, q, 2] - X[i, q, 2]
                ok = count >= min_joints
            valid[r, j] = ok
            if ok:
                m0 = m0 / count + V[j, 0] * dtj
                m1 = m1 / count + V[j, 1] * dtj
                m2 = m2 / count + V[j, 2] * dtj
                d[r, j] = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
            else:
                d[r, j] = np.inf
    for r in range(k):                                   # agreement, jumps
        i = rows[r]
        agreed = False
        for j in range(n):
            if valid[r, j] and d[r, j] <= agree_m:
                agreed = True
        dmax[r] = -1.0
        for j in range(n):
            jumped[r, j] = False
            if agreed:
                if valid[r, j] and d[r, j] <= agree_m:
                    links[i, j] = t
                    links[j, i] = t
            elif valid[r, j] and d[r, j] >= gate_m and t - links[i, j] <= link_s:
                jumped[r, j] = True
                if d[r, j] > dmax[r]:
                    dmax[r] = d[r, j]


def _gate_frames(rows, t, joints, conf, torso, matrix, points, tracked, keep, T, X, Mk, V,
                 owner, trusted, links, own, n, min_joints, agree_m, gate_m, link_s, valid, d,
                 jumped, dmax, found):  # pragma: no cover (compiled)
    """``_gate`` of one datagram's k skeletons as the engine decoded them: joints (k, J, 3)
    and conf (k, J) in the sensor's space, ``matrix`` its sensor -> stage transform. Each
    skeleton's ``torso`` joints that the sensor tracks (conf >= 1) are placed on stage into
    ``points`` and ``tracked`` (scratch, at least (k, P, 3) and (k, P)); a skeleton that
    tracks none of them is left out, as ``calibration.checks`` leaves it out: ``keep``
    gets the skeletons judged, in order, and ``_gate`` judges them (its outputs are rows
    0 .. judged - 1 of valid, d, jumped, dmax). Writes found[0] the number judged,
    found[1] how many jumped, found[2] the closest any judged view came to a view it
    was compared with (inf: none compared)."""
    k = joints.shape[0]
    p = torso.shape[0]
    judged = 0
    for r in range(k):
        seen = False
        for q in range(p):
            c = conf[r, torso[q]] >= 1.0
            tracked[judged, q] = c
            seen = seen or c
        if not seen:
            continue
        for q in range(p):
            x = joints[r, torso[q], 0]
            y = joints[r, torso[q], 1]
            z = joints[r, torso[q], 2]
            for a in range(3):
                points[judged, q, a] = (matrix[a, 0] * x + matrix[a, 1] * y + matrix[a, 2] * z
                                        + matrix[a, 3])
        keep[judged] = r
        judged += 1
    found[0] = judged
    found[1] = 0
    closest = np.inf
    if judged > 0:
        krows = np.empty(judged, dtype=np.int64)
        for r in range(judged):
            krows[r] = rows[keep[r]]
        _gate(krows, t, points[:judged], tracked[:judged], T, X, Mk, V, owner, trusted, links,
              own, n, min_joints, agree_m, gate_m, link_s, valid[:judged], d[:judged],
              jumped[:judged], dmax[:judged])
        for r in range(judged):
            if dmax[r] >= 0.0:
                found[1] += 1
            for j in range(n):
                if d[r, j] < closest:
                    closest = d[r, j]
    found[2] = closest


#: "/jointCoordinates" padded (a constant of ``_view_joints``: iterating a str there made
#: numba compile its unicode support, a second more of compilation)
_JC_ADDRESS = np.frombuffer(b"/jointCoordinates\0\0\0", dtype=np.uint8).copy()


def _view_joints(user, joints, conf, names, name_end, out):  # pragma: no cover (compiled)
    """``sensors.encode.encode_view_joints`` of the joints with ``conf`` > 0, into ``out``
    (long enough for all 25); returns the message's length. ``names`` holds the joint
    names, each padded to 4 bytes, joint j's ending at ``name_end[j]``. The floats are
    rounded to float32 as numpy's ``astype('>f4')`` does (to nearest) and written big-endian."""
    n = conf.shape[0]
    k = 0
    for j in range(n):
        if conf[j] > 0.0:
            k += 1
    pos = 0
    for b in range(_JC_ADDRESS.shape[0]):                # the address, padded to 20 bytes
        out[pos] = _JC_ADDRESS[b]
        pos += 1
    out[pos] = 44                                        # ','
    out[pos + 1] = 105                                   # 'i'
    pos += 2
    for m in range(k):
        out[pos] = 115                                   # 's'
        out[pos + 1] = 102                               # 'f'
        out[pos + 2] = 102
        out[pos + 3] = 102
        out[pos + 4] = 102
        pos += 5
    out[pos] = 0                                         # the tags' end, padded
    pos += 1
    while pos % 4:
        out[pos] = 0
        pos += 1
    u = np.uint32(user)
    for b in range(4):
        out[pos + b] = (u >> np.uint32(24 - 8 * b)) & np.uint32(255)
    pos += 4
    value = np.empty(4, dtype=np.float32)
    bits = value.view(np.uint32)
    for j in range(n):
        if not conf[j] > 0.0:
            continue
        start = name_end[j - 1] if j else 0
        for b in range(start, name_end[j]):
            out[pos] = names[b]
            pos += 1
        value[0] = joints[j, 0]
        value[1] = joints[j, 1]
        value[2] = joints[j, 2]
        value[3] = conf[j]
        for a in range(4):
            v = bits[a]
            out[pos] = (v >> np.uint32(24)) & np.uint32(255)
            out[pos + 1] = (v >> np.uint32(16)) & np.uint32(255)
            out[pos + 2] = (v >> np.uint32(8)) & np.uint32(255)
            out[pos + 3] = v & np.uint32(255)
            pos += 4
    return pos



def _native_choose(zs, rs, confs, S, st, at, q, rates, bias_var, gate2, inferred, mean, var,
                   masks):  # pragma: no cover (compiled)
    """``fuser.Fuser._choose`` for the G views of one instant (zs (G, N, 3), rs, confs (G, N)),
    the instant's first view at ``at`` and the state before it S, st: writes masks (G, N)."""
    G = zs.shape[0]
    n = zs.shape[1]
    if G == 1:
        for k in range(n):
            masks[0, k] = math.isfinite(rs[0, k])
        return
    _prior(S, st, at, q, rates, mean, var)
    tracked = np.empty((G, n), dtype=np.bool_)
    for g in range(G):
        for k in range(n):
            tracked[g, k] = confs[g, k] > inferred
    _consistent(zs, rs, mean, var, bias_var, gate2, tracked, True, masks)


def _native_masked(r, mask, out):  # pragma: no cover (compiled)
    """``out`` = r where ``mask``, else NaN; returns how many joints seen (r finite) the mask
    leaves out (``fuser``'s ``excluded``)."""
    left = 0
    for j in range(r.shape[0]):
        if mask[j]:
            out[j] = r[j]
        else:
            out[j] = np.nan
            if math.isfinite(r[j]):
                left += 1
    return left


def _native_gather(s, first, ins, zi, ri, ci, ring_z, ring_r, ring_conf, gz, gr,
                   gc):  # pragma: no cover (compiled)
    """Rows of gz (G, N, 3), gr, gc (G, N) from the views kept in ring entries ``first``,
    ``first + 1``, ... (mod R) of slot ``s``, with the view zi, ri, ci at row ``ins`` (a
    view being folded in: an instant's new view, or one inserted into a span)."""
    R = ring_z.shape[1]
    f = first
    for m in range(gz.shape[0]):
        if m == ins:
            for k in range(gz.shape[1]):
                gr[m, k] = ri[k]
                gc[m, k] = ci[k]
                for c in range(3):
                    gz[m, k, c] = zi[k, c]
            continue
        for k in range(gz.shape[1]):
            gr[m, k] = ring_r[s, f, k]
            gc[m, k] = ring_conf[s, f, k]
            for c in range(3):
                gz[m, k, c] = ring_z[s, f, k, c]
        f = f + 1 if f + 1 < R else 0


def _native_start(S, st, held_z, held_t, t, z, r, init, outcome, used, pos,
                  vel):  # pragma: no cover (compiled)
    """``kalman._fix_rows`` in a ring entry ``_step_rows`` has just written (S, st, held_z,
    held_t), for its measurements t, z, r: each row it left to restart (outcome 5: rejected
    twice in a row) started again from its held and its new measurement as
    ``kalman._restart`` does -- two points at least 20 ms apart give it a velocity, else
    it starts at rest at the later time -- and each row to start (outcome 1) started at
    rest (``kalman._start``); init (3,): the initial velocity variance and the modes'
    initial probabilities (``kalman.initial_mu``). Each such row is recorded as used
    (``kalman.USED``), and its position and velocity are what ``FilterState.predicted(t)``
    gives from its new state."""
    for i in range(S.shape[2]):
        o = outcome[i]
        if o != 1 and o != 5:
            continue
        ti = t[i]
        dt = 0.0
        if o == 5:
            dt = ti - held_t[i]
            if dt < 0.02 and held_t[i] > ti:
                ti = held_t[i]           # (np.maximum(t, held_t))
        two = o == 5 and dt >= 0.02
        for j in range(3):
            for m in range(2):
                S[0, m, i, j] = z[i, j]
                S[2, m, i, j] = r[i]
                if two:
                    S[1, m, i, j] = (z[i, j] - held_z[i, j]) / dt
                    S[3, m, i, j] = r[i] / dt
                    S[4, m, i, j] = 2.0 * r[i] / (dt * dt)
                    S[5, m, i, j] = _MU_FLOOR if m == 0 else 1.0
                else:
                    S[1, m, i, j] = 0.0
                    S[3, m, i, j] = 0.0
                    S[4, m, i, j] = init[0]
                    S[5, m, i, j] = init[1 + m]
        st[i] = ti
        held_t[i] = np.nan
        used[i] = True
        _row_predicted(S, st, t[i], i, pos, vel)


def _native_span(s, before, out0, sz, sr, sconf, smeta, ring, ring_t, ring_hz, ring_ht, ring_z,
                 ring_r, ring_conf, ring_used, ring_mask, ring_view, ring_out, q, q_scale, rates,
                 gate2, reject2, group_s, bias_var, inferred, tg, init, outcome, counts, pos,
                 vel, given, given_n, first):  # pragma: no cover (compiled)
    """``fuser.Fuser._replay`` in the native core's ring: the M views of a span (sz (M, N, 3),
    sr, sconf (M, N), smeta (M, 6): t, recent row, arrival, size, -, the joints its
    instant's choice left out before) folded in again in capture order from the state in
    ring entry ``before`` of slot ``s``, into entries out0 .. out0 + M - 1 (mod R): grouped
    into instants afresh (a view within ``group_s`` of its instant's first), each
    instant's joints chosen (``_native_choose``) and its views stepped in turn
    (``_step_rows``, rows to start or restart started: ``_native_start``). Each entry keeps
    its view, mask, instant, the joints left out and its rows' outcomes (``ring_out``).
    Adds the steps' rows restarted, joints downweighted and rejected to counts[0],
    counts[2], counts[3], and the change in joints left out to counts[5]; pos and vel are
    the last step's.

    ``given_n`` > 0: the span is one instant whose views but the last are ring entries
    ``first`` ... (their steps the core's own, outcomes kept), and ``given`` (M, N) its
    joints chosen again. A row is independent of the others in a step, so a row whose mask
    is the same in every view but the last has the same states as before: only the rows
    whose masks changed are stepped again (the same floats as stepping every row), and the
    commit writes back only those (``_native_rows_again``, ``_native_rows_back``); the last
    view is stepped in full."""
    M = sz.shape[0]
    n = sz.shape[1]
    R = ring.shape[1]
    cs = np.empty(4, dtype=np.int64)
    rr = np.empty(n)
    mean = np.empty((n, 3))
    var = np.empty(n)
    prev = before
    if given_n > 0:
        prev = _native_rows_again(s, before, out0, sz, sr, smeta, ring, ring_t, ring_hz,
                                  ring_ht, ring_used, ring_mask, ring_view, ring_out, ring_z,
                                  ring_r, ring_conf, q, q_scale, rates, gate2, reject2, init,
                                  counts, given, first)
        v = M - 1
        e = out0 + v
        if e >= R:
            e -= R
        _native_span_step(s, prev, e, v, smeta[0, 0], given[v], sz, sr, sconf, smeta, ring,
                          ring_t, ring_hz, ring_ht, ring_z, ring_r, ring_conf, ring_used,
                          ring_mask, ring_view, ring_out, q, q_scale, rates, gate2, reject2,
                          tg, init, outcome, counts, pos, vel, rr, cs)
        return
    k = 0
    while k < M:
        at = smeta[k, 0]
        g = k + 1
        while g < M and smeta[g, 0] - at <= group_s:
            g += 1
        G = g - k
        gz = np.empty((G, n, 3))
        gr = np.empty((G, n))
        gc = np.empty((G, n))
        for m in range(G):
            for j in range(n):
                gr[m, j] = sr[k + m, j]
                gc[m, j] = sconf[k + m, j]
                for c in range(3):
                    gz[m, j, c] = sz[k + m, j, c]
        masks = np.empty((G, n), dtype=np.bool_)
        _native_choose(gz, gr, gc, ring[s, prev], ring_t[s, prev], at, q, rates, bias_var, gate2,
                       inferred, mean, var, masks)
        for m in range(G):
            v = k + m
            e = out0 + v
            if e >= R:
                e -= R
            _native_span_step(s, prev, e, v, at, masks[m], sz, sr, sconf, smeta, ring, ring_t,
                              ring_hz, ring_ht, ring_z, ring_r, ring_conf, ring_used, ring_mask,
                              ring_view, ring_out, q, q_scale, rates, gate2, reject2, tg, init,
                              outcome, counts, pos, vel, rr, cs)
            prev = e
        k = g


def _native_span_step(s, prev, e, v, at, mask, sz, sr, sconf, smeta, ring, ring_t, ring_hz,
                      ring_ht, ring_z, ring_r, ring_conf, ring_used, ring_mask, ring_view,
                      ring_out, q, q_scale, rates, gate2, reject2, tg, init, outcome, counts,
                      pos, vel, rr, cs):  # pragma: no cover (compiled)
    """A span's view ``v`` stepped in full from ring entry ``prev`` into entry ``e``, with
    the joints ``mask`` lets through, its instant beginning at ``at`` (``_native_span``)."""
    n = sz.shape[1]
    left = _native_masked(sr[v], mask, rr)
    for j in range(n):
        tg[j] = smeta[v, 0]
    _step_rows(ring[s, prev], ring_t[s, prev], ring_hz[s, prev], ring_ht[s, prev], tg,
               sz[v], rr, q, q_scale, rates, gate2, reject2, ring[s, e], ring_t[s, e],
               ring_hz[s, e], ring_ht[s, e], outcome, ring_used[s, e], cs, pos, vel)
    if cs[0] or cs[1]:
        _native_start(ring[s, e], ring_t[s, e], ring_hz[s, e], ring_ht[s, e], tg, sz[v],
                      rr, init, outcome, ring_used[s, e], pos, vel)
    counts[0] += cs[0]
    counts[2] += cs[2]
    counts[3] += cs[3]
    counts[5] += left - int(smeta[v, 5])
    for j in range(n):
        ring_r[s, e, j] = sr[v, j]
        ring_conf[s, e, j] = sconf[v, j]
        ring_mask[s, e, j] = mask[j]
        ring_out[s, e, j] = outcome[j]
        for c in range(3):
            ring_z[s, e, j, c] = sz[v, j, c]
    for c in range(4):
        ring_view[s, e, c] = smeta[v, c]
    ring_view[s, e, 4] = at
    ring_view[s, e, 5] = left


def _native_rows_again(s, before, out0, sz, sr, smeta, ring, ring_t, ring_hz, ring_ht, ring_used,
                       ring_mask, ring_view, ring_out, ring_z, ring_r, ring_conf, q, q_scale,
                       rates, gate2, reject2, init, counts, given,
                       first):  # pragma: no cover (compiled)
    """``_native_span``'s instant chosen again, its views but the last (M - 1 ring entries from
    ``first``, the state before them in entry ``before``): the rows whose mask ``given``
    changes in any of them stepped again from the entry before, as ``_native_span_step``
    steps them (``_step_rows`` on those rows alone, then ``_native_start``), into entry
    out0 + m; there only those rows, the mask, the outcomes of those rows and the joints
    left out are written (the commit writes back only those, ``_native_rows_back``), but
    for the last of them, copied whole first: the last view's step reads it. Adds the
    entries' rows restarted, downweighted and rejected (their outcomes, kept and new) and
    the change in joints left out to ``counts``; returns the entry of the last of them."""
    M = sz.shape[0]
    n = sz.shape[1]
    R = ring.shape[1]
    dirty = np.zeros(n, dtype=np.bool_)
    f = first
    for m in range(M - 1):
        for j in range(n):
            if given[m, j] != ring_mask[s, f, j]:
                dirty[j] = True
        f = f + 1 if f + 1 < R else 0
    C = 0
    for j in range(n):
        if dirty[j]:
            C += 1
    idx = np.empty(C, dtype=np.int64)
    C = 0
    for j in range(n):
        if dirty[j]:
            idx[C] = j
            C += 1
    S = np.empty((6, 2, C, 3))
    st = np.empty(C)
    hz = np.empty((C, 3))
    ht = np.empty(C)
    O = np.empty((6, 2, C, 3))
    ot = np.empty(C)
    ohz = np.empty((C, 3))
    oht = np.empty(C)
    tg = np.empty(C)
    zc = np.empty((C, 3))
    rc = np.empty(C)
    oc = np.empty(C, dtype=np.int8)
    uc = np.empty(C, dtype=np.bool_)
    pc = np.empty((C, 3))
    vc = np.empty((C, 3))
    qc = np.empty(C if q_scale.shape[0] > 0 else 0)
    for c in range(qc.shape[0]):
        qc[c] = q_scale[idx[c]]
    cs = np.empty(4, dtype=np.int64)
    prev = before
    f = first
    for m in range(M - 1):
        e = out0 + m
        if e >= R:
            e -= R
        if m == M - 2:
            _native_move(s, f, e, ring, ring_t, ring_hz, ring_ht, ring_z, ring_r, ring_conf,
                         ring_used, ring_mask, ring_view, ring_out)
        if C:
            for c in range(C):
                j = idx[c]
                _native_row(ring[s, prev], ring_t[s, prev], ring_hz[s, prev], ring_ht[s, prev], j,
                            S, st, hz, ht, c)
                tg[c] = smeta[m, 0]
                rc[c] = sr[m, j] if given[m, j] else np.nan
                for x in range(3):
                    zc[c, x] = sz[m, j, x]
            _step_rows(S, st, hz, ht, tg, zc, rc, q, qc, rates, gate2, reject2, O, ot, ohz, oht,
                       oc, uc, cs, pc, vc)
            if cs[0] or cs[1]:
                _native_start(O, ot, ohz, oht, tg, zc, rc, init, oc, uc, pc, vc)
            for c in range(C):
                j = idx[c]
                _native_row(O, ot, ohz, oht, c, ring[s, e], ring_t[s, e], ring_hz[s, e],
                            ring_ht[s, e], j)
                ring_used[s, e, j] = uc[c]
                ring_out[s, e, j] = oc[c]
        left = 0
        for j in range(n):
            ring_mask[s, e, j] = given[m, j]
            if not given[m, j] and math.isfinite(sr[m, j]):
                left += 1
            o = ring_out[s, e, j] if dirty[j] else ring_out[s, f, j]
            if o == 5:
                counts[0] += 1
            elif o == 3:
                counts[2] += 1
            elif o == 4:
                counts[3] += 1
        counts[5] += left - int(smeta[m, 5])
        ring_view[s, e, 5] = left
        prev = e
        f = f + 1 if f + 1 < R else 0
    return prev


def _native_row(S, st, hz, ht, i, T, tt, hzt, htt, k):  # pragma: no cover (compiled)
    """Row ``i`` of the filter state S (6, 2, N, 3), st, hz, ht copied to row ``k`` of T, tt,
    hzt, htt (a ring entry's, or a few rows' gathered apart)."""
    for a in range(6):
        for b in range(2):
            for x in range(3):
                T[a, b, k, x] = S[a, b, i, x]
    tt[k] = st[i]
    htt[k] = ht[i]
    for x in range(3):
        hzt[k, x] = hz[i, x]


def _native_rows_back(s, b, first, G, ring, ring_t, ring_hz, ring_ht, ring_used, ring_mask,
                      ring_view, ring_out):  # pragma: no cover (compiled)
    """An instant chosen again committed (``_native_rows_again``): of the G entries after the
    head from ``b``, the rows whose mask differs from entry ``first`` + m's in any of them,
    their outcomes, the masks and the joints left out, written back into entries
    ``first`` ... (those rows are the ones stepped again; the others are the same floats)."""
    R = ring.shape[1]
    n = ring_mask.shape[2]
    dirty = np.zeros(n, dtype=np.bool_)
    for m in range(G):
        src = b + m if b + m < R else b + m - R
        dst = first + m if first + m < R else first + m - R
        for j in range(n):
            if ring_mask[s, src, j] != ring_mask[s, dst, j]:
                dirty[j] = True
    for m in range(G):
        src = b + m if b + m < R else b + m - R
        dst = first + m if first + m < R else first + m - R
        for j in range(n):
            ring_mask[s, dst, j] = ring_mask[s, src, j]
            if not dirty[j]:
                continue
            _native_row(ring[s, src], ring_t[s, src], ring_hz[s, src], ring_ht[s, src], j,
                        ring[s, dst], ring_t[s, dst], ring_hz[s, dst], ring_ht[s, dst], j)
            ring_used[s, dst, j] = ring_used[s, src, j]
            ring_out[s, dst, j] = ring_out[s, src, j]
        ring_view[s, dst, 5] = ring_view[s, src, 5]


def _native_move(s, src, dst, ring, ring_t, ring_hz, ring_ht, ring_z, ring_r, ring_conf,
                 ring_used, ring_mask, ring_view, ring_out):  # pragma: no cover (compiled)
    """Ring entry ``src`` of slot ``s`` copied to entry ``dst``."""
    ring[s, dst] = ring[s, src]
    ring_t[s, dst] = ring_t[s, src]
    ring_hz[s, dst] = ring_hz[s, src]
    ring_ht[s, dst] = ring_ht[s, src]
    ring_z[s, dst] = ring_z[s, src]
    ring_r[s, dst] = ring_r[s, src]
    ring_conf[s, dst] = ring_conf[s, src]
    ring_used[s, dst] = ring_used[s, src]
    ring_mask[s, dst] = ring_mask[s, src]
    ring_view[s, dst] = ring_view[s, src]
    ring_out[s, dst] = ring_out[s, src]


def _native_offsets(ints, times, z, conf, recent_t, joints, velocity, known, offsets, offset_s,
                    gap_max, tracked, cap2):  # pragma: no cover (compiled)
    """The view offsets (``offsets.learn``) of a batch's K frames of persons the native core
    holds, in the batch's order, as ``people.People._offset`` does them one by one. Frame i
    is z[ints[i, 0]] (25, 3) with confidences conf[ints[i, 0]], corrected in place; it is
    the view in row ints[i, 2] of the person in slot ints[i, 1], captured at times[i, 0],
    the person's newest frame being at times[i, 1]. The person's joints, velocities, known
    joints and views' times are the core's rows (``joints`` ... ``recent_t``), its offsets
    ``offsets`` (S, R, 25, 3); ``cap2`` is ``offsets.CAP_M`` squared."""
    for i in range(ints.shape[0]):
        k = ints[i, 0]
        s = ints[i, 1]
        row = ints[i, 2]
        t = times[i, 0]
        live = recent_t[s]
        gap = min(max(t - live[row], 0.0), gap_max)
        alpha = -math.expm1(-gap / offset_s)
        dt = min(max(t - times[i, 1], -gap_max), gap_max)
        _offsets(z[k], conf[k], joints[s], velocity[s], known[s], dt, offsets[s], live, row,
                 alpha, tracked, cap2)


def _native_fold(slots, t, z, r, conf, rows, pid, arrival, size, ring, ring_t, ring_hz, ring_ht,
                 ring_z, ring_r, ring_conf, ring_used, ring_mask, ring_view, ring_out, head, steps,
                 valid, newest, anchor, person_t, q, q_scale, rates, gate2, reject2, group_s, bias2,
                 replay_s, inferred, tg, init, given, outcome, counts, pos, vel, plan, stale,
                 recent_conf, recent_t, joints, velocity, pconf, known, carried, tracked, hold,
                 centre, carry_on, hold_back, parents, children, torso, names, name_end, buf,
                 offsets, centred):  # pragma: no cover (compiled)
    """The native core's datagram (``native.NativeCore.fold``): K views of K distinct persons
    folded as ``fuser.Fuser.fold`` folds them, settled and encoded, in one call.

    View i is of the person in slot ``slots[i]``: captured at t[i], joints z[i] (25, 3),
    variances r[i] (25,), confidences conf[i], remembered in row ``rows[i]`` of the
    person's ``recent_conf``/``recent_t``, sent as user ``pid[i]``; its datagram arrived at
    ``arrival[i]``, its trunk measured ``size[i]``. A person's filter is a ring of states
    (``ring`` (S, R, 6, 2, 25, 3), ``ring_t``, ``ring_hz``, ``ring_ht``), ``head[s]`` its
    newest: a step reads one entry and writes the next, so the states before each step stay
    where they were, and the entry also keeps the view that made it (``ring_z``,
    ``ring_r``, ``ring_conf``, the joints it used ``ring_used``, the joints its instant's
    choice let through ``ring_mask``, and ``ring_view`` (S, R, 6): t, recent row, arrival,
    size, its instant's anchor, the joints the choice left out). ``valid[s]`` steps back
    from the head have their state before them in the ring; ``steps[s]`` counts the steps
    since the person was taken.

    As the Python path: a view after the person's newest that begins an instant is a plain
    step; one that joins the newest instant is a plain step when it and the instant's views
    all agree (``Fuser._agrees``), else the instant's joints are chosen again
    (``_native_choose``): a plain step with its mask if the earlier views keep theirs, else
    the instant folded again (``_native_span``); a view before the newest is inserted in
    capture order and the span from its instant on folded again. A replay's steps are
    written after the head first and moved into place only when the datagram is committed.
    A step's rows to start or restart are started as ``kalman._fix_rows`` starts them
    (``_native_start``). The core declines (returns -1 - i for view i, nothing committed,
    the entries after the heads scratch) a view the Python path would drop as late or fit
    before its history, a span or instant reaching past ``valid``, a span longer than a
    third of the ring and a person twice in a datagram. Else the heads
    move, each person is remembered, settled (``_settle``, in place on its rows as
    ``_settle_many``) and encoded (``_view_joints``) into ``buf`` at ``offsets[i]`` ..
    ``offsets[i + 1]``; ``centred[i]`` is ``_settle``'s count of torso joints known (0: the
    caller finds the centre). Returns K. ``counts`` (K, 6) per view: rows restarted, rows
    started (of a plain step; a replay's are not counted), joints downweighted, rejected
    and held, 1 if replayed, the change in joints left out by instants' choices. ``init``
    (3,): ``_native_start``'s. ``plan`` (K, 2): scratch (a view's span: first entry, and
    its length, negative where only changed rows are written back); ``given`` (R, N):
    scratch (an instant's joints chosen again)."""
    K = slots.shape[0]
    R = ring.shape[1]
    n = z.shape[1]
    bias_var = bias2 * 0.5
    rr = np.empty(n)
    cs = np.empty(4, dtype=np.int64)
    mean = np.empty((n, 3))
    var = np.empty(n)
    for i in range(K):
        s = slots[i]
        for j in range(i):
            if slots[j] == s:
                return -1 - i
        for c in range(6):
            counts[i, c] = 0
        a = head[s]
        b = a + 1
        if b == R:
            b = 0
        ti = t[i]
        plan[i, 0] = -1                  # a step into entry b; else a span from plan[i, 0]
        plan[i, 1] = 0
        plan_ins = 0
        masked = False
        given_n = 0
        # the oldest step kept began an instant when none was lost since the person was
        # taken (the Python path's history begins with one; ``take`` put it all in)
        whole = valid[s] == steps[s]
        if ti >= newest[s] and ti - anchor[s] > group_s:
            pass                         # begins an instant
        elif ti >= newest[s]:
            # joins the newest instant: its views are the steps back from the head that share
            # its anchor, all in the ring
            e = a
            back = 0
            agree = True
            while True:
                if back >= valid[s]:
                    if whole and back > 0:
                        break
                    return -1 - i
                if ring_view[s, e, 4] != anchor[s]:
                    break
                if ring_view[s, e, 5] != 0:
                    agree = False
                if agree:
                    for k in range(n):
                        dx = ring_z[s, e, k, 0] - z[i, k, 0]
                        dy = ring_z[s, e, k, 1] - z[i, k, 1]
                        dz = ring_z[s, e, k, 2] - z[i, k, 2]
                        d2 = (dx * dx + dy * dy + dz * dz) / (ring_r[s, e, k] + r[i, k] + bias2)
                        if d2 > gate2:
                            agree = False
                            break
                back += 1
                e = e - 1 if e > 0 else R - 1
            if not agree:
                # the instant's joints chosen again, this view with them
                G = back + 1
                first = e + 1 if e + 1 < R else 0
                gz = np.empty((G, n, 3))
                gr = np.empty((G, n))
                gc = np.empty((G, n))
                _native_gather(s, first, back, z[i], r[i], conf[i], ring_z, ring_r, ring_conf,
                               gz, gr, gc)
                masks = np.empty((G, n), dtype=np.bool_)
                _native_choose(gz, gr, gc, ring[s, e], ring_t[s, e], anchor[s], q, rates,
                               bias_var, gate2, inferred, mean, var, masks)
                same = True
                f = first
                for m in range(back):
                    for k in range(n):
                        if masks[m, k] != ring_mask[s, f, k]:
                            same = False
                    f = f + 1 if f + 1 < R else 0
                if same:
                    masked = True
                    counts[i, 5] = _native_masked(r[i], masks[back], rr)
                    for k in range(n):
                        ring_mask[s, b, k] = masks[back, k]
                else:
                    plan[i, 0] = first
                    plan[i, 1] = back + 1
                    # only the rows whose masks change are stepped again, where the
                    # instant's steps are the core's own (their outcomes kept)
                    given_n = G
                    f = first
                    for m in range(back):
                        if ring_out[s, f, 0] < 0:
                            given_n = 0
                        f = f + 1 if f + 1 < R else 0
                    for m in range(G):
                        for k in range(n):
                            given[m, k] = masks[m, k]
        else:
            # before the newest: after the last step captured no later than it
            e = a
            back = 0
            while back < valid[s] and ring_view[s, e, 0] > ti:
                back += 1
                e = e - 1 if e > 0 else R - 1
            if back >= valid[s] or ring_view[s, e, 4] < newest[s] - replay_s:
                return -1 - i        # (before the Python path's history: late, or not known)
            if ti - ring_view[s, e, 4] <= group_s:
                ins = 1              # joins e's instant: the span from its first step
                while True:
                    if back + 1 >= valid[s]:
                        if whole:
                            break
                        return -1 - i
                    p = e - 1 if e > 0 else R - 1
                    if ring_view[s, p, 4] != ring_view[s, e, 4]:
                        break
                    e = p
                    back += 1
                    ins += 1
                first = e
                span = back + 2
            else:
                ins = 0              # begins the span after e
                first = e + 1 if e + 1 < R else 0
                span = back + 1
            plan[i, 0] = first
            plan[i, 1] = span
            plan_ins = ins
        M = plan[i, 1]
        if M:
            if 3 * M > R:
                return -1 - i
            # the span's views (ring entries from ``first``, this one inserted), stepped from
            # the state before ``first`` into the entries after the head
            if valid[s] > R - M - 1:
                valid[s] = R - M - 1    # (those entries are written over, kept or not)
            first = plan[i, 0]
            if ti >= newest[s]:
                plan_ins = M - 1
            sz = np.empty((M, n, 3))
            sr = np.empty((M, n))
            sc = np.empty((M, n))
            sm = np.empty((M, 6))
            _native_gather(s, first, plan_ins, z[i], r[i], conf[i], ring_z, ring_r, ring_conf,
                           sz, sr, sc)
            f = first
            for m in range(M):
                if m == plan_ins:
                    sm[m, 0] = ti
                    sm[m, 1] = rows[i]
                    sm[m, 2] = arrival[i]
                    sm[m, 3] = size[i]
                    sm[m, 4] = np.nan
                    sm[m, 5] = 0.0
                    continue
                for c in range(6):
                    sm[m, c] = ring_view[s, f, c]
                f = f + 1 if f + 1 < R else 0
            before = first - 1 if first > 0 else R - 1
            counts[i, 4] = 1
            _native_span(s, before, b, sz, sr, sc, sm, ring, ring_t, ring_hz, ring_ht, ring_z,
                         ring_r, ring_conf, ring_used, ring_mask, ring_view, ring_out, q, q_scale,
                         rates, gate2, reject2, group_s, bias_var, inferred, tg, init,
                         outcome[i], counts[i], pos[i], vel[i], given, given_n, first)
            if given_n > 0:
                plan[i, 1] = -M           # (the commit writes back the changed rows alone)
            continue
        for k in range(n):
            tg[k] = ti
            if not masked:
                rr[k] = r[i, k]
        _step_rows(ring[s, a], ring_t[s, a], ring_hz[s, a], ring_ht[s, a], tg, z[i], rr, q,
                   q_scale, rates, gate2, reject2, ring[s, b], ring_t[s, b], ring_hz[s, b],
                   ring_ht[s, b], outcome[i], ring_used[s, b], cs, pos[i], vel[i])
        for c in range(4):
            counts[i, c] = cs[c]
        if cs[0] or cs[1]:
            _native_start(ring[s, b], ring_t[s, b], ring_hz[s, b], ring_ht[s, b], tg, z[i], rr,
                          init, outcome[i], ring_used[s, b], pos[i], vel[i])
        for k in range(n):
            ring_r[s, b, k] = r[i, k]
            ring_conf[s, b, k] = conf[i, k]
            ring_out[s, b, k] = outcome[i, k]
            if not masked:
                ring_mask[s, b, k] = math.isfinite(r[i, k])
            for c in range(3):
                ring_z[s, b, k, c] = z[i, k, c]
        ring_view[s, b, 0] = ti
        ring_view[s, b, 1] = rows[i]
        ring_view[s, b, 2] = arrival[i]
        ring_view[s, b, 3] = size[i]
        ring_view[s, b, 4] = ti if ti - anchor[s] > group_s else anchor[s]
        ring_view[s, b, 5] = counts[i, 5]
    at = 0
    offsets[0] = 0
    for i in range(K):
        s = slots[i]
        b = head[s] + 1
        if b == R:
            b = 0
        M = plan[i, 1]
        rows_only = M < 0                 # (an instant chosen again: ``_native_rows_again``)
        if rows_only:
            M = -M
            plan[i, 1] = M
        if M:
            # the replayed span moved from the entries after the head into place
            first = plan[i, 0]
            if rows_only:
                _native_rows_back(s, b, first, M - 1, ring, ring_t, ring_hz, ring_ht,
                                  ring_used, ring_mask, ring_view, ring_out)
            for m in range(M - 1 if rows_only else 0, M):
                src = b + m
                if src >= R:
                    src -= R
                dst = first + m
                if dst >= R:
                    dst -= R
                _native_move(s, src, dst, ring, ring_t, ring_hz, ring_ht, ring_z, ring_r,
                             ring_conf, ring_used, ring_mask, ring_view, ring_out)
            b = first + M - 1
            if b >= R:
                b -= R
        else:
            if valid[s] < R - 2:
                valid[s] += 1
        head[s] = b
        steps[s] += 1
        if M and valid[s] < R - M - 1:
            valid[s] += 1
        if t[i] > newest[s]:
            newest[s] = t[i]
        anchor[s] = ring_view[s, b, 4]
        for k in range(conf.shape[1]):
            recent_conf[s, rows[i], k] = conf[i, k]
        recent_t[s, rows[i]] = t[i]
        ts = person_t[s] if person_t[s] > t[i] else t[i]
        person_t[s] = ts
        centred[i] = _settle(pos[i], vel[i], ring_t[s, b], ts, stale, recent_conf[s],
                             recent_t[s], joints[s], known[s], tracked[s], hold[s], carry_on,
                             hold_back, inferred, parents, children, torso, joints[s],
                             velocity[s], pconf[s], known[s], carried[s], centre[s])
        at += _view_joints(pid[i], joints[s], pconf[s], names, name_end, buf[at:])
        offsets[i + 1] = at
    return K


_F8_4 = "float64[:, :, :, ::1]"
_SIGNATURES = {
    "_step_rows": f"void({_F8_4}, float64[::1], float64[:, ::1], float64[::1], float64[::1], "
                  f"float64[:, ::1], float64[::1], float64[::1], float64[::1], float64[::1], "
                  f"float64, float64, {_F8_4}, float64[::1], float64[:, ::1], float64[::1], "
                  f"int8[::1], boolean[::1], int64[::1], float64[:, ::1], float64[:, ::1])",
    "_step_views": f"int64({_F8_4}, float64[::1], float64[:, ::1], float64[::1], "
                   f"float64[::1], float64[:, :, ::1], float64[:, ::1], float64[::1], "
                   f"float64[::1], float64[::1], float64, float64, float64[:, :, :, :, ::1], "
                   f"float64[:, ::1], float64[:, :, ::1], float64[:, ::1], int8[:, ::1], "
                   f"boolean[:, ::1], int64[:, ::1], float64[:, :, ::1], float64[:, :, ::1], "
                   f"float64[::1], int64)",
    "_carry": "void(float64[:, ::1], boolean[::1], boolean[::1], float64[:, ::1], int64[::1], "
              "int64[::1], boolean[::1])",
    "_settle": "int64(float64[:, ::1], float64[:, ::1], float64[::1], float64, float64, "
               "float64[:, ::1], float64[::1], float64[:, ::1], boolean[::1], boolean[::1], "
               "float64[:, ::1], "
               "boolean, boolean, float64, int64[::1], int64[::1], int64[::1], float64[:, ::1], "
               "float64[:, ::1], float64[::1], boolean[::1], boolean[::1], float64[::1])",
    "_settle_many": "void(int64[::1], float64[:, :, ::1], float64[:, :, ::1], float64[:, ::1], "
                    "float64[::1], float64, float64[:, :, ::1], float64[:, ::1], "
                    "float64[:, :, ::1], float64[:, :, ::1], float64[:, ::1], boolean[:, ::1], "
                    "boolean[:, ::1], boolean[:, ::1], float64[:, :, ::1], float64[:, ::1], "
                    "boolean, boolean, float64, int64[::1], int64[::1], int64[::1], int64[::1])",
    "_frame": "int64(float64[:, :], float64[:, ::1], float64[::1], boolean, int64[::1], "
              "int64[::1], int64[::1], int64[::1], int64[::1], int64[::1], float64, "
              "float64[:, ::1], float64[::1])",
    "_frame_r": "int64(float64[:, :], float64[:, ::1], float64[::1], boolean, int64[::1], "
                "int64[::1], int64[::1], int64[::1], int64[::1], int64[::1], float64, float64, "
                "float64, float64, float64, float64[:, ::1], float64[::1], float64[::1], "
                "float64[::1])",
    "_frame_r_many": "void(float64[:, :], float64[:, :, ::1], float64[:, ::1], boolean, "
                     "int64[::1], int64[::1], int64[::1], int64[::1], int64[::1], int64[::1], "
                     "float64, float64, float64, float64, float64, float64[:, :, ::1], "
                     "float64[:, ::1], float64[:, ::1], float64[:, ::1], int64[::1])",
    "_prior": "void(float64[:, :, :, :], float64[:], float64, float64[::1], float64[::1], "
              "float64[:, ::1], float64[::1])",
    "_forecast": "void(float64[:, :, :, :], float64[:], float64, float64, float64[::1], "
                 "float64[::1], float64[::1], float64[::1], float64[:, :], boolean[:], float64, "
                 "int64[:, ::1], float64[:, ::1], float64[:, ::1], float64[::1], float64[::1])",
    "_forecast_many": "void(float64[:, :, :, :, ::1], float64[:, ::1], float64[::1], float64, "
                      "float64[::1], float64[::1], float64[::1], float64[::1], float64[:, :, ::1], "
                      "boolean[:, ::1], float64, int64[:, ::1], float64[:, :, ::1], "
                      "float64[:, :, ::1], float64[:, ::1], float64[:, ::1])",
    "_consistent": "void(float64[:, :, ::1], float64[:, ::1], float64[:, ::1], float64[::1], "
                   "float64, float64, boolean[:, ::1], boolean, boolean[:, ::1])",
    "_distance": "float64(float64[:, ::1], float64[::1], float64[:, ::1], float64[:, ::1], "
                 "boolean[::1], float64, int64[::1])",
    "_offsets": "void(float64[:, ::1], float64[::1], float64[:, ::1], float64[:, ::1], "
                "boolean[::1], float64, float64[:, :, ::1], float64[::1], int64, float64, "
                "float64, float64)",
    "_gate": "void(int64[::1], float64, float64[:, :, ::1], boolean[:, ::1], float64[::1], "
             "float64[:, :, ::1], boolean[:, ::1], float64[:, ::1], int64[::1], boolean[::1], "
             "float64[:, ::1], int64, int64, int64, float64, float64, float64, boolean[:, ::1], "
             "float64[:, ::1], boolean[:, ::1], float64[::1])",
    "_gate_frames": "void(int64[::1], float64, float64[:, :, ::1], float64[:, ::1], int64[::1], "
                    "float64[:, ::1], float64[:, :, ::1], boolean[:, ::1], int64[::1], "
                    "float64[::1], float64[:, :, ::1], boolean[:, ::1], float64[:, ::1], "
                    "int64[::1], boolean[::1], float64[:, ::1], int64, int64, int64, float64, "
                    "float64, float64, boolean[:, ::1], float64[:, ::1], boolean[:, ::1], "
                    "float64[::1], float64[::1])",
    "_view_joints": "int64(int64, float64[:, ::1], float64[::1], uint8[::1], int64[::1], "
                    "uint8[::1])",
}
#: the native core's kernel (``native.NativeCore``), compiled only when a core is made
#: (``warm_native``): 6-7 s more of a first start's compilation on this VM, for engines
#: that do not use it
_NATIVE_SIGNATURES = {
    "_native_offsets": "void(int64[:, ::1], float64[:, ::1], float64[:, :, ::1], float64[:, ::1], "
                       "float64[:, ::1], float64[:, :, ::1], float64[:, :, ::1], boolean[:, ::1], "
                       "float64[:, :, :, ::1], float64, float64, float64, float64)",
    "_native_fold": "int64(int64[::1], float64[::1], float64[:, :, ::1], float64[:, ::1], "
                    "float64[:, ::1], int64[::1], int64[::1], float64[::1], float64[::1], "
                    "float64[:, :, :, :, :, ::1], float64[:, :, ::1], float64[:, :, :, ::1], "
                    "float64[:, :, ::1], float64[:, :, :, ::1], float64[:, :, ::1], "
                    "float64[:, :, ::1], boolean[:, :, ::1], boolean[:, :, ::1], "
                    "float64[:, :, ::1], int8[:, :, ::1], int64[::1], int64[::1], int64[::1], "
                    "float64[::1], "
                    "float64[::1], float64[::1], float64[::1], float64[::1], float64[::1], "
                    "float64, float64, float64, float64, float64, float64, "
                    "float64[::1], float64[::1], boolean[:, ::1], int8[:, ::1], int64[:, ::1], "
                    "float64[:, :, ::1], "
                    "float64[:, :, ::1], int64[:, ::1], float64, float64[:, :, ::1], "
                    "float64[:, ::1], float64[:, :, ::1], "
                    "float64[:, :, ::1], float64[:, ::1], boolean[:, ::1], boolean[:, ::1], "
                    "boolean[:, ::1], float64[:, :, ::1], float64[:, ::1], boolean, boolean, "
                    "int64[::1], int64[::1], int64[::1], uint8[::1], int64[::1], "
                    "uint8[::1], int64[::1], int64[::1])",
}


def _scan_sig():
    """``scan``'s signature: the datagram is a read-only view of its bytes."""
    t = numba.types
    return t.int64(t.Array(t.uint8, 1, "C", readonly=True), t.int64[:, ::1],
                   t.float64[:, :, ::1], t.float64[:, ::1])


_SCAN_HELPERS = ("_starts", "_nul", "_find", "_int", "_client", "_skeleton", "_hand")
#: ``handbank``'s kernels (the hand votes), given to ``handbank.use_kernels``
_HAND_SIGNATURES = {
    "add": "void(float64[::1], int64, int64, int64, float64, float64, float64, float64)",
    "add_frame": "void(float64[::1], int64, float64, int64, float64, int64, float64, float64, "
                 "float64)",
    "forget": "void(float64[::1], int64)",
    "update": "int64(float64[::1], float64, float64, float64, float64)",
    "vote": "Tuple((int64, float64))(float64[::1], int64, float64, float64)",
    "newest": "float64(float64[::1])",
}
#: the kernels that let the GIL go while they run: only the calibrator's jump gate. A
#: kernel on the engine's or the receiver's path (a few microseconds each, several per
#: skeleton) that let it go would hand it to the calibrator at every call and wait, on
#: its way out, for the calibrator to give it back (up to the 5 ms switch interval).
_NOGIL = frozenset({"_gate", "_gate_frames"})
_compiled: dict = {}
#: the kernels as Python functions (what numba compiles)
_PYTHON = {name: globals()[name] for name in _SIGNATURES}
_PYTHON_NATIVE = {name: globals()[name] for name in _NATIVE_SIGNATURES}
#: what the native core's kernel calls besides the kernels above
_NATIVE_HELPERS = ("_native_masked", "_native_choose", "_native_gather", "_native_start",
                   "_native_move", "_native_row", "_native_rows_back", "_native_rows_again",
                   "_native_span_step", "_native_span")
_PYTHON_HELPERS = {name: globals()[name] for name in _NATIVE_HELPERS}
#: what ``_step_rows`` and ``_native_start`` call, as Python
_ROW_PREDICTED = _row_predicted
#: what ``_prior`` and ``_forecast`` call, as Python (in order: each after what it calls)
_FORECAST_HELPERS = {"_since": _since, "_div": _div, "_imm_axis": _imm_axis,
                     "_mend_bone": _mend_bone}


def warm() -> bool:
    """Compile the kernels now (or load them from numba's cache); False, after one logged
    line, if they cannot be and the numpy code is used instead."""
    global ENABLED
    if not ENABLED:
        return False
    if _compiled:
        return True
    if not _import():
        return False
    try:
        cache = [True]
        # (compiled into the kernels that call them)
        globals()["_row_predicted"] = numba.njit()(_ROW_PREDICTED)
        for name, fn in _FORECAST_HELPERS.items():
            globals()[name] = numba.njit()(fn)
        for name, sig in _SIGNATURES.items():
            # in order: a kernel that calls another finds it compiled under its own name
            _compiled[name] = globals()[name] = _njit(_PYTHON[name], sig, cache,
                                                      name in _NOGIL)
        _compiled["scan"] = _njit(_with_helpers(scan, "scan", _SCAN_HELPERS), _scan_sig(),
                                  cache, False)
        protocol.use_scanner(_compiled["scan"])
        hands = {name: _njit(_with_helpers(handbank, name, handbank.HELPERS), sig, cache, False)
                 for name, sig in _HAND_SIGNATURES.items()}
        _compiled["hands"] = hands
        handbank.use_kernels(hands)
    except Exception as exc:  # a numba that cannot compile here must not stop a show
        ENABLED = False
        _compiled.clear()
        protocol.use_scanner(None)
        handbank.use_kernels(None)
        log.warning("compiled kernels unavailable (%s: %s); the engine runs its numpy code",
                    type(exc).__name__, str(exc).splitlines()[0] if str(exc) else "")
        return False
    return True


def warm_native() -> bool:
    """Compile the native core's kernel now (after ``warm``); False if it cannot be."""
    if not warm():
        return False
    if "_native_fold" in _compiled:
        return True
    try:
        for name in _NATIVE_HELPERS:       # (compiled into the kernel that calls them)
            globals()[name] = numba.njit()(_PYTHON_HELPERS[name])
        for name, sig in _NATIVE_SIGNATURES.items():
            _compiled[name] = globals()[name] = _njit(_PYTHON_NATIVE[name], sig, [True], False)
    except Exception as exc:  # as in warm: logged, and the caller runs without it
        log.warning("the native core's kernel is unavailable (%s: %s)", type(exc).__name__,
                    str(exc).splitlines()[0] if str(exc) else "")
        return False
    return True


def ready() -> bool:
    """Whether the kernels are compiled and used: compiled on first use if need be (the
    engine compiles them when it is built, so a show never pays it mid-way)."""
    return bool(_compiled) or (ENABLED and warm())


@contextlib.contextmanager
def disabled():
    """The numpy code only, within the block (tests of the reference code)."""
    global ENABLED
    saved, kernels = ENABLED, dict(_compiled)
    ENABLED = False
    _compiled.clear()
    protocol.use_scanner(None)
    handbank.use_kernels(None)
    try:
        yield
    finally:
        ENABLED = saved
        _compiled.update(kernels)
        protocol.use_scanner(kernels.get("scan"))
        handbank.use_kernels(kernels.get("hands"))


def why_not() -> str:
    """Why the kernels are not used ('' when they are)."""
    return "" if ENABLED else (_WHY_NOT or "compilation failed (logged)")


_EMPTY = np.empty(0)
_FLAT: dict[int, tuple] = {}
#: ``frame_r``'s constants of each smoothing settings object
_FRAME_R: dict[int, tuple] = {}


def _per_settings(cache: dict[int, tuple], s: KalmanSettings, make) -> tuple:
    """``make(s)``, a tuple, computed once per settings object (kept by its identity, as
    ``imm._constants`` keeps its own; at most 64 kept)."""
    entry = cache.get(id(s))
    if entry is None or entry[0] is not s:
        if len(cache) > 64:
            cache.clear()
        entry = cache[id(s)] = (s, *make(s))
    return entry


def _flat(s: KalmanSettings) -> tuple[np.ndarray, np.ndarray]:
    """``imm._constants`` as the kernel takes them: writable (2,) arrays (a read-only array is
    another type to numba)."""
    _, q, rates = _per_settings(_FLAT, s, _flat_constants)
    return q, rates


def _flat_constants(s: KalmanSettings) -> tuple[np.ndarray, np.ndarray]:
    q, rates = _constants(s)
    return np.array(q.ravel()), np.array(rates.ravel())


def _frame_constants(s: KalmanSettings) -> tuple[float, float, float]:
    return math.sqrt(s.measurement_noise), float(s.noise_per_m), float(s.inferred_sd_m ** 2)


def step_rows(S: np.ndarray, st: np.ndarray, held_z: np.ndarray, held_t: np.ndarray,
              t: np.ndarray, z: np.ndarray, r: np.ndarray, s: KalmanSettings,
              q_scale: np.ndarray | None) -> tuple[np.ndarray, ...]:
    """The compiled ``_step_rows`` (see there): (new block (6, 2, N, 3), its t (N,), held_z
    (N, 3), held_t (N,), outcome (N,) int8, used (N,) bool, counts [rows to restart, rows
    to start, rows downweighted, rows rejected and held], position and velocity (N, 3) at
    t). ``warm()`` must have succeeded; ``kalman.step`` is the way to call it."""
    q, rates = _flat(s)
    n = len(st)
    out = np.empty((6, 2, n, 3))
    out_t = np.empty(n)
    out_held_z = np.empty((n, 3))
    out_held_t = np.empty(n)
    outcome = np.empty(n, dtype=np.int8)
    used = np.empty(n, dtype=np.bool_)
    counts = np.empty(4, dtype=np.int64)
    pos, vel = np.empty((n, 3)), np.empty((n, 3))
    qs = _EMPTY if q_scale is None else np.ascontiguousarray(q_scale, dtype=float)
    _compiled["_step_rows"](np.ascontiguousarray(S), np.ascontiguousarray(st),
                            np.ascontiguousarray(held_z), np.ascontiguousarray(held_t), t, z, r,
                            q, qs, rates, float(s.gate_sigma ** 2), float(s.reject_sigma ** 2),
                            out, out_t, out_held_z, out_held_t, outcome, used, counts, pos, vel)
    return out, out_t, out_held_z, out_held_t, outcome, used, counts, pos, vel


class Views:
    """What ``step_views`` writes: for each of G measurement sets of N rows, the state after
    it and its outcome, used, counts, pos and vel (the arrays of ``_step_views``)."""

    __slots__ = ("block", "t", "held_z", "held_t", "outcome", "used", "counts", "pos", "vel")

    def __init__(self, G: int, n: int) -> None:
        self.block, self.t = np.empty((G, 6, 2, n, 3)), np.empty((G, n))
        self.held_z, self.held_t = np.empty((G, n, 3)), np.empty((G, n))
        self.outcome, self.used = np.empty((G, n), dtype=np.int8), np.empty((G, n), dtype=np.bool_)
        self.counts = np.empty((G, 4), dtype=np.int64)
        self.pos, self.vel = np.empty((G, n, 3)), np.empty((G, n, 3))


def step_views(S: np.ndarray, st: np.ndarray, held_z: np.ndarray, held_t: np.ndarray,
               t: np.ndarray, z: np.ndarray, r: np.ndarray, s: KalmanSettings,
               q_scale: np.ndarray | None, into: Views, start: int) -> int:
    """The compiled ``_step_views`` (see there) from set ``start`` on, into ``into``: G, or the
    set after which rows are to restart or start. ``kalman.step_views`` is the way to
    call it."""
    q, rates = _flat(s)
    qs = _EMPTY if q_scale is None else np.ascontiguousarray(q_scale, dtype=float)
    return _compiled["_step_views"](
        np.ascontiguousarray(S), np.ascontiguousarray(st), np.ascontiguousarray(held_z),
        np.ascontiguousarray(held_t), t, z, r, q, qs, rates, float(s.gate_sigma ** 2),
        float(s.reject_sigma ** 2), into.block, into.t, into.held_z, into.held_t, into.outcome,
        into.used, into.counts, into.pos, into.vel, np.empty(len(st)), int(start))


def settle(pos: np.ndarray, vel: np.ndarray, row_t: np.ndarray, t: float, stale: float,
           recent_conf: np.ndarray, recent_t: np.ndarray, prev: np.ndarray,
           known: np.ndarray, tracked: np.ndarray,
           hold: np.ndarray, carry_on: bool, hold_back: bool, inferred: float,
           parents: np.ndarray, children: np.ndarray, torso: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                      np.ndarray | None]:
    """The compiled ``_settle`` (see there) for one person on arrays of its own: new arrays
    (joints, velocity, conf, known, carried, centre or None when no torso joint is known);
    ``tracked`` and ``hold`` (C-contiguous) are updated in place. The engine settles a
    batch on the person bank (``settle_many``); this is the one-person reference that
    tests/test_person_bank.py holds the batch kernel to."""
    n = len(pos)
    joints, velocity = np.empty((n, 3)), np.empty((n, 3))
    conf_out, known_out = np.empty(n), np.empty(n, dtype=bool)
    carried, centre = np.zeros(n, dtype=bool), np.empty(3)
    f = np.ascontiguousarray
    count = _compiled["_settle"](
        f(pos, dtype=float), f(vel, dtype=float), f(row_t, dtype=float), float(t), float(stale),
        recent_conf, recent_t, f(prev, dtype=float), known, tracked, hold, bool(carry_on),
        bool(hold_back), float(inferred), parents, children, torso, joints, velocity,
        conf_out, known_out, carried, centre)
    return joints, velocity, conf_out, known_out, carried, (centre if count else None)


def settle_many(slots: np.ndarray, pos: np.ndarray, vel: np.ndarray, row_t: np.ndarray,
                t: np.ndarray, stale: float, bank, carry_on: bool, hold_back: bool,
                inferred: float, parents: np.ndarray, children: np.ndarray, torso: np.ndarray
                ) -> np.ndarray:
    """The compiled ``_settle_many`` (see there) over the persons in ``slots`` of ``bank``
    (``bank.PersonBank``), whose rows it updates; returns the counts (P,) of torso joints
    known (0: the caller finds the centre otherwise). A TypeError if an array is not one the
    kernel takes."""
    counts = np.empty(len(slots), dtype=np.int64)
    _compiled["_settle_many"](
        slots, pos, vel, row_t, t, float(stale), bank.recent_conf, bank.recent_t, bank.joints,
        bank.velocity, bank.conf, bank.known, bank.carried, bank.tracked, bank.hold,
        bank.centre, bool(carry_on), bool(hold_back), float(inferred), parents, children, torso,
        counts)
    return counts


def frame_r(matrix: np.ndarray, joints: np.ndarray, conf: np.ndarray, unswap: bool,
            look: tuple, traded: tuple, margin: float, s: KalmanSettings, inferred: float
            ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, float, int]:
    """The compiled ``_frame_r``: a frame's (stage-space joints, conf, traded bits), its
    joints' measurement variances (25,) under the smoothing settings ``s`` (NaN: not seen),
    new arrays, its trunk length (``tracking.body_size``, the same float; NaN for its
    None) and how many joints it sees (confidence above 0: ``np.count_nonzero(conf > 0)``,
    which the caller then need not compute). ``look`` and ``traded`` are ``fusion``'s index
    arrays (left, right; (arm, leg))."""
    n = len(conf)
    joints_out, conf_out, r_out = np.empty((n, 3)), np.empty(n), np.empty(n)
    size = np.empty(2)
    const = _per_settings(_FRAME_R, s, _frame_constants)
    f = np.ascontiguousarray
    (arm_l, arm_r), (leg_l, leg_r) = traded
    bits = _compiled["_frame_r"](np.asarray(matrix, dtype=float), f(joints, dtype=float),
                                 f(conf, dtype=float), bool(unswap), look[0], look[1], arm_l,
                                 arm_r, leg_l, leg_r, float(margin), const[1], const[2],
                                 float(inferred), const[3], joints_out, conf_out, r_out, size)
    return joints_out, conf_out, bits, r_out, float(size[0]), int(size[1])


def frame_r_many(matrix: np.ndarray, joints: np.ndarray, conf: np.ndarray, unswap: bool,
                 look: tuple, traded: tuple, margin: float, s: KalmanSettings, inferred: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The compiled ``_frame_r_many``: ``frame_r`` of K frames of one sensor, ``joints``
    (K, 25, 3) and ``conf`` (K, 25), in one call: (stage-space joints (K, 25, 3), conf
    (K, 25), traded bits (K,), variances (K, 25), (K, 2) [trunk length, joints seen]),
    new arrays; row k is what ``frame_r`` gives for frame k."""
    n = len(joints)
    joints_out, conf_out = np.empty((n, 25, 3)), np.empty((n, 25))
    r_out, size, bits = np.empty((n, 25)), np.empty((n, 2)), np.empty(n, dtype=np.int64)
    const = _per_settings(_FRAME_R, s, _frame_constants)
    (arm_l, arm_r), (leg_l, leg_r) = traded
    _compiled["_frame_r_many"](np.asarray(matrix, dtype=float), joints, conf, bool(unswap),
                               look[0], look[1], arm_l, arm_r, leg_l, leg_r, float(margin),
                               const[1], const[2], float(inferred), const[3], joints_out,
                               conf_out, r_out, size, bits)
    return joints_out, conf_out, bits, r_out, size


def distance(joints: np.ndarray, conf: np.ndarray, person_joints: np.ndarray,
             velocity: np.ndarray, known: np.ndarray, dt: float, torso: np.ndarray) -> float | None:
    """The compiled ``_distance``: mean distance (m), None where nothing is shared."""
    d = _compiled["_distance"](joints, conf, person_joints, velocity, known, float(dt), torso)
    return None if d != d else d


def offsets(z: np.ndarray, conf: np.ndarray, joints: np.ndarray, velocity: np.ndarray,
            known: np.ndarray, dt: float, offsets: np.ndarray, live: np.ndarray, row: int,
            alpha: float, tracked: float) -> None:
    """The compiled ``_offsets``: ``offsets.learn``, in place."""
    _compiled["_offsets"](z, conf, joints, velocity, known, float(dt), offsets, live, int(row),
                          float(alpha), float(tracked), _OFFSET_CAP2)


def prior(S: np.ndarray, st: np.ndarray, t: float, s: KalmanSettings
          ) -> tuple[np.ndarray, np.ndarray]:
    """The compiled ``_prior``: ((N, 3) mean, (N,) variance), as ``fuser.prior_of``."""
    q, rates = _flat(s)
    n = st.shape[0]
    mean, var = np.empty((n, 3)), np.empty(n)
    _compiled["_prior"](S, st, float(t), q, rates, mean, var)
    return mean, var


def forecast(S: np.ndarray, st: np.ndarray, target: float, horizon: float, q: np.ndarray,
             rates: np.ndarray, memory: np.ndarray, limits: np.ndarray, joints: np.ndarray,
             seen: np.ndarray, tol: float, bones: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The compiled ``_forecast``: (joints (N, 3), velocity (N, 3), s.d. (N,), counts (4,))
    of one body predicted to ``target``, as ``forecast.Forecaster.predict``."""
    n = st.shape[0]
    out, vel, sd, counts = np.empty((n, 3)), np.empty((n, 3)), np.empty(n), np.empty(4)
    _compiled["_forecast"](S, st, float(target), float(horizon), q, rates, memory, limits,
                           joints, seen, float(tol), bones, out, vel, sd, counts)
    return out, vel, sd, counts


def forecast_many(S: np.ndarray, st: np.ndarray, target: np.ndarray, horizon: float,
                  q: np.ndarray, rates: np.ndarray, memory: np.ndarray, limits: np.ndarray,
                  joints: np.ndarray, seen: np.ndarray, tol: float, bones: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The compiled ``_forecast_many``: ``forecast`` of B bodies at once, S (B, 6, 2, N, 3),
    st (B, N), target (B,), joints (B, N, 3), seen (B, N); (out (B, N, 3), vel (B, N, 3),
    s.d. (B, N), counts (B, 4)), each body's the floats ``forecast`` gives it."""
    b, n = st.shape
    out, vel, sd, counts = (np.empty((b, n, 3)), np.empty((b, n, 3)), np.empty((b, n)),
                            np.empty((b, 4)))
    _compiled["_forecast_many"](S, st, target, float(horizon), q, rates, memory, limits,
                                joints, seen, float(tol), bones, out, vel, sd, counts)
    return out, vel, sd, counts


def consistent(z: np.ndarray, r: np.ndarray, prior: np.ndarray, prior_var: np.ndarray,
               bias_var: float, chi2: float, tracked: np.ndarray | None) -> np.ndarray:
    """The compiled ``_consistent``: (G, J) bool, as ``fusion.consistent_views`` (G >= 2).
    TypeError for arrays the kernel does not take, shapes that do not match included (it
    reads without bounds checks; numpy would broadcast or raise)."""
    G, J = r.shape if r.ndim == 2 else (-1, -1)
    if (z.shape != (G, J, 3) or np.shape(prior) != (J, 3) or np.shape(prior_var) != (J,)
            or (tracked is not None and np.shape(tracked) != (G, J))):
        raise TypeError("consistent: shapes do not match")
    used = np.empty(r.shape, dtype=np.bool_)
    _compiled["_consistent"](z, r, prior, prior_var, float(bias_var), float(chi2),
                             _NO_TRACKED if tracked is None else tracked, tracked is not None,
                             used)
    return used


_NO_TRACKED = np.zeros((1, 1), dtype=np.bool_)


def gate(rows: np.ndarray, t: float, points: np.ndarray, tracked: np.ndarray, T: np.ndarray,
         X: np.ndarray, Mk: np.ndarray, V: np.ndarray, owner: np.ndarray, trusted: np.ndarray,
         links: np.ndarray, own: int, n: int, min_joints: int, agree_m: float, gate_m: float,
         link_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The compiled ``_gate``: (jumped (k, n) bool, the largest distance per view, the
    distances (k, n): inf where the two views were not compared); the
    gate's arrays updated in place. Runs without the GIL (the calibrator's worker thread
    then leaves the engine thread its core)."""
    k = len(rows)
    valid, jumped = np.empty((k, n), dtype=bool), np.empty((k, n), dtype=bool)
    d, dmax = np.empty((k, n)), np.empty(k)
    _compiled["_gate"](rows, float(t), np.ascontiguousarray(points, dtype=float),
                       np.ascontiguousarray(tracked, dtype=bool), T, X, Mk, V, owner, trusted,
                       links, int(own), int(n), int(min_joints), float(agree_m), float(gate_m),
                       float(link_s), valid, d, jumped, dmax)
    return jumped, dmax, d


def gate_frames(rows: np.ndarray, t: float, joints: np.ndarray, conf: np.ndarray,
                torso: np.ndarray, matrix: np.ndarray, scratch: tuple, T: np.ndarray,
                X: np.ndarray, Mk: np.ndarray, V: np.ndarray, owner: np.ndarray,
                trusted: np.ndarray, links: np.ndarray, own: int, n: int, min_joints: int,
                agree_m: float, gate_m: float, link_s: float) -> None:
    """The compiled ``_gate_frames``: one datagram's skeletons (joints (k, J, 3), conf (k,
    J), C-contiguous float64) judged by the gate without the GIL; ``scratch`` (points,
    tracked, keep, valid, d, jumped, dmax, found) holds what it writes, each at least k
    rows (n columns), found (3,) float64 (see ``_gate_frames``)."""
    points, tracked, keep, valid, d, jumped, dmax, found = scratch
    _compiled["_gate_frames"](rows, float(t), joints, conf, torso, matrix, points, tracked,
                              keep, T, X, Mk, V, owner, trusted, links, int(own), int(n),
                              int(min_joints), float(agree_m), float(gate_m), float(link_s),
                              valid, d, jumped, dmax, found)


def carry(joints: np.ndarray, reported: np.ndarray, tracked: np.ndarray, offsets: np.ndarray,
          parents: np.ndarray, children: np.ndarray) -> np.ndarray:
    """The compiled ``fusion.carry_untracked`` (in place on C-contiguous float64 ``joints``
    and ``offsets``); returns the (25,) bool joints carried."""
    carried = np.empty(len(joints), dtype=bool)
    _compiled["_carry"](joints, reported, tracked, offsets, parents, children, carried)
    return carried


def _names() -> tuple[np.ndarray, np.ndarray, int]:
    """The joint names as ``_view_joints`` takes them (the encoder's, padded), and the
    longest message it writes."""
    padded = _NAME_BYTES
    ends = np.cumsum([len(p) for p in padded]).astype(np.int64)
    tags = 2 + 5 * len(JOINTS) + 1
    longest = 20 + tags + (-tags) % 4 + 4 + int(ends[-1]) + 16 * len(JOINTS)
    return np.frombuffer(b"".join(padded), dtype=np.uint8).copy(), ends, longest


_NAMES, _NAME_END, _LONGEST = _names()


def view_joints(user: int, joints: np.ndarray, conf: np.ndarray) -> bytes:
    """The compiled ``sensors.encode.encode_view_joints`` (joints where ``conf`` > 0): the
    same bytes, in one call instead of a dozen numpy operations."""
    out = np.empty(_LONGEST, dtype=np.uint8)
    n = _compiled["_view_joints"](int(user), np.ascontiguousarray(joints, dtype=float),
                                  np.ascontiguousarray(conf, dtype=float), _NAMES, _NAME_END,
                                  out)
    return out[:n].tobytes()


def _njit(fn, sig, cache: list[bool], nogil: bool):
    """``fn`` compiled for ``sig``, cached on disk while ``cache[0]``; where numba finds no
    writable place for its cache (a read-only install, a service user without a home),
    one warning, and this and every later kernel are compiled at every start instead
    (docs/installing.md)."""
    if cache[0]:
        try:
            return numba.njit(sig, cache=True, nogil=nogil)(fn)
        except RuntimeError as exc:
            if "cannot cache" not in str(exc):
                raise
            log.warning("compiled kernels: no disk cache (%s); compiling at every start "
                        "(set NUMBA_CACHE_DIR to a writable folder)", str(exc).splitlines()[0])
            cache[0] = False
    return numba.njit(sig, cache=False, nogil=nogil)(fn)


def _with_helpers(module, entry: str, helpers: tuple[str, ...]):
    """``module.entry`` to compile, with the module's ``helpers`` it calls compiled: each a
    copy of the function bound to a copy of the module's globals, so the module itself
    stays plain Python (it imports no compiler and runs uncompiled in its tests). The
    helpers are compiled into the entry, so they need no disk cache of their own."""
    ns = dict(vars(module))

    def copy(name):
        fn = ns[name]
        return types.FunctionType(fn.__code__, ns, name, fn.__defaults__)

    for name in helpers:
        ns[name] = numba.njit()(copy(name))
    return copy(entry)
