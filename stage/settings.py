"""The engine's settings, as the rig file spells them (``fusion:``, ``clients:``, ``smoothing:``).

Plain frozen dataclasses that validate themselves; the rig loader builds them
from YAML and the engine, tracking and Kalman code read them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from numbers import Real

from .errors import ConfigError


@dataclass(frozen=True)
class KalmanSettings:
    """Noise model of the joint filter.

    process_noise: variance of the white-noise acceleration, (m/s^2)^2, per axis.
    measurement_noise: variance of one axis of a confidence-1 measurement, m^2;
        a measurement of confidence c has variance ``measurement_noise / c``.
    initial_velocity_var: variance of the (unknown, taken as 0) velocity of a
        newly seen point, (m/s)^2.
    """

    # 2 m/s^2 RMS acceleration: at 30 Hz with 1 cm noise, a tracking index
    # sigma_a*dt^2/sigma_z of ~0.22. bench/bench_kalman.py measures ~37 % less
    # jitter than the raw joints, no lag at constant velocity (~0.4 frame on a
    # 1 Hz, 0.3 m swing), and a 1 m/s stop overshooting ~2 cm and settling in
    # ~8 frames. Raise it for sharper moves, lower it for stiller pieces.
    process_noise: float = 4.0
    # Kinect v2 tracked joints jitter by about 1 cm per axis: (0.01 m)^2.
    measurement_noise: float = 1e-4
    # Joints of a standing or walking performer rarely exceed ~1-2 m/s when first
    # seen; 1 (m/s)^2 lets the velocity converge within a few frames.
    initial_velocity_var: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if (isinstance(value, bool) or not isinstance(value, Real)
                    or not math.isfinite(value) or value <= 0):
                raise ConfigError(f"kalman {f.name} must be a finite number > 0, got {value!r}")


@dataclass(frozen=True)
class FusionSettings:
    associate_m: float = 0.5     # an unbound view joins a person whose torso is this close
    release_m: float = 0.8       # a bound view leaves its person beyond this distance...
    release_frames: int = 3      # ...for this many frames in a row (hysteresis)
    merge_m: float = 0.3         # two persons this close...
    merge_s: float = 0.5         # ...for this long, never seen together by one sensor, are one
    outlier_m: float = 0.10      # joint outlier margin beyond the median spread
    stale_s: float = 0.15        # a view older than this is not averaged in
    lost_grace_s: float = 0.5    # a person with no views is kept this long before /lostUser
    min_interval_s: float = 0.025  # fuse a person at most this often (0: on every frame)
    hand_vote: str = "plain"     # or "confidence": votes weighted by hand-joint confidence

    def __post_init__(self) -> None:
        if self.hand_vote not in ("plain", "confidence"):
            raise ConfigError(f"'hand_vote' must be 'plain' or 'confidence', got '{self.hand_vote}'")
        if self.release_m < self.associate_m:
            raise ConfigError("'release_m' must be at least 'associate_m' (hysteresis)")


@dataclass(frozen=True)
class ClientSettings:
    timeout_s: float = 1.0            # silence after which a client loses its users
    max_messages_per_s: float = 3000  # per-source budget; beyond it datagrams count as flood
    # per-host budget (all source ports of one address together), so a sender cannot
    # escape its budget by using many ports; several sensors on one PC share it
    max_messages_per_s_per_host: float = 24000
    # a timetag further than this from our wall clock is not a capture time: rejected and
    # counted (bad_time); generous, since sensor PCs need not run NTP
    max_clock_skew_s: float = 86400.0
    # a client whose clock goes back by more than this has restarted: its users are
    # dropped and its clock followed afresh (smaller steps back are UDP reordering: late)
    restart_back_s: float = 0.25
    # with no reference in the rig, a sensor becomes the reference once it has sent valid
    # skeletons of a person for this long (0: its first one, so a lone sensor is fused at
    # once); a client that only registers never does, and a reference chosen so that goes
    # silent before anything is calibrated against it is replaced (docs/security.md)
    reference_after_s: float = 0.0


@dataclass(frozen=True)
class LimitSettings:
    """Caps that keep memory and CPU bounded whatever arrives (docs/security.md)."""

    max_clients: int = 64         # sensor ids remembered; beyond, the longest-silent is forgotten
    max_views: int = 32           # views registered over OSC at once
    view_ttl_s: float = 60.0      # a view registered over OSC expires unless it re-registers
    view_send_errors: int = 5     # a view refused this many times in a row is dropped
    max_drop_keys: int = 256      # drop counters by client/source; beyond, one "(other)" key
    max_sources: int = 4096       # per-source and per-host rate-limit entries (LRU)
    stats_reply_bytes: int = 8192  # a /stage/stats reply is one datagram of at most this


@dataclass(frozen=True)
class AlertSettings:
    """When to tell someone (docs/installing.md): a part down or suspect for ``after_s``."""

    after_s: float = 60.0
    command: str = ""             # run with the alert in STAGE_ALERT_* environment variables
    osc: str = ""                 # HOST:PORT to send /stage/alert to
    summary_every_s: float = 60.0  # the one-line health summary in the log
