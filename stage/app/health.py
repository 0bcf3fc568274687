"""Health of a live show for an installer who is not in the room (docs/installing.md).

Every second a ``HealthMonitor`` thread asks the engine thread for its state
(``Engine.call_soon``: an engine that does not answer within two seconds is
itself reported), reads the views' counters, and builds one dict:

- per sensor: connected, frames per second, seconds since last heard,
  calibration state and reason (``stage.views.status.sensor_health``);
- per view: alive, frames waiting, errors (plugin views and OSC views);
- per synth (MIDI port): connected, reconnecting, errors;
- the engine: frame time p99 (ms per batch), resident memory, CPU, drops,
  the kernel's receive-queue drops; and the live calibrator's restarts.

It is published to the monitor page (``ViewHost.health`` rides on the
status), answered over OSC (``/stage/health``, docs/osc-api.md), logged as
one summary line a minute, and watched: a part down or suspect for longer
than ``alerts.after_s`` fires the alert hook (a command and/or an OSC
message ``/stage/alert``) once, and again when it recovers.
"""

from __future__ import annotations

import logging
import os
import queue
import shlex
import socket
import subprocess
import threading
import time
from typing import Any, Callable

from ..network import parse_hostport
from ..sensors.protocol import encode_message
from ..settings import AlertSettings
from ..views.status import sensor_health

log = logging.getLogger("stage.health")

#: an engine that has not answered a health request for this long is reported down
ENGINE_ANSWER_S = 2.0
#: text fields in health and alerts are cut to this many characters
MAX_TEXT = 160
#: an alert command running longer than this is killed
COMMAND_TIMEOUT_S = 30.0


def rss_bytes() -> int | None:
    """Resident memory of this process (Linux /proc; elsewhere the peak from getrusage)."""
    try:
        with open("/proc/self/statm", encoding="ascii") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        pass
    try:
        import resource
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak if os.uname().sysname == "Darwin" else peak * 1024
    except Exception:  # no resource module (Windows): unknown
        return None


def _short(text: Any) -> str:
    text = str(text)
    return text if len(text) <= MAX_TEXT else text[:MAX_TEXT - 1] + "~"


