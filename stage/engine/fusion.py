"""Pure fusion maths: sensor views into stage space, their noise, which views agree.

Everything here is a function of numpy arrays in stage space; the engine
decides which views belong together and when (``tracking``), and folds them
into each person's filter (``fuser``).
"""

from __future__ import annotations

import math

import numpy as np

from ..joints import JOINT_INDEX, TORSO
from . import jit


def consistent_views(z: np.ndarray, r: np.ndarray, prior: np.ndarray, prior_var: np.ndarray,
                     bias_var: float, chi2: float, tracked: np.ndarray | None = None,
                     ) -> np.ndarray:
    """Which of G views of one instant to use, joint by joint: the largest set that agrees.

    z: (G, J, 3) metres, stage space; r: (G, J) per-axis variance, NaN or inf where the
    view does not see the joint; prior: (J, 3) the filter's prediction for the instant
    (NaN where it has none); prior_var: (J,) its per-axis variance; bias_var: m^2, each
    view's systematic error (calibration, the sensor's fit) that does not average out;
    chi2: the squared Mahalanobis distance two views may be apart and still agree.

    Two views agree on a joint when |z_u - z_v|^2 / (r_u + r_v + 2 bias_var) <= chi2;
    a view agrees with the prior likewise. For each joint the view with the most
    agreement wins -- every agreeing view is a vote, the prior half a vote (it breaks a
    tie between two views, but two views outvote it), remaining ties go to the more
    certain side -- and the views that agree with it are used. A joint seen by one view
    only is always used (the filter's gate judges it). ``tracked`` (G, J) bool, optional:
    the views that track each joint (confidence above the inferred level); where any view tracks a joint, only a
    tracking view can win it, so views that merely infer it (guesses, and a prior that
    was fed them) never outvote a view that sees it. Returns used: (G, J) bool.
    """
    z = np.asarray(z, dtype=float)
    r = np.asarray(r, dtype=float)
    G = z.shape[0]
    if G > 1 and jit.ready():
        try:     # the same masks (tests/test_jit.py), about a tenth of the numpy code's time
            return jit.consistent(z, r, prior, prior_var, bias_var, chi2, tracked)
        except TypeError:    # arrays the kernel does not take (a caller's own): numpy
            pass
    seen = np.isfinite(r) & (r > 0)
    if G == 1:
        return seen.copy()
    rs = np.where(seen, r, np.inf)
    diff = z[:, None] - z[None]                                   # (G, G, J, 3)
    d2 = (diff * diff).sum(axis=-1) / (rs[:, None] + rs[None] + 2.0 * bias_var)
    agree = (d2 <= chi2) & seen[:, None] & seen[None]             # (G, G, J), diagonal = seen
    dp = z - prior[None]
    dp2 = (dp * dp).sum(axis=-1) / (rs + np.asarray(prior_var)[None] + bias_var)
    with_prior = (dp2 <= chi2) & seen                             # NaN prior: never
    info = np.where(seen, 1.0 / rs, 0.0)
    votes = agree.sum(axis=1) + 0.5 * with_prior                  # (G, J)
    # tie-break by the information of the agreeing views, scaled under half a vote
    support = (agree * info[None]).sum(axis=1)
    votes = votes + 0.25 * support / np.maximum(support.max(axis=0), 1e-300)[None]
    if tracked is not None:
        guess = seen & ~tracked & (seen & tracked).any(axis=0)[None]
        votes = np.where(guess, -0.5, votes)
    votes = np.where(seen, votes, -1.0)
    best = np.argmax(votes, axis=0)                               # (J,)
    used = agree[best, :, np.arange(z.shape[1])].T               # (G, J)
    return used | (seen & (seen.sum(axis=0) == 1)[None])


def torso_centre(joints: np.ndarray, conf: np.ndarray) -> np.ndarray | None:
    """Mean of the tracked torso joints (3,), or of all tracked joints; None if none."""
    mask = conf[list(TORSO)] > 0
    if mask.any():
        return joints[list(TORSO)][mask].mean(axis=0)
    mask = conf > 0
    if mask.any():
        return joints[mask].mean(axis=0)
    return None


def apply_transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 homogeneous transform to (..., 3) points."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def _side(names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    return (np.array([JOINT_INDEX[n + "Left"] for n in names]),
            np.array([JOINT_INDEX[n + "Right"] for n in names]))


#: left and right joints looked at, in pairs: the girdles (shoulders, hips) whose left-right
#: axes say which side of the body is which, then each limb's check joints (elbow and wrist;
#: knee and ankle), which must both lie on the wrong side for the limb to count as swapped
_LOOK_L, _LOOK_R = _side(("Shoulder", "Hip", "Elbow", "Wrist", "Knee", "Ankle"))
_LOOK = np.array([_LOOK_L, _LOOK_R])                  # (2, 6): one fancy index for both sides
#: the joints traded back per limb (arm, leg)
_TRADED = (_side(("Elbow", "Wrist", "Hand", "HandTip", "Thumb")), _side(("Knee", "Ankle", "Foot")))
#: ``unswap_limbs``'s bit mask: the arms were traded, the legs were
ARM_TRADED, LEG_TRADED = 1, 2
#: how far (m, along the body's left-right axis) a limb's joints must lie on the wrong side
SWAP_MARGIN_M = 0.03


