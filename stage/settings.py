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
    """The joint filter (``stage.engine.kalman``): two motion models, the sensor noise, the gate.

    quiet_noise, fast_noise: white-noise acceleration variance of the quiet and the
        fast motion model, (m/s^2)^2 per axis.
    quiet_to_fast_per_s, fast_to_quiet_per_s: how often the motion switches model
        (rates: the chance of a switch within dt is 1 - exp(-rate * dt)).
    measurement_noise: variance of one axis of a confidence-1 joint at most 1 m from
        its sensor, m^2; ``noise_per_m`` (m per m) is added to its s.d. per metre beyond,
        and a joint of confidence c has variance / c.
    inferred_sd_m: how far off (s.d. per axis, m) a joint the sensor only infers
        (confidence 0.5, Kinect convention) may be: a guess, not a measurement, so
        ``(1/c - 1) * inferred_sd_m^2`` is added to the variance of a joint of confidence
        c <= 0.5 (nothing to a joint above the inferred level, which is tracked, as a
        continuous 0.9 is; 0 turns it off).
    initial_velocity_var: variance of the (unknown, taken as 0) velocity of a newly
        seen joint, (m/s)^2.
    gate_sigma: beyond this Mahalanobis distance from the prediction a joint's
        variance is multiplied by (distance / gate_sigma)^2; reject_sigma: beyond this
        it is not used at all.
    """

    # Tuned on the CMU motion capture of subject 131 (walks, a hop, kicks; hands and feet
    # reach 12 m/s) at 30 Hz with 1 cm noise, and 2 cm noise with 2 % outliers of
    # 10-30 cm: bench/bench_smoothing.py, docs/smoothing.md.
    quiet_noise: float = 5.0           # 2.2 m/s^2 RMS: standing, swaying, the torso walking
    fast_noise: float = 2000.0         # 45 m/s^2 RMS: kicks, hops, arm swings
    quiet_to_fast_per_s: float = 1.5   # about 5 % a frame at 30 Hz
    fast_to_quiet_per_s: float = 3.2   # about 10 % a frame
    # Kinect v2 tracked joints jitter by about 1 cm per axis near the sensor...
    measurement_noise: float = 1e-4
    # ...and more further away (the simulator's Kinect model assumes 4 mm per metre)
    noise_per_m: float = 0.004
    # Kinect inferred joints are guesses: 10-30 cm off (issue 11 on real Kinects; the
    # simulator's realistic model), i.e. about 12 cm per axis; 10 cm counts an inferred
    # joint ~1/100 of a tracked one, so a second sensor that tracks it, or the filter's
    # prediction, carries it (docs/smoothing.md)
    inferred_sd_m: float = 0.10
    # Joints of a performer rarely exceed ~1-2 m/s when first seen; 1 (m/s)^2 lets the
    # velocity converge within a few frames.
    initial_velocity_var: float = 1.0
    gate_sigma: float = 2.5            # chi-square, 3 degrees of freedom: 90 % of good joints
    reject_sigma: float = 10.0         # a gross error (swapped limbs, a jump of a metre)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if (isinstance(value, bool) or not isinstance(value, Real)
                    or not math.isfinite(value) or value < 0
                    or (value == 0 and f.name not in ("noise_per_m", "inferred_sd_m"))):
                raise ConfigError(f"kalman {f.name} must be a finite number > 0, got {value!r}")
        if self.reject_sigma < self.gate_sigma:
            raise ConfigError("kalman reject_sigma must be at least gate_sigma")


