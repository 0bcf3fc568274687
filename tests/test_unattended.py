"""Running for weeks: health, alerts, logs, the service unit, the idle section, replay pace.

docs/installing.md describes what these check: health per sensor, view,
synth and engine (monitor, OSC, a line a minute), the alert hook (a command
and an OSC message), logs with dates or to the journal, ``stage
install-service``, the piece's attract section, and ``stage replay --to``
keeping time at any speed.
"""

from __future__ import annotations

import logging
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import LOCALHOST, Peer, Sensor, query_stats
from stage.app.health import HealthMonitor, summary_line
from stage.app.server import Server
from stage.app.status_line import StatusLine
from stage.clock import ManualClock
from stage.cli.main import _JournalFormatter, main
from stage.cli.service import unit_text
from stage.engine.engine import Engine
from stage.events import SectionChange
from stage.frames import Body, FusedFrame
from stage.joints import HandState
from stage.piece.loader import load_piece
from stage.piece.runtime import PieceRuntime, RecordingSink
from stage.rig import Rig, load_rig
from stage.sensors.protocol import encode_client_joints
from stage.sensors.sim import standing_pose
from stage.settings import AlertSettings

REPO = Path(__file__).resolve().parent.parent


class ManualHealthClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def live_engine() -> tuple[Engine, threading.Event, threading.Thread]:
    engine = Engine(Rig())
    stop = threading.Event()
    thread = threading.Thread(target=engine.run, args=(stop,), daemon=True)
    thread.start()
    return engine, stop, thread


# ---------------------------------------------------------------- health and alerts

def test_health_reports_sensors_views_engine_and_alerts_once_then_on_recovery(tmp_path):
    engine, stop, thread = live_engine()
    out = tmp_path / "alerts.txt"
    command = (f"{shlex.quote(sys.executable)} -c \"import os; open({str(out)!r}, 'a').write("
               f"os.environ['STAGE_ALERT_STATE'] + ' ' + os.environ['STAGE_ALERT_PART'] + ' ' + "
               f"os.environ['STAGE_ALERT_NAME'] + chr(10))\"")
    listener = Peer()
    clock = ManualHealthClock()
    health = HealthMonitor(engine, alerts=AlertSettings(after_s=30.0, command=command,
                                                        osc=f"{LOCALHOST}:{listener.port}"),
                           clock=clock)
    try:
        body = standing_pose((0.0, 2.5), np.pi)
        engine.handle_datagram(encode_client_joints("kin", 0, body, np.ones(25)),
                               ("127.0.0.1", 5000))  # not thread-safe in general; idle engine
        h = health.poll()
        assert h["sensors"]["kin"]["connected"] and h["engine"]["ok"]
        assert h["engine"]["rss_mb"] > 0
        # the sensor goes silent: down, but an alert only after 30 s of it
        engine.call_soon(lambda e: e.tick(e.clock.now() + 5.0))
        clock.t += 1.0
        h = health.poll()
        assert not h["sensors"]["kin"]["ok"] and "silent" in h["sensors"]["kin"]["reason"]
        assert health.alerts.sent == []
        clock.t += 31.0
        health.poll()
        clock.t += 1.0
        health.poll()                                 # still down: no second alert
        assert [a["state"] for a in health.alerts.sent] == ["down"]
        msg = listener.wait_for(lambda m: m.address == "/stage/alert")
        assert msg.params[:3] == ("down", "sensor", "kin") and msg.params[3] >= 30.0
        # it comes back: one 'recovered'
        engine.handle_datagram(encode_client_joints("kin", 0, body, np.ones(25)),
                               ("127.0.0.1", 5000))
        clock.t += 1.0
        h = health.poll()
        assert h["sensors"]["kin"]["ok"]
        assert [a["state"] for a in health.alerts.sent] == ["down", "recovered"]
        listener.wait_for(lambda m: m.address == "/stage/alert" and m.params[0] == "recovered")
        health.alerts.close()
        assert out.read_text().splitlines() == ["down sensor kin", "recovered sensor kin"]
        line = summary_line(h)
        assert line.startswith("ok |") and "1/1 sensors ok" in line
    finally:
        stop.set()
        thread.join(5)
        listener.close()


def test_an_engine_that_does_not_answer_is_reported():
    engine = Engine(Rig())          # no thread runs it: call_soon is never served
    health = HealthMonitor(engine, clock=ManualHealthClock())
    h = health.poll()
    assert not h["engine"]["ok"] and "did not answer" in h["engine"]["reason"]
    assert not h["ok"] and h["problems"]


def test_a_calibrator_restart_shows_in_health_for_a_minute():
    class Cal:
        crashes, last_crash = 0, ""
    engine, stop, thread = live_engine()
    clock = ManualHealthClock()
    cal = Cal()
    health = HealthMonitor(engine, calibrator=cal, clock=clock)
    try:
        assert health.poll()["calibrator"]["ok"]
        cal.crashes, cal.last_crash = 1, "frame of k: IndexError: boom"
        clock.t += 1
        c = health.poll()["calibrator"]
        assert not c["ok"] and "IndexError" in c["reason"] and c["crashes"] == 1
        clock.t += 61
        assert health.poll()["calibrator"]["ok"]
    finally:
        stop.set()
        thread.join(5)