def unswap_limbs(joints: np.ndarray, conf: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """A sensor's left and right arm (or leg) traded back when the sensor swapped them.

    joints (25, 3), conf (25,) of one view. Each limb is judged along the left-right axis
    of its own girdle (arms: the shoulders; legs: the hips), or of the other girdle when
    its own is not tracked; a twisted torso over a lunge would otherwise make a correct
    pair of legs look crossed along the shoulders' axis. A limb counts as swapped when
    BOTH its check joints (elbow and wrist; knee and ankle) of the left side lie at least
    ``SWAP_MARGIN_M`` right of the right side's along that axis: depth cameras mix up a
    left and a right limb that overlap in their image (real Kinects do, and the
    simulator's model), and when two of three sensors do it at once the consistency vote
    follows them (legs 20 cm off). Crossed arms cross the wrists but not the elbows, and
    crossed legs the ankles but rarely the knees, so they are left alone; a leg crossed
    fully behind the other (a curtsy) is traded all the same (docs/smoothing.md).
    Returns (joints, conf, traded): ``traded`` is a bit mask, ``ARM_TRADED`` (1) and
    ``LEG_TRADED`` (2), 0 when nothing was; the arrays are new only when something was
    traded.
    """
    # a dozen numbers: read into Python once (small numpy operations cost more than these)
    cl, cr = conf[_LOOK].tolist()
    c = [a if a < b else b for a, b in zip(cl, cr)]       # (6,) per pair: both seen?
    if c[0] < 1.0 and c[1] < 1.0:                         # no girdle tracked
        return joints, conf, 0
    pl, pr = joints[_LOOK].tolist()
    diff = [(a[0] - b[0], a[1] - b[1], a[2] - b[2]) for a, b in zip(pl, pr)]  # left - right
    traded = 0
    for k, (tl, tr) in enumerate(_TRADED):                # arm (shoulders), leg (hips)
        if not (c[2 + 2 * k] > 0 and c[3 + 2 * k] > 0):
            continue
        girdle = k if c[k] >= 1.0 else 1 - k
        ax, ay, az = diff[girdle]
        size = math.sqrt(ax * ax + ay * ay + az * az)
        if size < 0.05:                                   # shoulders or hips on one point
            continue
        # elbow, wrist or knee, ankle along the girdle's axis
        across = [(x * ax + y * ay + z * az) / size for x, y, z in diff[2 + 2 * k: 4 + 2 * k]]
        if across[0] < -SWAP_MARGIN_M and across[1] < -SWAP_MARGIN_M:
            if not traded:
                joints, conf = joints.copy(), conf.copy()
            joints[tl], joints[tr] = joints[tr], joints[tl]
            conf[tl], conf[tr] = conf[tr], conf[tl]
            traded |= 1 << k
    return joints, conf, traded


def _levels() -> list[tuple[np.ndarray, np.ndarray]]:
    """``BONES`` grouped by depth in the joint tree: [(parents, children)], root first."""
    from .forecast import BONES
    depth = {BONES[0][0]: 0}
    for a, b in BONES:
        depth[b] = depth[a] + 1
    out = []
    for d in range(1, max(depth.values()) + 1):
        pairs = [(a, b) for a, b in BONES if depth[b] == d]
        out.append((np.array([a for a, _ in pairs]), np.array([b for _, b in pairs])))
    return out


_LEVELS = _levels()
_PARENTS = np.concatenate([a for a, _ in _LEVELS])
_CHILDREN = np.concatenate([b for _, b in _LEVELS])


def carry_untracked(joints: np.ndarray, reported: np.ndarray, tracked: np.ndarray,
                    offsets: np.ndarray) -> np.ndarray:
    """``carry_untracked_numpy`` (below), compiled (``jit``) where the arrays allow."""
    if (jit.ready() and joints.dtype == np.float64 and offsets.dtype == np.float64
            and joints.flags.c_contiguous and offsets.flags.c_contiguous
            and reported.dtype == np.bool_ and tracked.dtype == np.bool_):
        return jit.carry(joints, np.ascontiguousarray(reported), np.ascontiguousarray(tracked),
                         offsets, _PARENTS, _CHILDREN)
    return carry_untracked_numpy(joints, reported, tracked, offsets)


def carry_untracked_numpy(joints: np.ndarray, reported: np.ndarray, tracked: np.ndarray,
                          offsets: np.ndarray) -> np.ndarray:
    """Joints that no sensor tracks now, carried by their parent joint (in place).

    joints (25, 3) m, a fused body; reported (25,) bool, the joints it reports; tracked
    (25,) bool, those some sensor tracks now (confidence above the inferred level); offsets (25, 3) each joint's
    offset from its parent (``forecast.BONES``) the last time it was tracked, NaN before
    that: updated in place for tracked joints whose parent is reported. A reported joint
    that is not tracked (every sensor only infers it: a guess 10-30 cm off, and the filter
    fed by guesses drifts with the velocity it had) is placed at its parent plus that
    offset, parents first, so a hidden wrist and hand follow the elbow as they were last
    seen. Returns (25,) bool: the joints so placed.
    """
    carried = np.zeros(len(joints), dtype=bool)
    both = reported[_CHILDREN] & reported[_PARENTS]
    move = both & ~tracked[_CHILDREN] & ~np.isnan(offsets[_CHILDREN, 0])
    # children in tree order, so a parent is placed before its children (a few joints)
    for child, parent in zip(_CHILDREN[move].tolist(), _PARENTS[move].tolist()):
        joints[child] = joints[parent] + offsets[child]
        carried[child] = True
    keep = both & tracked[_CHILDREN]
    offsets[_CHILDREN[keep]] = joints[_CHILDREN[keep]] - joints[_PARENTS[keep]]
    return carried
