"""Hand states from MediaPipe's 21 hand landmarks, as the Kinect v2 defines them.

The Kinect SDK reports a hand as ``open`` (fingers extended), ``closed`` (a
fist) or ``lasso`` (index and middle finger extended, the others folded, like
a pair of scissors held closed), and ``unknown`` when it cannot tell. Here
each finger's straightness is measured on MediaPipe's hand world landmarks
(metres, so the hand's size and distance do not matter): the straight-line
distance from the knuckle (MCP) to the fingertip over the length of the
finger's three segments, 1.0 for a straight finger, about 0.4 for one curled
into a fist. The thumb is left out, as the Kinect leaves it out: a fist with
the thumb out is still closed, an open hand with the thumb tucked still open.

Confidence: how clearly every finger is on its side of the extended/folded
boundary (0 at the boundary, 1 well past it), times MediaPipe's own hand
presence score. A hand whose state is less certain than ``min_confidence``
is reported ``unknown``: the Kinect does the same rather than guess.

Hands are given to bodies by distance: each detected hand's wrist goes to the
nearest pose wrist (in the image) that is close enough and not yet taken.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...joints import HandState

#: landmark indices of (MCP, PIP, DIP, TIP) for index, middle, ring and pinky
FINGERS = {"index": (5, 6, 7, 8), "middle": (9, 10, 11, 12), "ring": (13, 14, 15, 16),
           "pinky": (17, 18, 19, 20)}
WRIST = 0
N_HAND_LANDMARKS = 21
#: straightness above which a finger is extended, below which it is folded; between
#: them the finger is ambiguous and the hand's confidence falls towards 0
EXTENDED = 0.9
FOLDED = 0.7


def straightness(landmarks: np.ndarray) -> dict[str, float]:
    """Per finger (index, middle, ring, pinky): |tip - MCP| / finger length, 0-1."""
    lm = np.asarray(landmarks, float).reshape(N_HAND_LANDMARKS, 3)
    out = {}
    for name, (mcp, pip, dip, tip) in FINGERS.items():
        length = (np.linalg.norm(lm[pip] - lm[mcp]) + np.linalg.norm(lm[dip] - lm[pip])
                  + np.linalg.norm(lm[tip] - lm[dip]))
        out[name] = float(np.linalg.norm(lm[tip] - lm[mcp]) / length) if length > 1e-9 else 0.0
    return out


def _extended_score(s: float) -> float:
    """-1 clearly folded ... 0 ambiguous ... +1 clearly extended."""
    mid, half = (EXTENDED + FOLDED) / 2, (EXTENDED - FOLDED) / 2
    return float(np.clip((s - mid) / half, -1.0, 1.0))


#: each state's pattern over (index, middle, ring, pinky): +1 extended, -1 folded
_PATTERNS = {HandState.OPEN: (1, 1, 1, 1), HandState.CLOSED: (-1, -1, -1, -1),
             HandState.LASSO: (1, 1, -1, -1)}


def classify(landmarks: np.ndarray, presence: float = 1.0, min_confidence: float = 0.5,
             ) -> tuple[HandState, float]:
    """One hand's 21 world landmarks (metres) -> (state, confidence 0-1).

    The state is the Kinect pattern the fingers match best; the confidence
    is the weakest finger's agreement with it times ``presence``. Below
    ``min_confidence`` the state is ``unknown`` (the confidence is still given).
    """
    scores = [_extended_score(s) for s in straightness(landmarks).values()]
    best, best_conf = HandState.UNKNOWN, 0.0
    for state, pattern in _PATTERNS.items():
        agreement = min(p * s for p, s in zip(pattern, scores))
        if agreement > best_conf:
            best, best_conf = state, agreement
    conf = float(best_conf * np.clip(presence, 0.0, 1.0))
    return (best if conf >= min_confidence else HandState.UNKNOWN), conf


@dataclass
class Hand:
    """One detected hand: wrist in normalised image coordinates, its state and confidence."""

    wrist_image: np.ndarray     # (2,) x, y in 0-1
    state: HandState
    confidence: float


def assign_hands(wrists: np.ndarray, hands: list[Hand], max_distance: np.ndarray | float
                 ) -> list[Hand | None]:
    """Give each pose wrist at most one detected hand, nearest first.

    wrists: (W, 2) pose wrists in normalised image coordinates (NaN where the
    pose does not see it); max_distance: (W,) or scalar, the farthest a hand's
    own wrist may be from the pose wrist (normalised units). Returns one entry
    per pose wrist: the hand given to it, or None.
    """
    wrists = np.asarray(wrists, float).reshape(-1, 2)
    limit = np.broadcast_to(np.asarray(max_distance, float), (len(wrists),))
    pairs = []
    for w, wrist in enumerate(wrists):
        if not np.isfinite(wrist).all():
            continue
        for h, hand in enumerate(hands):
            d = float(np.linalg.norm(hand.wrist_image[:2] - wrist))
            if d <= limit[w]:
                pairs.append((d, w, h))
    out: list[Hand | None] = [None] * len(wrists)
    used: set[int] = set()
    for _, w, h in sorted(pairs):
        if out[w] is None and h not in used:
            out[w] = hands[h]
            used.add(h)
    return out