class Alerter:
    """Runs the alert command and/or sends ``/stage/alert``; never blocks the caller long."""

    def __init__(self, settings: AlertSettings) -> None:
        self.settings = settings
        self.sent: list[dict] = []      # every alert raised (tests, the summary)
        self._queue: queue.Queue = queue.Queue()
        self._worker: threading.Thread | None = None
        self._osc: tuple[str, int] | None = parse_hostport(settings.osc) if settings.osc else None
        self._sock: socket.socket | None = None

    def fire(self, state: str, part: str, name: str, seconds: float, reason: str) -> None:
        alert = {"state": state, "part": part, "name": name, "seconds": round(seconds, 1),
                 "reason": _short(reason)}
        self.sent.append(alert)
        del self.sent[:-100]
        text = (f"stage: {part} {name} {state}" + (f" for {seconds:.0f} s" if state != "recovered"
                                                  else "") + (f": {reason}" if reason else ""))
        (log.warning if state != "recovered" else log.info)("alert: %s", text)
        if self.settings.command:
            self._run(alert, text)
        if self._osc is not None:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                self._sock.sendto(encode_message("/stage/alert", state, part, name,
                                                 float(seconds), alert["reason"]), self._osc)
            except OSError as exc:
                log.error("could not send the alert to %s:%d: %s", *self._osc, exc)

    def _run(self, alert: dict, text: str) -> None:
        env = dict(os.environ, STAGE_ALERT_STATE=alert["state"], STAGE_ALERT_PART=alert["part"],
                   STAGE_ALERT_NAME=alert["name"], STAGE_ALERT_SECONDS=str(alert["seconds"]),
                   STAGE_ALERT_REASON=alert["reason"], STAGE_ALERT_TEXT=text)
        if self._queue.qsize() >= 100:  # the command hangs: do not pile up more
            log.error("alert command backlog full; this alert is only logged")
            return
        self._queue.put(env)
        if self._worker is None:
            self._worker = threading.Thread(target=self._commands, name="stage-alert",
                                            daemon=True)
            self._worker.start()

    def _commands(self) -> None:
        """Run the alert commands one at a time, in order (down before recovered)."""
        while True:
            env = self._queue.get()
            if env is None:
                return
            try:
                done = subprocess.run(shlex.split(self.settings.command), env=env,
                                      stdin=subprocess.DEVNULL, timeout=COMMAND_TIMEOUT_S)
                if done.returncode:
                    log.error("the alert command exited with status %d", done.returncode)
            except subprocess.TimeoutExpired:
                log.error("the alert command took longer than %g s; killed", COMMAND_TIMEOUT_S)
            except (OSError, ValueError) as exc:
                log.error("could not run the alert command %r: %s", self.settings.command, exc)
            finally:
                self._queue.task_done()

    def close(self, wait_s: float = 5.0) -> None:
        """Let queued alert commands finish (up to ``wait_s``), then stop."""
        if self._worker is not None:
            deadline = time.monotonic() + wait_s
            while self._queue.unfinished_tasks and time.monotonic() < deadline:
                time.sleep(0.02)
            self._queue.put(None)
            self._worker.join(max(0.0, deadline - time.monotonic()) + 0.1)
            self._worker = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class HealthMonitor:
    """See the module docstring. ``poll()`` does one round (the thread calls it every second).

    engine: the live engine; host: the ViewHost (or None); calibrator: the live
    calibrator (or None); status: the console status line (or None), which is
    given an idle line when no frame printed one.
    """

    def __init__(self, engine: Any, host: Any = None, calibrator: Any = None,
                 alerts: AlertSettings | None = None, status: Any = None,
                 every_s: float = 1.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.engine, self.host, self.calibrator, self.status = engine, host, calibrator, status
        self.alerts = Alerter(alerts or AlertSettings())
        self.every_s = every_s
        self.clock = clock
        self.latest: dict[str, Any] = {}
        self._bad_since: dict[str, tuple[float, str]] = {}
        self._alerted: set[str] = set()
        self._frames: tuple[float, dict[str, int]] | None = None
        self._cpu: tuple[float, float] | None = None
        self._next_summary = clock() + (alerts or AlertSettings()).summary_every_s
        self._crashes_seen = (0, float("-inf"))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.rounds = 0

    # ------------------------------------------------------------ thread
    def start(self) -> "HealthMonitor":
        self.engine.health_messages = self.messages
        self._thread = threading.Thread(target=self._run, name="stage-health", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self.alerts.close()

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            try:
                self.poll()
            except Exception:  # health must never take the show down
                log.exception("health check failed")

    # ------------------------------------------------------------ one round
    def _engine_state(self) -> dict | None:
        """The engine's state, read on its own thread; None when it does not answer."""
        box: dict[str, Any] = {}
        done = threading.Event()
        status = self.status

        def read(engine: Any) -> None:
            box["stats"] = engine.stats()
            box["batch_ms"] = engine.batch_time.summary_ms()
            box["skeletons"] = {cid: c.skeletons for cid, c in engine.clients.items()}
            box["queue"] = engine.queue.qsize()
            box["views"] = engine.output.describe(engine.clock.now())
            box["rig_sensors"] = list(engine.rig.sensors)
            if status is not None and hasattr(status, "idle"):
                status.idle(engine.clock.now())
            done.set()
        try:
            self.engine.call_soon(read)
        except Exception:
            return None
        return box if done.wait(ENGINE_ANSWER_S) else None

    def poll(self) -> dict[str, Any]:
        now = self.clock()
        state = self._engine_state()
        health: dict[str, Any] = {"time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                                  "sensors": {}, "views": {}, "synths": {}}
        health["engine"] = self._engine(state, now)
        if state is not None:
            health["sensors"] = self._sensors(state, now)
            for view in state["views"]:
                ok = view.get("refused", 0) == 0
                health["views"][f"osc {view['address']}"] = {
                    "ok": ok, "alive": True, "queue": 0, "errors": view.get("refused", 0),
                    "reason": "" if ok else f"{view['refused']} datagram(s) refused"}
        self._host_parts(health)
        health["calibrator"] = self._calibrator(now)
        problems = [f"{part} {name}: {entry.get('reason') or 'not ok'}"
                    for part, name, entry in _parts(health) if not entry.get("ok", True)]
        health["ok"] = not problems
        health["problems"] = problems
        self.latest = health
        if self.host is not None:
            self.host.health = health  # the monitor page shows it with the next status
        self._watch(health, now)
        if now >= self._next_summary:
            self._next_summary = now + self.alerts.settings.summary_every_s
            log.info("health: %s", summary_line(health))
        self.rounds += 1
        return health

    def _engine(self, state: dict | None, now: float) -> dict[str, Any]:
        cpu_now = time.process_time()
        cpu = None
        if self._cpu is not None and now > self._cpu[0]:
            cpu = 100.0 * (cpu_now - self._cpu[1]) / (now - self._cpu[0])
        self._cpu = (now, cpu_now)
        rss = rss_bytes()
        out: dict[str, Any] = {"rss_mb": None if rss is None else round(rss / 2**20, 1),
                               "cpu_percent": None if cpu is None else round(cpu, 1)}
        if state is None:
            out.update(ok=False, reason=f"the engine did not answer within {ENGINE_ANSWER_S:g} s")
            return out
        stats, batch = state["stats"], state["batch_ms"]
        p99 = batch.get("p99")
        out.update(uptime_s=stats["uptime_s"], frame_ms_p99=None if p99 is None else round(p99, 3),
                   queue=state["queue"], drops_total=stats["drops_total"],
                   kernel_drops=sum(stats["drops"].get("(kernel)", {}).values()),
                   persons=len(stats["persons"]), clients=len(stats["clients"]))
        out["ok"] = True
        if p99 is not None and p99 > 100.0:
            out.update(ok=False, reason=f"frame time p99 {p99:.0f} ms (engine far behind)")
        return out

    def _sensors(self, state: dict, now: float) -> dict[str, Any]:
        stats = state["stats"]
        frames = {cid: c["frames"] for cid, c in stats["clients"].items()}
        previous, self._frames = self._frames, (now, frames)
        out: dict[str, Any] = {}
        listed = set(state["rig_sensors"])
        for cid, client in stats["clients"].items():
            # a client that never sent a skeleton and is not in the rig is not a sensor to
            # watch (a stray /registerDevice must not raise alerts for weeks)
            if cid not in listed and not state["skeletons"].get(cid) and not client["active"]:
                continue
            rate = 0.0
            if previous is not None and now > previous[0]:
                rate = max(0.0, (frames[cid] - previous[1].get(cid, frames[cid]))
                           / (now - previous[0]))
            ok, reason, fitness, cal_state = sensor_health(client)
            out[cid] = {"ok": ok, "connected": bool(client["active"]), "rate_hz": round(rate, 1),
                        "last_seen_s": client["silent_s"], "calibration": cal_state or (
                            "calibrated" if client["calibrated"] else "uncalibrated"),
                        "fitness": fitness, "reason": _short(reason)}
        for sid in listed - out.keys():
            out[sid] = {"ok": False, "connected": False, "rate_hz": 0.0, "last_seen_s": None,
                        "calibration": "", "fitness": None,
                        "reason": "in the rig but never connected"}
        return out

    def _host_parts(self, health: dict[str, Any]) -> None:
        host = self.host
        if host is None:
            return
        for name, view in host.stats().items():
            own = view.get("view", {}) or {}
            state = view.get("state")
            ok = state in ("running", "loaded")
            health["views"][name] = {
                "ok": ok, "alive": ok, "queue": view.get("frames_pending", 0),
                "errors": int(own.get("send_errors", 0) or 0),
                "dropped": view.get("frames_dropped", 0) + view.get("events_dropped", 0),
                "reason": "" if ok else _short(f"{state}: {view.get('error') or ''}")}
            for port, p in (own.get("ports") or {}).items():
                connected = bool(p.get("connected"))
                health["synths"][port] = {
                    "ok": connected, "connected": connected,
                    "reconnecting": bool(p.get("reconnecting")), "errors": p.get("errors", 0),
                    "reason": "" if connected else _short(p.get("reason") or "disconnected")}

    def _calibrator(self, now: float) -> dict[str, Any]:
        cal = self.calibrator
        if cal is None:
            return {"ok": True, "running": False, "crashes": 0, "last_crash": ""}
        crashes = getattr(cal, "crashes", 0)
        out = {"ok": True, "running": True, "crashes": crashes,
               "last_crash": _short(getattr(cal, "last_crash", ""))}
        if crashes != self._crashes_seen[0]:
            self._crashes_seen = (crashes, now)
        if crashes and now - self._crashes_seen[1] < 60.0:  # restarted a moment ago: suspect for a minute
            out.update(ok=False, reason=f"restarted after a failure: {out['last_crash']}")
        return out

    # ------------------------------------------------------------ alerts
    def _watch(self, health: dict[str, Any], now: float) -> None:
        after = self.alerts.settings.after_s
        bad_now: set[str] = set()
        for part, name, entry in _parts(health):
            key = f"{part}\0{name}"
            if entry.get("ok", True):
                continue
            bad_now.add(key)
            since, _ = self._bad_since.setdefault(key, (now, ""))
            self._bad_since[key] = (since, str(entry.get("reason", "")))
            if key not in self._alerted and now - since >= after:
                self._alerted.add(key)
                state = "down" if entry.get("connected") is False or part == "engine" else "suspect"
                self.alerts.fire(state, part, name, now - since, str(entry.get("reason", "")))
        for key in list(self._bad_since):
            if key not in bad_now:
                since, reason = self._bad_since.pop(key)
                if key in self._alerted:
                    self._alerted.discard(key)
                    part, name = key.split("\0", 1)
                    self.alerts.fire("recovered", part, name, now - since, "")

    # ------------------------------------------------------------ OSC
    def messages(self) -> list[bytes]:
        """The latest health as OSC messages (docs/osc-api.md); engine thread, no waiting."""
        h = self.latest
        if not h:
            return [encode_message("/stage/health", 0, 1, "no health check has run yet")]
        out = [encode_message("/stage/health", int(h["ok"]), len(h["problems"]),
                              _short(summary_line(h)))]
        for sid, s in sorted(h["sensors"].items()):
            out.append(encode_message("/stage/health/sensor", _short(sid), int(s["ok"]),
                                      int(s["connected"]), float(s["rate_hz"]),
                                      float(s["last_seen_s"] if s["last_seen_s"] is not None
                                            else -1.0),
                                      _short(s["calibration"]), _short(s["reason"])))
        for name, v in sorted(h["views"].items()):
            out.append(encode_message("/stage/health/view", _short(name), int(v["ok"]),
                                      int(v["alive"]), int(v["queue"]), int(v["errors"]),
                                      _short(v["reason"])))
        for port, p in sorted(h["synths"].items()):
            out.append(encode_message("/stage/health/synth", _short(port), int(p["ok"]),
                                      int(p["connected"]), int(p["reconnecting"]),
                                      int(p["errors"]), _short(p["reason"])))
        e = h["engine"]
        out.append(encode_message("/stage/health/engine", int(e["ok"]),
                                  float(e.get("frame_ms_p99") or 0.0),
                                  float(e.get("rss_mb") or 0.0), float(e.get("cpu_percent") or 0.0),
                                  float(e.get("uptime_s") or 0.0), int(e.get("drops_total") or 0),
                                  int(e.get("kernel_drops") or 0), _short(e.get("reason", ""))))
        c = h["calibrator"]
        out.append(encode_message("/stage/health/calibrator", int(c["ok"]), int(c["crashes"]),
                                  _short(c["last_crash"])))
        return out[:256]


def _parts(health: dict[str, Any]):
    for part in ("sensors", "views", "synths"):
        for name, entry in health.get(part, {}).items():
            yield part[:-1], name, entry
    for part in ("engine", "calibrator"):
        if part in health:
            yield part, part, health[part]


def summary_line(health: dict[str, Any]) -> str:
    """One line: the counts that matter and what is wrong."""
    sensors = health.get("sensors", {})
    ok_sensors = sum(1 for s in sensors.values() if s["ok"])
    e = health.get("engine", {})
    parts = [f"{ok_sensors}/{len(sensors)} sensors ok",
             f"{len(health.get('views', {}))} views",
             f"{sum(1 for p in health.get('synths', {}).values() if p['ok'])}/"
             f"{len(health.get('synths', {}))} synths ok"]
    if e.get("frame_ms_p99") is not None:
        parts.append(f"frame p99 {e['frame_ms_p99']:.2f} ms")
    if e.get("rss_mb") is not None:
        parts.append(f"rss {e['rss_mb']:.0f} MB")
    if e.get("cpu_percent") is not None:
        parts.append(f"cpu {e['cpu_percent']:.0f} %")
    if e.get("persons") is not None:
        parts.append(f"{e['persons']} on stage")
    if e.get("drops_total"):
        parts.append(f"drops {e['drops_total']}")
    problems = health.get("problems", [])
    head = "ok" if not problems else f"{len(problems)} problem(s): " + "; ".join(problems[:5])
    return head + " | " + ", ".join(parts)