@pytest.mark.integration
def test_health_is_answered_over_osc_at_the_documented_addresses():
    with Server(Rig(), LOCALHOST, 0) as server:
        health = HealthMonitor(server.engine, clock=ManualHealthClock())
        server.engine.health_messages = health.messages
        sensor = Sensor("kin", server.address)
        sensor.register()
        sensor.frame(0, standing_pose((0.0, 2.5), np.pi))
        query_stats(server.address)
        health.poll()
        asker = Peer()
        asker.send_message(server.address, "/stage/health")
        head = asker.wait_for(lambda m: m.address == "/stage/health")
        s = asker.wait_for(lambda m: m.address == "/stage/health/sensor")
        e = asker.wait_for(lambda m: m.address == "/stage/health/engine")
        c = asker.wait_for(lambda m: m.address == "/stage/health/calibrator")
        sensor.close()
        asker.close()
    assert head.typetags == "iis" and head.params[0] == 1
    assert s.typetags == "siiffss" and s.params[:3] == ("kin", 1, 1)
    assert e.typetags == "ifffffiis" or e.typetags == "iffffiis"
    assert c.typetags == "iis"
    doc = (REPO / "docs" / "osc-api.md").read_text()
    for address in ("/stage/health", "/stage/health/sensor", "/stage/health/view",
                    "/stage/health/synth", "/stage/health/engine", "/stage/health/calibrator",
                    "/stage/alert"):
        assert f"`{address}" in doc, address


def test_the_status_line_speaks_when_nothing_is_fused():
    import io
    clock = ManualClock(10.0)
    engine = Engine(Rig(), clock)
    out = io.StringIO()
    status = StatusLine(engine, out=out)
    clock.advance(1.5)
    status.idle(clock.now())
    assert "nobody on stage" in out.getvalue() and out.getvalue().count("\n") == 1
    status.idle(clock.now())               # at most one line a second
    assert out.getvalue().count("\n") == 1


# ---------------------------------------------------------------- logs

def test_the_log_file_has_dates_and_the_journal_gets_priorities(tmp_path):
    log_file = tmp_path / "stage.log"
    root = logging.getLogger()
    level = root.level
    try:
        assert main(["--log-file", str(log_file), "plugins"]) == 0
        logging.getLogger("stage.test").warning("a line for the installer")
    finally:
        for handler in [h for h in root.handlers if getattr(h, "_stage", False)]:
            root.removeHandler(handler)
            handler.close()
        root.setLevel(level)
    line = [ln for ln in log_file.read_text().splitlines() if "for the installer" in ln][0]
    assert line[:10].count("-") == 2 and line[4] == "-"      # 2026-11-22 ...
    fmt = _JournalFormatter("%(levelname)s %(name)s: %(message)s")
    record = logging.LogRecord("stage.x", logging.WARNING, "", 0, "two\nlines", None, None)
    assert fmt.format(record) == "<4>WARNING stage.x: two\n<4>lines"


def test_a_rig_file_made_read_only_is_not_rewritten(tmp_path):
    from stage.engine.rigstore import RigStore
    path = tmp_path / "rig.yaml"
    path.write_text("# the installer's notes\nreference: a\nsensors: {a: {}}\n")
    path.chmod(0o444)
    rig = load_rig(str(path))
    store = RigStore(threaded=False)
    store.save(rig, str(path), "a calibration")
    assert path.read_text().startswith("# the installer's notes")
    assert store.errors == 1


# ---------------------------------------------------------------- the service unit

def test_the_service_unit_restarts_on_failure_and_stops_cleanly():
    text = unit_text(["serve", "--rig", "/etc/stage/my rig.yaml"], "gallery", False, "/srv/show")
    assert "Restart=on-failure" in text and "SuccessExitStatus=130" in text
    assert 'ExecStart=' in text and '"/etc/stage/my rig.yaml"' in text
    assert "WantedBy=multi-user.target" in text
    assert "WantedBy=default.target" in unit_text(["play", "p.yaml"], "s", True, "/x")
    with pytest.raises(Exception, match="not a command to run as a service"):
        unit_text(["stats"], "s", False, "/x")


