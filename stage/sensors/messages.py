"""The messages of the OSC wire API as Python objects (decoded by ``protocol``).

Plain data: what a datagram can hold once validated (see ``protocol.decode_datagram``),
the drop reasons, and the limits the decoder enforces. docs/osc-api.md lists them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Union

import numpy as np

from ..joints import HandState

#: Coordinates beyond this many metres from the sensor are not a person.
MAX_COORD_M = 20.0
MAX_USER_ID = 5

#: Every reason a datagram or message can be dropped, in the order the docs list them.
DROP_REASONS: tuple[str, ...] = (
    "malformed",        # not OSC at all, truncated, bad padding
    "unknown_address",  # an address this server does not serve
    "bad_arity",        # wrong number of arguments
    "bad_types",        # an argument of the wrong OSC type
    "non_finite",       # NaN or inf in a coordinate or confidence
    "out_of_range",     # coordinate over 20 m, confidence outside [0, 1], port outside 1-65535
    "unknown_joint",    # a joint name that is not one of the 25
    "duplicate_joint",  # the same joint twice in one skeleton
    "bad_user_id",      # user id not an integer 0-5
    "bad_hand",         # hand not left/right
    "bad_hand_state",   # state not one of the five names or codes
    "flood",            # a client over its message-rate budget
    "queue_full",       # the engine queue is full (engine far behind)
    "not_allowed",      # client or address not in the rig's allow-lists (docs/security.md)
    "wrong_source",     # a known sensor id sent from another address than it registered from
    "too_many_clients", # a new sensor id while the client table is full of active sensors
    "too_many_views",   # a /registerView while the view table is full
    "bad_time",         # a timetag further from our wall clock than clients.max_clock_skew_s
    "late",             # older than the frame already fused for that user
    "kernel_overflow",  # the kernel dropped it: the socket's receive queue was full
    "internal_error",   # the engine failed on this message (a bug; logged with a traceback)
)
#: sensor types and other free text from the wire are cut to this many characters
MAX_TEXT = 64


@dataclass(slots=True)
class RegisterDevice:
    client: str
    sensor_type: str


@dataclass(slots=True)
class NewUser:
    client: str
    user: int
    position: np.ndarray  # (3,) metres, sensor space


@dataclass(slots=True)
class LostUser:
    client: str
    user: int


@dataclass(slots=True)
class JointCoordinates:
    client: str
    user: int
    joints: np.ndarray  # (25, 3) float64, metres, sensor space; zeros where absent
    conf: np.ndarray    # (25,) float64 in [0, 1]; 0 where the joint was not sent


@dataclass(slots=True)
class HandStateMsg:
    client: str
    user: int
    hand: int           # 0 left, 1 right
    state: HandState


@dataclass(slots=True)
class FloorPlane:
    """stage extension: the floor plane a sensor reports, ax + by + cz + d = 0 in its space."""

    client: str
    plane: np.ndarray   # (4,) a, b, c, d; (a, b, c) normalised to unit length


@dataclass(slots=True)
class RegisterView:
    host: str
    port: int
    register: bool = True  # False for /unregisterView
    rate_hz: float | None = None  # a fixed output rate asked for (stage addition); None: every update
    forecast_s: float | None = None  # bodies predicted this far ahead (stage addition); None: 0


@dataclass(slots=True)
class StatsQuery:
    reply_port: int | None  # None: reply to the sender's port


@dataclass(slots=True)
class HealthQuery:
    """stage extension: ``/stage/health [port]``: the health messages, to the sender's address."""

    reply_port: int | None


@dataclass(slots=True)
class ViewUnreachable:
    """Not from the wire: the kernel said a datagram to this address was refused (ICMP)."""

    host: str
    port: int


ClientMessage = Union[RegisterDevice, NewUser, LostUser, JointCoordinates, HandStateMsg, FloorPlane]
Message = Union[ClientMessage, RegisterView, StatsQuery, HealthQuery, ViewUnreachable]


@dataclass(slots=True)
class Inbound:
    """A decoded message as a receiver hands it to the engine (the sensors -> engine contract)."""

    message: Message
    arrival: float              # engine clock, when the datagram was read
    source: tuple[str, int]     # sender address
    timetag: float | None = None  # capture time on the client's clock (Unix s), if bundled


@dataclass(slots=True)
class Decoded:
    """What one datagram held: messages with their timetag, and the drops."""

    messages: list[tuple[Message, float | None]] = field(default_factory=list)
    drops: list[tuple[str, str]] = field(default_factory=list)  # (client or source, reason)
