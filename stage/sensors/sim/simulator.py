"""The simulator: virtual Kinects watching scripted performers, speaking the real OSC API.

``Simulator(scenario, seed)`` is deterministic: the same scenario and seed
give the same datagrams, byte for byte, however they are consumed
(``stream`` for the datagrams with their times, ``record`` to a recording
file, ``run_realtime`` over UDP; ``stage.app.offline.feed`` runs them through
an in-process engine). ``SimSource`` is the simulator as a ``stage.sources.v1``
source.

Times: simulation seconds from 0. A sensor's bundles carry its own clock as
timetag (an offset of up to +-2 s and a drift of up to +-20 ppm unless the
scenario fixes them, seed 003). A datagram arrives ``latency`` (60-80 ms per
sensor, seed 004) plus a little network jitter after its capture.

The pipeline delay. A frame's capture timestamp (what the client sends) is
later than the movement it shows: a frame stamped ``t`` holds the body as the
ground truth had it at ``t - d``, where ``d`` is the sensor model's
``pipeline_delay_s`` (default 60 ms, Kinect v2's own pipeline) plus
``pipeline_jitter_s`` of Gaussian jitter per frame (cut at 3 s.d., never
below 0). ``truth(t)`` is the movement itself, so a benchmark measures how
late (or, with a forecast, how early) the engine acts against it. The
delay is drawn from its own random stream, so changing it changes no noise.
"""

from __future__ import annotations

import heapq
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from ...errors import ConfigError
from ..clients.osc import BodyFrame, ClientEncoder, UserSlots
from ..source import ThreadedSource
from ...joints import JOINT_INDEX, HandState
from ...rig import Rig, SensorConfig, set_calibration
from .kinect import (KinectModel, UserTrack, VirtualPose, body_visible, faces_away, measure,
                     mirrored, sensed_hand, visibility)
from .scenario import Scenario, builtin_with_ring, load_scenario

log = logging.getLogger("stage.sim")

#: sensor clocks of offline runs count from here (Unix seconds), so output is reproducible
EPOCH = 1_700_000_000.0
#: longest network jitter added to a datagram (the exponential tail is cut here)
JITTER_CAP_S = 0.005
_HAND = (JOINT_INDEX["HandLeft"], JOINT_INDEX["HandRight"])


@dataclass
class Datagram:
    """One datagram with its times (simulation seconds)."""

    capture: float
    arrival: float
    sensor: str
    source: tuple[str, int]
    data: bytes


class _SensorRun:
    """One virtual sensor's state while a simulation runs."""

    def __init__(self, index: int, spec, scenario: Scenario, seed: int, rng_setup) -> None:
        self.index = index
        self.spec = spec
        self.id = spec.id
        self.model: KinectModel = spec.model
        seq = np.random.SeedSequence([seed, 1, index])
        self.rng = np.random.default_rng(seq)
        self.net_rng = np.random.default_rng(np.random.SeedSequence([seed, 2, index]))
        self.delay_rng = np.random.default_rng(np.random.SeedSequence([seed, 3, index]))
        self.offset = spec.clock_offset if spec.clock_offset is not None else \
            float(rng_setup.uniform(-2.0, 2.0))
        self.drift = (spec.clock_drift_ppm if spec.clock_drift_ppm is not None else
                      float(rng_setup.uniform(-20.0, 20.0))) * 1e-6
        lo, hi = scenario.latency_range
        self.latency = spec.latency if spec.latency is not None else float(rng_setup.uniform(lo, hi))
        self.phase = spec.phase if spec.phase is not None else \
            float(rng_setup.uniform(0.0, 1.0 / self.model.fps))
        self.source = ("sim", index + 1)
        self.poses: list[tuple[float, VirtualPose]] = [(0.0, spec.pose)]
        self.plugged: list[tuple[float, bool]] = [(0.0, True)]
        for event in scenario.events:
            if event.target != spec.id:
                continue
            if event.kind == "bump":
                self.poses.append((event.at, self.poses[-1][1].moved(event.yaw, event.pitch,
                                                                     event.roll, event.move)))
            elif event.kind in ("unplug", "replug"):
                self.plugged.append((event.at, event.kind == "replug"))
        # takes (KinectModel.take_s): where this sensor's cut starts, drawn only when asked for
        period = self.model.take_s + self.model.take_gap_s
        self.take_start = 0.0 if self.model.take_s <= 0 else float(
            np.random.default_rng(np.random.SeedSequence([seed, 3, index])).uniform(0, period))
        self.encoder = ClientEncoder(spec.id, spec.type)
        self.encoder.slots = UserSlots(self.model.max_users)
        self.tracks: dict[str, UserTrack] = {}
        self.k = 0
        self.next_floor = 0.0
        self.last_arrival = -math.inf

    def pose_at(self, t: float) -> VirtualPose:
        pose = self.poses[0][1]
        for when, p in self.poses:
            if when <= t:
                pose = p
        return pose

    def is_plugged(self, t: float) -> bool:
        state = True
        for when, s in self.plugged:
            if when <= t:
                state = s
        return state

    def in_take(self, t: float) -> bool:
        """Whether the sensor is recording at ``t`` (always, unless the model cuts takes)."""
        m = self.model
        return m.take_s <= 0 or (t + self.take_start) % (m.take_s + m.take_gap_s) < m.take_s

    def frame_time(self, k: int) -> float:
        return self.phase + k / self.model.fps

    def pipeline_delay(self) -> float:
        """This frame's pipeline delay, s: how long before its capture stamp it shows."""
        d, sd = self.model.pipeline_delay_s, self.model.pipeline_jitter_s
        if sd > 0:
            d += float(np.clip(self.delay_rng.normal(0.0, sd), -3 * sd, 3 * sd))
        return max(d, 0.0)

    def reset(self) -> None:
        """The sensor was unplugged: its client forgets everything."""
        self.encoder.reset()
        self.tracks.clear()
        self.next_floor = 0.0