def test_systemd_accepts_the_unit_and_its_command_runs_and_stops_on_sigterm(tmp_path):
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze not installed (apt-get install systemd)")
    rig = tmp_path / "rig.yaml"
    rig.write_text("server: {host: 127.0.0.1, port: 7799}\n")
    unit = tmp_path / "stage-test.service"
    text = unit_text(["serve", "--rig", str(rig), "--port", "0"], "stage-test", False,
                     str(tmp_path))
    unit.write_text(text)
    done = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stderr
    # what systemd would run: ExecStart's words, in WorkingDirectory, stopped with SIGTERM
    exec_start = next(ln for ln in text.splitlines() if ln.startswith("ExecStart="))
    argv = shlex.split(exec_start.split("=", 1)[1])
    proc = subprocess.Popen(argv, cwd=tmp_path, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        deadline = time.monotonic() + 30
        lines = []
        while time.monotonic() < deadline:
            line = proc.stderr.readline()
            lines.append(line)
            if "listening for sensors" in line:
                break
        assert any("listening for sensors" in ln for ln in lines), lines
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 130          # SuccessExitStatus: a clean stop, not a failure to restart


# ---------------------------------------------------------------- the idle section

IDLE_PIECE = """
piece: idle test
idle: {after: 5, section: attract, back: previous}
sections:
  - name: main
  - name: second
  - name: attract
    on_enter: [{program: 2}]
"""


def test_the_attract_section_plays_while_the_room_is_empty(tmp_path):
    path = tmp_path / "idle.yaml"
    path.write_text(IDLE_PIECE)
    piece = load_piece(str(path))
    sink = RecordingSink(None)
    runtime = PieceRuntime(piece, sink, seed=1)
    runtime.start(0.0)
    runtime.goto("second", 0.5)
    for t in range(1, 8):
        runtime.tick(float(t))
    assert runtime.section.name == "attract"
    joints = standing_pose((0.0, 2.0), 0.0)
    body = Body(1, joints, np.ones(25), np.zeros((25, 3)), (HandState.UNKNOWN,) * 2, joints[0],
                ("k",))
    runtime.on_frame(FusedFrame(8.0, {1: body}, (1,), (1,), ()))
    assert runtime.section.name == "second"         # back: previous
    changes = [(e.section, e.cause) for e in sink.events if isinstance(e, SectionChange)]
    assert changes[-2:] == [("attract", "idle"), ("second", "someone arrived")]


def test_an_idle_section_that_does_not_exist_is_a_user_error(tmp_path):
    path = tmp_path / "idle.yaml"
    path.write_text(IDLE_PIECE.replace("section: attract", "section: atract"))
    with pytest.raises(Exception, match=r"idle.yaml:3:\d+: .*atract"):
        load_piece(str(path))


# ---------------------------------------------------------------- replay keeps time

@pytest.mark.integration
def test_replay_at_max_speed_into_a_server_fuses_every_frame(tmp_path):
    from stage.app.show import Show, ShowOptions
    from stage.sensors.replay import ReplaySource
    from stage.sensors.sim import Simulator
    from stage.sensors.recording import read_recording
    from stage.sensors.replay import rig_from_meta
    rec = tmp_path / "take.rec"
    Simulator("default", seed=3).record(str(rec), duration=6.0)
    offline = Show(ShowOptions(replay=str(rec), offline=True, plugins=False,
                               self_healing=False)).run()
    rig = rig_from_meta(read_recording(str(rec)).meta)
    rig.port = 0
    with Server(rig, host=LOCALHOST) as server:
        source = ReplaySource(str(rec), speed=float("inf")).start(server.address)
        assert source.wait(30.0)
        stats = query_stats(server.address)
    want, got = offline.stats["counts"], stats["counts"]
    assert got["frames"] == want["frames"]
    # every frame fused: each one folded into its person, as in the deterministic offline
    # run, none dropped as late. A 30x-compressed time line (datagrams without their
    # capture times) folds in a handful and drops the rest as late. (How many updates go
    # out differs: a backlog is fused as one batch, each person sent once.)
    assert stats["fusion"]["views"] == offline.stats["fusion"]["views"] == want["frames"]
    assert stats["fusion"]["late"] == 0 and not any(
        "late" in reasons for reasons in stats["drops"].values())


# ---------------------------------------------------------------- the monitor's web server

@pytest.mark.integration
def test_the_monitor_keeps_a_bounded_number_of_connections_and_threads():
    import socket as _socket
    from stage_plugins.monitor.server import MAX_CONNECTIONS, Broadcaster, MonitorServer
    server = MonitorServer("127.0.0.1", 0, Broadcaster())
    server.start()
    before = threading.active_count()
    socks = []
    try:
        for _ in range(100):  # idle connections that never send a request
            s = _socket.create_connection(server.server_address[:2], timeout=5)
            socks.append(s)
        # the kernel hands over connections beyond the listen backlog slowly (SYN-ACK
        # retries): wait until the server has taken them all or nothing changes for 3 s
        deadline, last, since = time.monotonic() + 30, -1, time.monotonic()
        while server.refused < 100 - MAX_CONNECTIONS and time.monotonic() < deadline:
            if server.refused != last:
                last, since = server.refused, time.monotonic()
            elif time.monotonic() - since > 3.0:
                break
            time.sleep(0.05)
        grew = threading.active_count() - before
        assert grew <= MAX_CONNECTIONS + 2, grew
        assert server.refused >= 20
    finally:
        for s in socks:
            s.close()
        server.stop()