@dataclass(frozen=True)
class FusionSettings:
    """Who is who (association, merging, ids), how views of an instant are combined, hands.

    Each sensor frame is folded into its person's filter at once (``stage.engine.fuser``);
    the filter itself is ``KalmanSettings``.
    """

    associate_m: float = 0.5     # an unbound view joins a person whose torso is this close
    release_m: float = 0.8       # a bound view leaves its person beyond this distance...
    release_frames: int = 3      # ...for this many frames in a row (hysteresis)
    merge_m: float = 0.3         # two persons this close...
    merge_s: float = 0.5         # ...for this long, never seen together by one sensor, are one
    stale_s: float = 0.15        # a joint no view has reported for this long is not sent
    lost_grace_s: float = 0.5    # a person with no views is kept this long before /lostUser
    group_s: float = 0.005       # frames captured this close together are one instant: their
                                 # joints are checked against each other before they are fused
    view_bias_m: float = 0.02    # each view's own systematic error (calibration, the sensor's
                                 # fit), allowed for when views of an instant are compared
    replay_s: float = 0.15       # history kept per person to fold in frames that come late
    view_offset_s: float = 0.25  # each view's steady offset from its person's other views (a
                                 # sensor's own fit of the body, the calibration's residual)
                                 # is learned over about this long and taken off its joints,
                                 # so the fused stream does not swing between views (0: off;
                                 # ``stage.engine.offsets``)
    hand_vote: str = "confidence"  # or "plain": every report weighs 1, not the hand's confidence
    hand_memory_s: float = 0.045  # a hand report's weight falls by e every this many seconds
    hand_hold_s: float = 0.1     # a hand's new state must win the vote this long to be reported
                                 # (time counts up to twice as fast the more sensors agree)
    hand_reading_frames: int | None = None  # every sensor reads hand states every this many
                                 # frames and repeats them in between, so the vote's evidence
                                 # counts a reading once (docs/osc-api.md, rule 6); None: by
                                 # each sensor's type (Kinect v2 2, docs/sources.md; the
                                 # webcam client 1; others 2: ``sensors.kinds``), or
                                 # the sensor's own ``hand_reading_frames`` in the rig
    rejoin_s: float = 3.0        # a person lost this recently...
    rejoin_m: float = 0.75       # ...who reappears this close to where they were lost...
    rejoin_size_m: float = 0.05  # ...with a trunk length this close to theirs gets their id back
    unswap_limbs: bool = True    # trade back a view's left and right arm (leg) when both its
                                 # elbow and wrist (knee and ankle) lie on the wrong side of the
                                 # shoulders' (hips') axis (``fusion.unswap_limbs``)
    hold_back_inferred: bool = True  # a joint no sensor has tracked since the person was
                                 # found is not reported (confidence 0) while sensors only
                                 # infer it: a guess 10-30 cm off is not a position
    carry_untracked: bool = True  # a joint every sensor only infers now is reported at its
                                 # parent joint plus the offset it had when last tracked, as
                                 # inferred (``fusion.carry_untracked``)
    native: bool = True          # fold a datagram's views in the native core, one compiled
                                 # call (``stage.engine.native``; the same output to the
                                 # bit); off: the Python path alone

    def __post_init__(self) -> None:
        if self.hand_vote not in ("plain", "confidence"):
            raise ConfigError(f"'hand_vote' must be 'plain' or 'confidence', got '{self.hand_vote}'")
        if self.release_m < self.associate_m:
            raise ConfigError("'release_m' must be at least 'associate_m' (hysteresis)")


@dataclass(frozen=True)
class ForecastSettings:
    """How far ahead fused bodies may be predicted, and the bounds on a prediction
    (``stage.engine.forecast``; docs/anticipation.md).

    A forecast is the filter's state carried ``forecast_s`` past a body's capture time; a
    joint's predicted move is capped by its speed limit (m/s) times the horizon, and every
    bone keeps its length at capture time within ``bone_tolerance`` (a fraction).
    """

    views_s: float = 0.0              # forecast for the rig's and the command line's views
    max_s: float = 0.2                # the longest forecast anybody may ask for
    torso_speed_m_s: float = 4.0      # spine, neck, head, shoulders, hips
    limb_speed_m_s: float = 8.0       # elbows, knees
    extremity_speed_m_s: float = 12.0  # wrists, hands, thumbs, tips, ankles, feet (CMU 131:
                                      # feet reach 12 m/s in kicks, docs/smoothing.md)
    bone_tolerance: float = 0.1
    # how long a joint's vertical velocity lasts, s (0: for ever, a constant-velocity
    # forecast): the s.d. of the Gaussian fitted to the vertical velocity's autocorrelation
    # in CMU subject 131's motion capture (bench/bench_motion_memory.py; docs/anticipation.md)
    foot_velocity_memory_s: float = 0.0545  # ankles, feet (measured 54.5 ms)
    hand_velocity_memory_s: float = 0.0     # wrists, hands, thumbs, tips (measured 79 ms; off:
                                            # it changed no hand trigger on the tuning seeds)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value) \
                    or value < 0:
                raise ConfigError(f"forecast {f.name} must be a finite number >= 0, got {value!r}")
        if self.views_s > self.max_s:
            raise ConfigError(f"forecast views_s ({self.views_s:g}) is beyond max_s "
                              f"({self.max_s:g})")


#: rig keys that no longer exist, and what replaced them (one line each, for the error)
RETIRED_KEYS: dict[tuple[str, str], str] = {
    ("fusion", "min_interval_s"): "every sensor frame is now fused at once; there is no "
    "interval to set (see fusion: group_s, replay_s and smoothing: in CHANGELOG.md)",
    ("fusion", "outlier_m"): "outliers are now gated by the filter: smoothing: gate_sigma and "
    "reject_sigma, and fusion: view_bias_m for views of one instant",
    ("smoothing", "process_noise"): "the filter now has two motion models: smoothing: "
    "quiet_noise and fast_noise",
}


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