class Simulator:
    """Virtual Kinect v2 sensors around scripted performers (see module docs)."""

    def __init__(self, scenario: Scenario | str | None = None, seed: int = 0) -> None:
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        self.seed = int(seed)
        self.performers = self.scenario.performers
        self._scales = {p.name: p.props.s for p in self.performers}

    # ------------------------------------------------------------ geometry and truth
    def _runs(self) -> list[_SensorRun]:
        setup = np.random.default_rng(np.random.SeedSequence([self.seed, 0]))
        return [_SensorRun(k, spec, self.scenario, self.seed, setup)
                for k, spec in enumerate(self.scenario.sensors)]

    def sensor_poses(self, t: float = 0.0) -> dict[str, VirtualPose]:
        """True pose of every sensor at ``t`` (after any bump before ``t``)."""
        return {run.id: run.pose_at(t) for run in self._runs()}

    def sensor_clocks(self) -> dict[str, dict[str, float]]:
        """Per sensor: clock offset (s), drift (ppm), latency (s) this seed gives and the
        model's pipeline delay (s, before the capture stamp; see the module docs)."""
        return {r.id: {"offset_s": r.offset, "drift_ppm": r.drift * 1e6, "latency_s": r.latency,
                       "pipeline_delay_s": r.model.pipeline_delay_s}
                for r in self._runs()}

    def rig(self, calibrated: bool = True) -> Rig:
        """A rig for these sensors: exact calibrations from the true poses at t = 0, or none.

        The reference is the scenario's; stage space is the simulator's (y up,
        floor at y = 0). Uncalibrated: only the reference is fused, in its own
        space, as on the first day of an installation.
        """
        poses = self.sensor_poses(0.0)
        ref = self.scenario.reference or next(iter(poses))
        rig = Rig(port=7770, reference=ref)
        for sid, spec in zip(poses, self.scenario.sensors):
            rig.sensors[sid] = SensorConfig(sid, spec.type)
        if calibrated:
            rig.stage_frame = poses[ref].to_stage
            inverse = np.linalg.inv(poses[ref].to_stage)
            for sid, pose in poses.items():
                set_calibration(rig, sid, inverse @ pose.to_stage, "simulator", 1.0, 0.0)
        return rig

    def truth(self, t: float) -> dict[str, tuple[np.ndarray, tuple[HandState, HandState]]]:
        """Ground truth at ``t``: performer -> ((25, 3) joints, stage space, metres; hands).

        Only performers on stage at ``t`` are listed.
        """
        out = {}
        for p in self.performers:
            state = p.state(t)
            if state is not None:
                out[p.name] = state
        return out

    # ------------------------------------------------------------ the datagram stream
    def datagrams(self, duration: float, *, epoch: float = EPOCH, time_scale: float = 1.0,
                  ) -> Iterator[tuple[float, str, bytes]]:
        """Every datagram the sensors send in [0, duration), in capture-time order.

        Yields (capture time in simulation seconds, sensor id, datagram).
        ``epoch``/``time_scale``: the sensors' clocks read ``epoch + offset +
        capture * time_scale * (1 + drift)`` (real-time runs pass the wall
        clock and 1/speed).
        """
        for item in self._stream(duration, epoch, time_scale):
            yield item[0], item[1].id, item[2]

    def _stream(self, duration: float, epoch: float, time_scale: float,
                ) -> Iterator[tuple[float, _SensorRun, bytes]]:
        runs = self._runs()
        heap: list[tuple[float, int, int, str]] = []
        for run in runs:
            if run.is_plugged(0.0):
                heap.append((0.0, run.index, 0, "register"))
            for when, plugged in run.plugged[1:]:
                if plugged:
                    heap.append((when, run.index, 0, "register"))
            heap.append((run.frame_time(0), run.index, 1, "frame"))
        heapq.heapify(heap)
        cache: dict[float, list] = {}  # truth by capture time (sensors may share a time)
        while heap:
            t, index, _, kind = heapq.heappop(heap)
            if t >= duration:
                continue
            run = runs[index]
            if kind == "register":
                run.reset()
                yield t, run, run.encoder.register()
                continue
            run.k += 1
            sd = run.model.frame_jitter_s
            # jitter cut at 3 s.d., so the stream below can bound how far captures reorder
            capture = t + float(np.clip(run.rng.normal(0.0, sd), -3 * sd, 3 * sd)) if sd > 0 else t
            heapq.heappush(heap, (run.frame_time(run.k), index, 1, "frame"))
            dropped = run.rng.random() < run.model.drop_p
            if not run.is_plugged(t) or dropped or not run.in_take(t):
                continue
            capture = max(capture, 0.0)
            data = self._frame(run, capture, cache, epoch, time_scale)
            if len(cache) > 64:
                cache.clear()
            if data is not None:
                yield capture, run, data

    def _frame(self, run: _SensorRun, t: float, cache: dict, epoch: float,
               time_scale: float) -> bytes | None:
        # the body as it was one pipeline delay before the frame's capture stamp
        shown = max(t - run.pipeline_delay(), 0.0)
        truth = cache.get(shown)
        if truth is None:
            truth = cache[shown] = [(p, p.state(shown)) for p in self.performers]
        present = [(p, s) for p, s in truth if s is not None]
        model = run.model
        pose = run.pose_at(t)
        bodies: list[BodyFrame] = []
        nan_users = set()
        if present:
            stage = np.stack([s[0] for _, s in present])
            cam = pose.observe(stage)
            vis = visibility(model, cam, np.array([self._scales[p.name] for p, _ in present]))
            for k, (performer, (_, hands)) in enumerate(present):
                track = run.tracks.get(performer.name)
                visible = body_visible(vis, k)
                if track is None:
                    if not visible:
                        continue
                    track = run.tracks[performer.name] = UserTrack(run.rng, model)
                if not track.update(visible, t, model):
                    if track.visible_since is None:
                        del run.tracks[performer.name]
                    continue
                joints, conf = measure(model, track, run.rng, cam[k], vis.in_fov[k],
                                       vis.hidden_self[k], vis.hidden_other[k])
                true_hands = hands
                if model.mirror_back and faces_away(cam[k]):
                    joints, conf = mirrored(joints, conf)
                    true_hands = (hands[1], hands[0])
                # (read every frame, so the random stream does not depend on how often the
                # sensor updates them; repeated between its updates)
                seen = track.hands(tuple(sensed_hand(model, run.rng, true_hands[h],
                                                     float(conf[_HAND[h]]),
                                                     float(np.linalg.norm(cam[k][_HAND[h]])))
                                         for h in (0, 1)), model)
                bodies.append(BodyFrame(performer.name, joints, conf, seen))  # type: ignore[arg-type]
                if run.rng.random() < model.nan_p:
                    nan_users.add(performer.name)
        for name in [n for n in run.tracks if n not in {p.name for p, _ in present}]:
            del run.tracks[name]  # left the stage: the sensor loses them at once
        floor = None
        if t >= run.next_floor:
            floor = pose.floor_plane()
            run.next_floor = t + model.floor_every_s
        timetag = epoch + run.offset + t * time_scale * (1.0 + run.drift)
        return run.encoder.frame(bodies, timetag, floor, frozenset(nan_users))

    def stream(self, duration: float, *, epoch: float = EPOCH, time_scale: float = 1.0,
               ) -> Iterator[Datagram]:
        """The datagrams in arrival order, with their simulated arrival times.

        Arrival = capture + the sensor's latency + network jitter (exponential,
        mean ``network.jitter_s``, at most 5 ms); a sensor's own datagrams
        never overtake each other.
        """
        runs = {r.id: r for r in self._runs()}
        # captures come out of _stream in nominal-time order; with jitter cut at 3 s.d. a
        # later capture is never more than 6 s.d. earlier than one already seen
        slack = 6 * max((r.model.frame_jitter_s for r in runs.values()), default=0.0) + 1e-6
        jitter = self.scenario.network_jitter_s
        pending: list[tuple[float, int, Datagram]] = []
        n = 0
        for capture, run, data in self._stream(duration, epoch, time_scale):
            net = runs[run.id]
            delay = net.latency + (min(float(net.net_rng.exponential(jitter)), JITTER_CAP_S)
                                   if jitter > 0 else 0.0)
            arrival = max(capture + delay, net.last_arrival)
            net.last_arrival = arrival
            heapq.heappush(pending, (arrival, n, Datagram(capture, arrival, run.id, run.source,
                                                          data)))
            n += 1
            while pending and pending[0][0] <= capture - slack:
                yield heapq.heappop(pending)[2]
        while pending:
            yield heapq.heappop(pending)[2]

    # ------------------------------------------------------------ consumers
    def record(self, path: str, duration: float, truth_path: str | None = None,
               meta: dict | None = None) -> int:
        """Write ``duration`` seconds of the scenario to a recording (and the truth)."""
        from ..recording import RecordingWriter
        from .truth import write_truth
        n = 0
        with RecordingWriter(path, {**self.meta(), **(meta or {})}) as writer:
            for d in self.stream(duration):
                writer.write(d.arrival, d.source, d.data, d.capture)
                n += 1
        if truth_path:
            write_truth(self, truth_path, duration)
        return n

    def meta(self) -> dict:
        """What a recording of this simulator says about itself (JSON)."""
        return {"source": "stage sim", "scenario": self.scenario.name,
                "scenario_path": self.scenario.path, "seed": self.seed,
                "rig": self.rig(True).to_dict(),
                "sensors": {sid: {"to_stage": [[float(v) for v in row] for row in p.to_stage]}
                            for sid, p in self.sensor_poses(0.0).items()},
                "clocks": self.sensor_clocks()}

    def run_realtime(self, target: tuple[str, int], duration: float | None = None,
                     speed: float = 1.0, stop_event: threading.Event | None = None,
                     recorder=None) -> int:
        """Send the scenario over UDP in real time (``speed`` x), one socket per sensor.

        ``speed = math.inf`` sends as fast as possible. Blocks until
        ``duration`` simulated seconds are sent (None: until ``stop_event``).
        Returns the number of datagrams sent.
        """
        from ..clients.osc import UdpSender
        stop = stop_event or threading.Event()
        senders = {spec.id: UdpSender(target) for spec in self.scenario.sensors}
        wall0, mono0 = time.time(), time.monotonic()
        scale = 1.0 / speed if math.isfinite(speed) else 1.0
        sent = 0
        length = duration if duration is not None else math.inf
        try:
            for d in self.stream(length, epoch=wall0, time_scale=scale):
                if math.isfinite(speed):
                    delay = mono0 + d.arrival / speed - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        break
                if stop.is_set():
                    break
                senders[d.sensor].send(d.data)
                if recorder is not None:
                    recorder.write(time.monotonic(), d.source, d.data, None)
                sent += 1
        finally:
            for s in senders.values():
                s.close()
        return sent


