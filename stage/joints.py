"""The skeleton contract: the 25 Kinect v2 joints and the hand states.

Every source is mapped onto these names and this order (Kinect v2
``JointType``: ``SpineBase`` = 0 ... ``ThumbRight`` = 24).
"""

from __future__ import annotations

import difflib
from enum import IntEnum

JOINTS: tuple[str, ...] = (
    "SpineBase", "SpineMid", "Neck", "Head",
    "ShoulderLeft", "ElbowLeft", "WristLeft", "HandLeft",
    "ShoulderRight", "ElbowRight", "WristRight", "HandRight",
    "HipLeft", "KneeLeft", "AnkleLeft", "FootLeft",
    "HipRight", "KneeRight", "AnkleRight", "FootRight",
    "SpineShoulder", "HandTipLeft", "ThumbLeft", "HandTipRight", "ThumbRight",
)
N_JOINTS = len(JOINTS)
JOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(JOINTS)}

#: Joints whose mean is used as a person's position for association: the
#: torso moves least between sensors' views and is rarely self-occluded.
TORSO: tuple[int, ...] = tuple(
    JOINT_INDEX[n] for n in ("SpineBase", "SpineMid", "SpineShoulder", "HipLeft", "HipRight")
)

#: Named groups a composer may use wherever a joint is expected.
GROUPS: dict[str, tuple[str, ...]] = {
    "hands": ("HandLeft", "HandRight"),
    "feet": ("FootLeft", "FootRight"),
    "ankles": ("AnkleLeft", "AnkleRight"),
    "knees": ("KneeLeft", "KneeRight"),
    "elbows": ("ElbowLeft", "ElbowRight"),
    "wrists": ("WristLeft", "WristRight"),
    "shoulders": ("ShoulderLeft", "ShoulderRight"),
    "hips": ("HipLeft", "HipRight"),
    "spine": ("SpineBase", "SpineMid", "SpineShoulder", "Neck"),
}

#: Confidence values of the Kinect tracking states.
NOT_TRACKED, INFERRED, TRACKED = 0.0, 0.5, 1.0


class HandState(IntEnum):
    """Kinect hand-state codes; the fused vote breaks ties towards the higher code."""

    UNKNOWN = 0
    NOT_TRACKED = 1
    OPEN = 2
    CLOSED = 3
    LASSO = 4

    @property
    def wire_name(self) -> str:
        return HAND_STATE_NAMES[self]


HAND_STATE_NAMES: dict[HandState, str] = {
    HandState.UNKNOWN: "unknown",
    HandState.NOT_TRACKED: "notTracked",
    HandState.OPEN: "open",
    HandState.CLOSED: "closed",
    HandState.LASSO: "lasso",
}
_HAND_STATE_BY_NAME = {name.lower(): state for state, name in HAND_STATE_NAMES.items()}
_HAND_STATE_BY_NAME["not_tracked"] = HandState.NOT_TRACKED

HANDS: tuple[str, ...] = ("left", "right")


def parse_hand_state(value: object) -> HandState | None:
    """Return the hand state for a wire name (any case) or code 0-4, else None."""
    if isinstance(value, str):
        state = _HAND_STATE_BY_NAME.get(value.strip().lower())
        if state is not None:
            return state
        value = value.strip()
        if not value.isdigit():
            return None
        value = int(value)
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)) and float(value).is_integer() and 0 <= value <= 4:
        return HandState(int(value))
    return None


def parse_hand(value: object) -> int | None:
    """Return 0 for the left hand and 1 for the right (names, 'l'/'r' or 0/1), else None."""
    if isinstance(value, str):
        v = value.strip().lower()
        if v in ("left", "l"):
            return 0
        if v in ("right", "r"):
            return 1
        return None
    if isinstance(value, int) and not isinstance(value, bool) and value in (0, 1):
        return value
    return None


def suggest_joint(name: str) -> str | None:
    """The joint a misspelt ``name`` most likely meant, for error messages."""
    lowered = {n.lower(): n for n in (*JOINTS, *GROUPS)}
    if name.lower() in lowered:
        return lowered[name.lower()]
    close = difflib.get_close_matches(name.lower(), list(lowered), n=1, cutoff=0.6)
    return lowered[close[0]] if close else None
