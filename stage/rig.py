"""The rig file: the installer's description of sensors, calibration and ports.

A rig never mentions music. Every key, each optional (defaults shown)::

    server: {host: 0.0.0.0, port: 7770}
    reference: kinect-a            # its space is stage space unless stage_frame is set
    stage_frame: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]
    sensors:
      kinect-a: {type: kinect2}
      phone: {type: pose-app, hand_reading_frames: 1}   # a type the engine does not know,
                                   # whose client reads hand states every frame (fusion's key)
      kinect-b:
        type: kinect2
        calibration: {matrix: [[...4x4...]], method: rigid, fitness: 0.97, rms_m: 0.021,
                      date: 2026-11-21T10:00:00}
    allow_unknown_sensors: true    # false: only the sensors listed here are accepted
    allow:                         # who may send and where output may go (docs/security.md)
      sensors: [loopback, local]   # addresses or networks sensor datagrams are read from
      views: [loopback, local]     # where /registerView may point and stats replies may go
    views: ["127.0.0.1:9001"]
    clients: {timeout_s: 1.0, max_messages_per_s: 3000}
    limits: {max_clients: 64, max_views: 32, view_ttl_s: 60}   # see LimitSettings
    alerts: {after_s: 60, command: "notify-installer", osc: "10.0.0.9:9999"}
    fusion:                        # settings.FusionSettings
      associate_m: 0.5             # an unbound view joins a person whose torso is this close
      release_m: 0.8               # a bound view leaves its person beyond this...
      release_frames: 3            # ...for this many frames in a row
      merge_m: 0.3                 # two persons this close...
      merge_s: 0.5                 # ...this long, never seen together by one sensor, are one
      stale_s: 0.15                # a joint no view has reported for this long is not sent
      lost_grace_s: 0.5            # a person with no views is kept this long
      group_s: 0.005               # frames captured this close together are one instant
      view_bias_m: 0.02            # a view's systematic error, when views of an instant compare
      replay_s: 0.15               # history kept to fold in frames that come late
      view_offset_s: 0.25          # a view's steady offset from the others is learned over
                                   # this long and taken off (0: off; stage/engine/offsets.py)
      hand_vote: confidence        # or plain
      hand_memory_s: 0.045         # a hand report's weight falls by e in this time
      hand_hold_s: 0.1             # a hand's new state is sent once it has held this long
      hand_reading_frames: null    # all sensors read hand states every this many frames;
                                   # null: each sensor's own key, else by its registered type
                                   # (kinect2 2, webcam-mediapipe 1, others 2)
      rejoin_s: 3.0                # a person lost this recently...
      rejoin_m: 0.75               # ...back this close to where they were lost...
      rejoin_size_m: 0.05          # ...with a trunk length this close gets their id back
      unswap_limbs: true           # trade back a view's swapped left/right arm or leg
      hold_back_inferred: true     # joints no sensor has tracked yet are not reported
      carry_untracked: true        # joints only inferred now follow their parent joint
      native: true                 # a datagram's views folded by the native core, one compiled
                                   # call, the same output (stage/engine/native.py); false:
                                   # the Python path alone
    smoothing:                     # settings.KalmanSettings (docs/smoothing.md)
      enabled: true                # false: each joint is its latest accepted measurement
      quiet_noise: 5.0             # acceleration variance of the quiet motion model, (m/s^2)^2
      fast_noise: 2000.0           # ...and of the fast one
      quiet_to_fast_per_s: 1.5     # how often the motion switches model
      fast_to_quiet_per_s: 3.2
      measurement_noise: 1e-4      # variance of a confidence-1 joint up to 1 m away, m^2
      noise_per_m: 0.004           # added to its s.d. per metre beyond
      inferred_sd_m: 0.10          # an inferred joint (conf 0.5) is a guess this far off, m
      initial_velocity_var: 1.0    # (m/s)^2, a newly seen joint
      gate_sigma: 2.5              # beyond this Mahalanobis distance a joint counts less
      reject_sigma: 10.0           # beyond this it is not used
    forecast:                      # settings.ForecastSettings (docs/anticipation.md)
      views_s: 0.0                 # the views above get each body predicted this far ahead
      max_s: 0.2                   # the longest forecast a view or piece may ask for
      torso_speed_m_s: 4.0         # a predicted joint moves at most this fast...
      limb_speed_m_s: 8.0          # ...elbows, knees
      extremity_speed_m_s: 12.0    # ...wrists, hands, ankles, feet
      bone_tolerance: 0.1          # predicted bones keep their length within 10 %
      foot_velocity_memory_s: 0.0545  # how long a foot's vertical velocity lasts, s
      hand_velocity_memory_s: 0.0  # ...a hand's (0: for ever, constant velocity)

Retired keys (``settings.RETIRED_KEYS``: ``fusion: min_interval_s``, ``fusion: outlier_m``,
``smoothing: process_noise``) are refused with a line naming what replaced them.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import yaml

from .errors import ConfigError
from .geometry import invert
from .network import Networks, parse_hostport
from .settings import (RETIRED_KEYS, AlertSettings, ClientSettings, ForecastSettings,
                       FusionSettings, KalmanSettings,
                       LimitSettings)
from .yamlio import MarkedDict, Where, load_marked, write_atomic

DEFAULT_PORT = 7770


@dataclass
class Calibration:
    """A sensor's transform into the reference sensor's space."""

    matrix: np.ndarray            # (4, 4)
    method: str = "manual"
    fitness: float | None = None  # (0, 1], 1 = perfect
    rms_m: float | None = None
    date: str | None = None


@dataclass
class SensorConfig:
    id: str
    type: str = "kinect2"
    calibration: Calibration | None = None
    #: where this sensor may send from (an address or network); None: any allowed address
    address: Networks | None = None
    #: the frames one of its hand-state readings lasts (None: ``fusion.hand_reading_frames``,
    #: else by its type: ``stage.engine.hands.reading_frames``)
    hand_reading_frames: int | None = None


@dataclass
class Rig:
    host: str = "0.0.0.0"
    port: int = DEFAULT_PORT
    reference: str | None = None
    stage_frame: np.ndarray = field(default_factory=lambda: np.eye(4))
    sensors: dict[str, SensorConfig] = field(default_factory=dict)
    allow_unknown_sensors: bool = True
    #: addresses sensor datagrams are accepted from (docs/security.md)
    allow_sensors: Networks = field(default_factory=Networks)
    #: addresses views may be registered at and stats replies sent to
    allow_views: Networks = field(default_factory=Networks)
    views: list[tuple[str, int]] = field(default_factory=list)
    clients: ClientSettings = field(default_factory=ClientSettings)
    limits: LimitSettings = field(default_factory=LimitSettings)
    alerts: AlertSettings = field(default_factory=AlertSettings)
    fusion: FusionSettings = field(default_factory=FusionSettings)
    smoothing: KalmanSettings = field(default_factory=KalmanSettings)
    smoothing_enabled: bool = True
    forecast: ForecastSettings = field(default_factory=ForecastSettings)
    path: str | None = None

    def transform_for(self, sensor: str) -> np.ndarray | None:
        """Sensor space -> stage space (4x4), or None when the sensor is not calibrated."""
        if sensor == self.reference:
            return self.stage_frame.copy()
        config = self.sensors.get(sensor)
        if config is None or config.calibration is None:
            return None
        return self.stage_frame @ config.calibration.matrix

    def save(self, path: str | None = None) -> None:
        """Write the rig atomically (the previous file survives a crash mid-write)."""
        target = path or self.path
        if target is None:
            raise ConfigError("rig has no path to save to")
        write_atomic(target, yaml.safe_dump(self.to_dict(), sort_keys=False))
        self.path = str(target)

    def to_dict(self) -> dict[str, Any]:
        sensors: dict[str, Any] = {}
        for sid, cfg in self.sensors.items():
            entry: dict[str, Any] = {"type": cfg.type}
            if cfg.address is not None:
                entry["address"] = list(cfg.address.entries)
            if cfg.hand_reading_frames is not None:
                entry["hand_reading_frames"] = cfg.hand_reading_frames
            if cfg.calibration is not None:
                c = cfg.calibration
                entry["calibration"] = {
                    "matrix": [[float(v) for v in row] for row in c.matrix],
                    "method": c.method, "fitness": c.fitness, "rms_m": c.rms_m, "date": c.date}
            sensors[sid] = entry
        out: dict[str, Any] = {"server": {"host": self.host, "port": self.port}}
        if self.reference is not None:
            out["reference"] = self.reference
        if not np.allclose(self.stage_frame, np.eye(4)):
            out["stage_frame"] = [[float(v) for v in row] for row in self.stage_frame]
        out["sensors"] = sensors
        out["allow_unknown_sensors"] = self.allow_unknown_sensors
        out["allow"] = {"sensors": list(self.allow_sensors.entries),
                        "views": list(self.allow_views.entries)}
        out["views"] = [f"{h}:{p}" for h, p in self.views]
        out["clients"] = dataclasses.asdict(self.clients)
        out["limits"] = dataclasses.asdict(self.limits)
        out["alerts"] = dataclasses.asdict(self.alerts)
        out["fusion"] = dataclasses.asdict(self.fusion)
        out["smoothing"] = {"enabled": self.smoothing_enabled, **dataclasses.asdict(self.smoothing)}
        out["forecast"] = dataclasses.asdict(self.forecast)
        return out


def set_calibration(rig: Rig, sensor: str, matrix: np.ndarray, method: str,
                    fitness: float | None = None, rms_m: float | None = None) -> None:
    now = _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()
    config = rig.sensors.setdefault(sensor, SensorConfig(sensor))
    config.calibration = Calibration(np.asarray(matrix, dtype=float), method, fitness, rms_m, now)


def load_rig(path: str) -> Rig:
    """Read and validate a rig file; errors name file:line:column."""
    where = Where(path)
    data = where.mapping(load_marked(path), "the rig")
    where.check_keys(data, ("server", "reference", "stage_frame", "sensors",
                            "allow_unknown_sensors", "allow", "views", "clients", "limits",
                            "alerts", "fusion", "smoothing", "forecast"),
                     "the rig")
    rig = Rig(path=path)
    server = where.mapping(data.get("server"), "'server'")
    where.check_keys(server, ("host", "port"), "'server'")
    rig.host = str(server.get("host", rig.host))
    port = server.get("port", rig.port)
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise where.at_key(server, "port", f"'port' must be a whole number 1-65535, got {port!r}")
    rig.port = port
    if "reference" in data:
        rig.reference = str(data["reference"])
    if "stage_frame" in data:
        rig.stage_frame = _matrix(where, data, "stage_frame")
    sensors = where.mapping(data.get("sensors"), "'sensors'")
    for sid, entry in sensors.items():
        entry = where.mapping(entry, f"sensor '{sid}'", sensors.value_marks.get(sid))
        where.check_keys(entry, ("type", "calibration", "address", "hand_reading_frames"),
                         f"sensor '{sid}'")
        config = SensorConfig(str(sid), str(entry.get("type", "kinect2")))
        config.hand_reading_frames = _reading_frames(where, entry, f"sensor '{sid}'")
        if entry.get("address") is not None:
            config.address = _networks(where, entry, "address")
        if entry.get("calibration") is not None:
            cal = where.mapping(entry["calibration"], f"calibration of '{sid}'")
            where.check_keys(cal, ("matrix", "method", "fitness", "rms_m", "date"),
                             f"calibration of '{sid}'")
            if "matrix" not in cal:
                raise where.error(f"calibration of '{sid}' needs a 'matrix' (4x4)", cal.mark)
            config.calibration = Calibration(
                _matrix(where, cal, "matrix"), str(cal.get("method", "manual")),
                _optional_number(where, cal, "fitness"), _optional_number(where, cal, "rms_m"),
                None if cal.get("date") is None else str(cal["date"]))
        rig.sensors[str(sid)] = config
    if rig.reference is not None and rig.sensors and rig.reference not in rig.sensors:
        raise where.at_key(data, "reference",
                           f"reference '{rig.reference}' is not one of the sensors: "
                           f"{', '.join(rig.sensors)}")
    allow = data.get("allow_unknown_sensors", True)
    if not isinstance(allow, bool):
        raise where.at_key(data, "allow_unknown_sensors", "'allow_unknown_sensors' must be true or false")
    rig.allow_unknown_sensors = allow
    allow_lists = where.mapping(data.get("allow"), "'allow'")
    where.check_keys(allow_lists, ("sensors", "views"), "'allow'")
    if "sensors" in allow_lists:
        rig.allow_sensors = _networks(where, allow_lists, "sensors")
    if "views" in allow_lists:
        rig.allow_views = _networks(where, allow_lists, "views")
    views = data.get("views") or []
    if not isinstance(views, list):
        raise where.at_key(data, "views", "'views' must be a list of HOST:PORT")
    for k, text in enumerate(views):
        try:
            rig.views.append(parse_hostport(str(text)))
        except ValueError as exc:
            raise where.error(str(exc), getattr(views, "marks", [None] * len(views))[k]) from None
    rig.clients = _settings(where, data, "clients", ClientSettings)
    rig.limits = _settings(where, data, "limits", LimitSettings)
    rig.alerts = _settings(where, data, "alerts", AlertSettings)
    if rig.alerts.osc:
        try:
            parse_hostport(rig.alerts.osc)
        except ValueError as exc:
            raise where.error(f"alerts: osc: {exc}", getattr(data.get("alerts"), "mark", None)
                              ) from None
    rig.fusion = _settings(where, data, "fusion", FusionSettings)
    rig.forecast = _settings(where, data, "forecast", ForecastSettings)
    smoothing = where.mapping(data.get("smoothing"), "'smoothing'")
    enabled = smoothing.get("enabled", True)
    if not isinstance(enabled, bool):
        raise where.at_key(smoothing, "enabled", "'enabled' must be true or false")
    rig.smoothing_enabled = enabled
    rest = MarkedDict({k: v for k, v in smoothing.items() if k != "enabled"})
    rest.mark = getattr(smoothing, "mark", (0, 0))
    rest.marks = getattr(smoothing, "marks", {})
    rest.value_marks = getattr(smoothing, "value_marks", {})
    rig.smoothing = _settings(where, {"smoothing": rest}, "smoothing", KalmanSettings)
    return rig


def _networks(where: Where, mapping: dict, key: str) -> Networks:
    """An allow-list: one entry or a list of addresses, networks, 'loopback', 'local', 'any'."""
    value = mapping[key]
    entries = value if isinstance(value, list) else [value]
    if not entries:
        return Networks(())
    try:
        return Networks(str(e) for e in entries)
    except ValueError as exc:
        raise where.at_key(mapping, key, f"'{key}': {exc}") from None


def _reading_frames(where: Where, mapping: dict, what: str) -> int | None:
    """A ``hand_reading_frames`` key: a whole number of frames, 1-8, or null (not set)."""
    value = mapping.get("hand_reading_frames")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 8:
        raise where.at_key(mapping, "hand_reading_frames",
                           f"'hand_reading_frames' of {what} must be a whole number of frames "
                           f"1-8 (a Kinect v2 2, a client reading hands every frame 1) or "
                           f"null, got {value!r}")
    return value


def _optional_number(where: Where, mapping: dict, key: str) -> float | None:
    if mapping.get(key) is None:
        return None
    return where.number(mapping, key, 0.0)


def _matrix(where: Where, mapping: dict, key: str) -> np.ndarray:
    value = mapping[key]
    try:
        matrix = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise where.at_key(mapping, key, f"'{key}' must be a 4x4 list of numbers") from None
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise where.at_key(mapping, key, f"'{key}' must be a 4x4 list of finite numbers")
    if not np.allclose(matrix[3], (0, 0, 0, 1)):
        raise where.at_key(mapping, key, f"'{key}' last row must be 0 0 0 1")
    return matrix


#: settings for which 0 means something (off, none): every other number must be > 0
_ZERO_ALLOWED = {"reference_after_s", "view_offset_s", "noise_per_m", "inferred_sd_m",
                 "views_s", "bone_tolerance", "foot_velocity_memory_s", "hand_velocity_memory_s"}


def _settings(where: Where, data: dict, key: str, cls: type) -> Any:
    section = where.mapping(data.get(key), f"'{key}'")
    for (owner, old), instead in RETIRED_KEYS.items():
        if owner == key and old in section:
            raise where.at_key(section, old, f"'{key}: {old}' is no longer used: {instead}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    where.check_keys(section, fields, f"'{key}'")
    values: dict[str, Any] = {}
    for name, value in section.items():
        default = fields[name].default
        if name == "hand_reading_frames":
            values[name] = _reading_frames(where, section, f"'{key}'")
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise where.at_key(section, name, f"'{name}' must be true or false")
            values[name] = value
        elif isinstance(default, str):
            if not isinstance(value, str):
                raise where.at_key(section, name, f"'{name}' must be text")
            values[name] = value
        elif isinstance(default, int) and not isinstance(default, bool):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise where.at_key(section, name, f"'{name}' must be a whole number >= 1")
            values[name] = value
        elif name in _ZERO_ALLOWED:
            values[name] = where.number(section, name, default, minimum=0.0)
        else:
            values[name] = where.number(section, name, default, exclusive_minimum=0.0)
    try:
        return cls(**values)
    except ConfigError as exc:
        raise where.error(exc.bare_message, getattr(section, "mark", None)) from None


# ---------------------------------------------------------------- calibration results

def store_stage_transform(rig: Rig, sensor: str, to_stage: np.ndarray, reference: str | None,
                          method: str, fitness: float | None, rms_m: float | None) -> None:
    """Record a sensor -> STAGE transform (what the engine uses) in the rig.

    The rig keeps each sensor's transform into the reference sensor's space
    and the reference's own placement as ``stage_frame``. A new transform for
    the reference itself (it was moved and re-calibrated against the others)
    becomes the new stage frame, and every other calibration is re-expressed
    against it, so stage space stays where the other sensors put it.
    """
    if reference is not None:
        rig.reference = reference
        rig.sensors.setdefault(reference, SensorConfig(reference))
    if sensor == rig.reference:
        old = rig.stage_frame
        new_inverse = invert(to_stage)
        for sid, config in rig.sensors.items():
            if sid != sensor and config.calibration is not None:
                config.calibration.matrix = new_inverse @ old @ config.calibration.matrix
        rig.stage_frame = np.asarray(to_stage, dtype=float)
        set_calibration(rig, sensor, np.eye(4), method, fitness, rms_m)
    else:
        set_calibration(rig, sensor, invert(rig.stage_frame) @ to_stage, method, fitness, rms_m)


def store_reference_transform(rig: Rig, sensor: str, to_reference: np.ndarray,
                              reference: str, method: str, fitness: float | None,
                              rms_m: float | None) -> None:
    """Record a sensor -> REFERENCE-space transform (offline calibration) in the rig.

    The caller resets ``rig.stage_frame`` when the reference changes (the old
    frame placed the old reference).
    """
    rig.reference = reference
    rig.sensors.setdefault(reference, SensorConfig(reference))
    set_calibration(rig, sensor, to_reference, method, fitness, rms_m)
