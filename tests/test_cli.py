"""The ``stage`` command as a user runs it: exit codes, one-line errors, clean shutdown.

Every CLI runs as ``python -m stage.cli`` in a subprocess, so PATH does not matter.
"""

from __future__ import annotations

import json
import re
import signal
import socket
import subprocess
import sys
import time

import pytest

import stage
from helpers import LOCALHOST, free_udp_port, query_stats

pytestmark = pytest.mark.integration

CLI = [sys.executable, "-m", "stage.cli"]


def run(*args: str, timeout: float = 30.0) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout)


def start_serve(port: int, *args: str) -> tuple[subprocess.Popen, dict]:
    """``stage serve`` on LOCALHOST:port with ``args``, and its first /stage/stats reply: it
    is up when it answers (each try waits for a reply, no fixed sleep)."""
    proc = subprocess.Popen([*CLI, "serve", "--host", LOCALHOST, "--port", str(port), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 20.0
    while True:
        assert proc.poll() is None, f"stage serve exited early: {proc.communicate()}"
        try:
            return proc, query_stats((LOCALHOST, port), timeout=0.2)
        except AssertionError:
            if time.monotonic() >= deadline:
                proc.kill()
                proc.communicate()
                raise AssertionError("stage serve never answered /stage/stats") from None


def one_line_error(stderr: str) -> str:
    """The whole stderr, asserted to be exactly one line and no traceback."""
    assert "Traceback" not in stderr, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    return lines[0]


def test_version():
    done = run("--version")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"stage {stage.__version__}"


def test_no_command_is_bad_input():
    done = run()
    assert done.returncode == 2
    assert "usage: stage" in done.stdout
    assert "Traceback" not in done.stderr


def test_missing_rig_file(tmp_path):
    missing = tmp_path / "missing.yaml"
    done = run("serve", "--rig", str(missing), "--duration", "5")
    assert done.returncode == 2
    line = one_line_error(done.stderr)
    assert line == f"stage: {missing}: no such file"


def test_rig_file_with_yaml_syntax_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("server:\n  host: 127.0.0.1\n  port: [7770\nsensors: {}\n")
    done = run("serve", "--rig", str(bad), "--duration", "5")
    assert done.returncode == 2
    line = one_line_error(done.stderr)
    assert re.fullmatch(rf"stage: {re.escape(str(bad))}:\d+:\d+: YAML syntax: .+", line), line


def test_port_in_use():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind((LOCALHOST, 0))
        port = taken.getsockname()[1]
        done = run("serve", "--host", LOCALHOST, "--port", str(port), "--duration", "5")
    assert done.returncode == 1
    line = one_line_error(done.stderr)
    assert line.startswith(f"stage: cannot listen for OSC on udp {LOCALHOST}:{port}"), line


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_serve_answers_stats_and_stops_cleanly_on_signal(sig):
    port = free_udp_port()
    proc, _ = start_serve(port)
    try:
        done = run("stats", "--port", str(port), "--timeout", "5")
        assert done.returncode == 0, done.stderr
        stats = json.loads(done.stdout)
        assert stats["clients"] == {} and "drops" in stats and "uptime_s" in stats

        proc.send_signal(sig)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err  # interrupted, as the README promises (issue 9: was 0)
    assert "Traceback" not in err, err
    assert "stopped;" in err  # the shutdown summary: it went through server.stop()


def test_view_forecast_sends_the_views_bodies_predicted_ahead():
    """``--view-forecast S``: the --view views are sent each body S seconds ahead (the
    server says so in /stage/stats); more than the rig's max_s is one line of bad input."""
    port, view = free_udp_port(), free_udp_port()
    proc, stats = start_serve(port, "--view", f"{LOCALHOST}:{view}", "--view-forecast", "0.05")
    try:
        assert stats["forecast"]["views_s"] == {f"{LOCALHOST}:{view}": 0.05}
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    done = run("serve", "--port", "0", "--view-forecast", "0.5", "--duration", "1")
    assert done.returncode == 2
    assert one_line_error(done.stderr) == ("stage: --view-forecast 0.5: must be between 0 and "
                                           "the rig's forecast: max_s (0.2 s)")


def test_stats_without_server_fails_with_one_line():
    port = free_udp_port()
    done = run("stats", "--port", str(port), "--timeout", "0.5")
    assert done.returncode == 1
    line = one_line_error(done.stderr)
    assert line.startswith(f"stage: no answer from 127.0.0.1:{port} within 0.5 s")


def test_demo_runs_and_reports():
    done = run("demo", "--duration", "3", timeout=60)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    lines = done.stdout.strip().splitlines()
    assert lines[0].startswith("stage demo: 3 virtual Kinects -> engine on udp 127.0.0.1:")
    status = [line for line in lines if "person 1 at" in line]
    assert status, done.stdout
    assert any("seen by 3" in line for line in status), done.stdout
    summary = lines[-1]
    assert re.fullmatch(r"stage demo: done; (\d+) sensor frames in, (\d+) fused, (\d+) datagrams "
                        r"out, 0 dropped, latency p50 .+ ms p99 .+ ms", summary), summary
    frames_in = int(re.search(r"(\d+) sensor frames in", summary).group(1))
    assert frames_in > 0


# ---------------------------------------------------------------- issue 9: one-line errors

@pytest.mark.parametrize("command", ["serve", "monitor", "demo", "record"])
def test_a_port_out_of_range_is_one_line_of_bad_input(command, tmp_path):
    extra = ["--out", str(tmp_path / "x.rec")] if command == "record" else []
    done = run(command, "--port", "99999", *extra)
    assert done.returncode == 2
    assert "Traceback" not in done.stderr and "OverflowError" not in done.stderr
    assert "'99999' is not a port (0-65535)" in done.stderr


def test_stats_with_a_host_that_does_not_exist_is_one_line():
    done = run("stats", "--host", "nonsense.invalid", "--timeout", "0.5")
    assert done.returncode == 2
    assert one_line_error(done.stderr) == "stage: --host nonsense.invalid: no such host"


def test_sim_can_write_its_rig_and_a_recording_to_dev_null(tmp_path):
    rig = tmp_path / "sim-rig.yaml"
    done = run("sim", "--rig-out", str(rig), "--duration", "1", "--out", "/dev/null")
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert rig.exists()


@pytest.mark.parametrize("where", ["before", "after"])
def test_global_options_go_before_or_after_the_subcommand(where, tmp_path):
    missing = tmp_path / "missing.yaml"
    args = ["--debug", "serve", "--rig", str(missing)] if where == "before" else [
        "serve", "--rig", str(missing), "--debug"]
    done = run(*args)
    assert done.returncode != 0
    assert "Traceback" in done.stderr  # --debug shows the traceback, wherever it was given
    quiet = run("sim", "--list", "--quiet") if where == "after" else run("--quiet", "sim", "--list")
    assert quiet.returncode == 0, quiet.stderr
    assert "default" in quiet.stdout


def test_sigterm_ends_a_show_with_status_130():
    port = free_udp_port()
    proc = subprocess.Popen([*CLI, "serve", "--host", LOCALHOST, "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 20.0
        while True:
            assert proc.poll() is None, proc.communicate()
            try:
                query_stats((LOCALHOST, port), timeout=0.2)
                break
            except AssertionError:
                assert time.monotonic() < deadline
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err


def test_the_install_hint_names_a_distribution_that_is_ours():
    done = run("client", "--help")
    assert done.returncode == 0
    assert "pip install 'stage[" not in done.stdout
    assert f"pip install '{stage.DISTRIBUTION}[webcam]'" in done.stdout