class SimSource(ThreadedSource):
    """The built-in simulator as a source: virtual Kinects watching scripted performers.

    ``scenario``: a built-in name, a YAML path, a ``Scenario`` or None (the
    default scenario); ``duration``: seconds to run (default: the scenario's
    own, else until stopped); ``speed``: x real time live (``math.inf``: as
    fast as possible).
    """

    name = "sim"
    description = "the built-in simulator: virtual Kinects watching scripted performers"
    offline = True

    def __init__(self, scenario: "str | Scenario | None" = None, seed: int = 1,
                 duration: float | None = None, speed: float = 1.0,
                 sim: Simulator | None = None, sensors: int | None = None) -> None:
        super().__init__()
        if sensors is not None:  # a built-in scenario with this many sensors on its ring
            if sim is not None or isinstance(scenario, Scenario):
                raise ConfigError("'sensors' goes with the name of a built-in scenario")
            scenario = builtin_with_ring(scenario or "default", count=sensors)
        self.sim = sim or Simulator(scenario or None, seed)
        self._duration = duration if duration is not None else self.sim.scenario.duration
        self.speed = speed

    def describe(self) -> str:
        return f"simulator (scenario '{self.sim.scenario.name}', seed {self.sim.seed})"

    def rig(self) -> Rig:
        return self.sim.rig()

    @property
    def duration(self) -> float | None:
        return self._duration

    def items(self) -> Iterator[tuple[float, tuple[str, int], bytes]]:
        if not self._duration:
            raise ConfigError("an offline simulation needs a duration (the scenario has no end)")
        for d in self.sim.stream(self._duration):
            yield d.arrival, d.source, d.data

    def _run(self, target: tuple[str, int], stop: threading.Event) -> None:
        self.sent = self.sim.run_realtime(target, self._duration, self.speed, stop)
