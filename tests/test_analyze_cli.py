"""`stage analyze`: the command, its report, and the whole way from `stage sim` and
`stage record` over real UDP to a report a real browser draws."""

from __future__ import annotations

import base64
import json
import struct
import subprocess
import sys
import zlib

import pytest
from helpers import free_udp_port
from test_monitor_browser import ARTIFACTS, browser  # noqa: F401  (a fixture)

from stage.analysis.svg import LEFT_COLOUR, RIGHT_COLOUR
from stage.cli.main import main
from stage.sensors.sim import Simulator, load_scenario

LEFT_SIDE = "left=kinect-l1,kinect-l2,kinect-l3"


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """Twelve seconds of the walkway scenario (one pass) as a recording, with its truth."""
    folder = tmp_path_factory.mktemp("walk")
    rec, truth = folder / "walk.rec", folder / "walk.npz"
    Simulator(load_scenario("walkway"), seed=4).record(str(rec), 12.0, str(truth))
    return rec, truth


def test_analyze_compares_sensor_subsets_with_the_truth(walk, tmp_path, capsys):
    rec, truth = walk
    report = tmp_path / "walk.html"
    assert main(["analyze", str(rec), "--sensors", LEFT_SIDE, "--sensors", "all", "--truth",
                 str(truth), "--report", str(report)]) == 0
    out = capsys.readouterr().out
    assert "left (kinect-l1, kinect-l2, kinect-l3):" in out and "all (" in out
    assert "step width (cm)" in out and "ICC(A,1)" in out
    assert f"report written to {report}" in out
    assert main(["analyze", str(rec), "--sensors", LEFT_SIDE, "--sensors", "all", "--truth",
                 str(truth), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert list(data["subsets"]) == ["left", "all"]
    for name, sub in data["subsets"].items():
        g = sub["gait"]
        assert g["step_length"]["all"]["mean"] == pytest.approx(0.70, abs=0.02), name
        assert g["step_width"]["all"]["mean"] == pytest.approx(0.12, abs=0.03), name
        assert g["cadence"] == pytest.approx(110, rel=0.03), name
        assert sub["matched_steps"] == g["used"] >= 8    # every step found, none invented
        assert sub["agreement"]["step_length"]["all"]["rmse"] < 0.035
        assert set(sub["kpi"]["envelope_m3"]) == {"HandLeft", "HandRight", "FootLeft",
                                                  "FootRight"}
    assert data["truth"]["shift_s"] == pytest.approx(0.0, abs=0.04)   # the same clock
    page = report.read_text()
    assert page.startswith("<!doctype html>") and page.count("<svg") >= 10
    embedded = page.split('<script type="application/json" id="analysis">')[1]
    assert json.loads(embedded.split("</script>")[0].replace("<\\/", "</"))["sensors"] == \
        data["sensors"]


@pytest.mark.parametrize("extra, message", [
    (["--sensors", "kinect-x"], "no frames from sensor(s) kinect-x in the recording"),
    (["--sensors", "a=kinect-l1", "--sensors", "a=kinect-r1"], "give each subset its own NAME"),
    (["--sensors", "a="], "give sensor ids"),
    (["--truth", "missing.npz"], "missing.npz: not a ground-truth file"),
    (["--report", "no/such/folder/r.html"], "no folder"),
])
def test_one_line_errors(walk, extra, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["analyze", str(walk[0]), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("stage: ") and message in err and "\n" not in err


def test_a_recording_without_a_rig_needs_one(tmp_path, capsys):
    assert main(["analyze", str(tmp_path / "none.rec")]) == 2
    assert "none.rec: no such file" in capsys.readouterr().err
    # stage record keeps no rig: several sensors cannot be put in one space without one
    from stage.sensors.recording import RecordingWriter
    rec = tmp_path / "bare.rec"
    with RecordingWriter(str(rec), {"source": "stage record"}) as w:
        for d in Simulator(load_scenario("walkway"), seed=1).stream(2.0):
            w.write(d.arrival, d.source, d.data)
    assert main(["analyze", str(rec)]) == 2
    err = capsys.readouterr().err
    assert "carries no rig" in err and "--rig" in err and "stage calibrate" in err


def _pixel(png: bytes) -> tuple[int, int, int]:
    """The first pixel of a PNG screenshot (8-bit RGB or RGBA, as Chromium writes them)."""
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    pos, data, width, kind = 8, b"", 0, 2
    while pos < len(png):
        length, tag = struct.unpack(">I4s", png[pos:pos + 8])
        body = png[pos + 8:pos + 8 + length]
        if tag == b"IHDR":
            width, _, depth, kind = struct.unpack(">IIBB", body[:10])
            assert depth == 8
        elif tag == b"IDAT":
            data += body
        pos += 12 + length
    raw = zlib.decompress(data)
    channels = 4 if kind == 6 else 3
    assert raw[0] == 0 or width == 1       # filter "none" (or sub, a no-op for one pixel)
    return tuple(raw[1:1 + channels][:3])  # type: ignore[return-value]


def _run(args: list[str], **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "stage.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


@pytest.mark.integration
def test_stage_record_of_stage_sim_analysed_and_drawn_in_chromium(tmp_path, browser):  # noqa: F811
    """`stage sim` sends the walkway over UDP in real time while `stage record` records
    it (no capture times, the sensors' clocks off by up to 2 s, no rig: --rig-out gives
    it); `stage analyze` reads that recording; headless Chromium draws the report."""
    port = free_udp_port()
    rec, rig, report = tmp_path / "live.rec", tmp_path / "rig.yaml", tmp_path / "live.html"
    recorder = _run(["record", "--out", str(rec), "--port", str(port), "--host", "127.0.0.1",
                     "--duration", "13"])
    try:
        assert "stage record: udp" in recorder.stdout.readline()     # listening
        sim = _run(["sim", "walkway", "--to", f"127.0.0.1:{port}", "--duration", "11.5",
                    "--seed", "2", "--rig-out", str(rig)])
        sim_out, sim_err = sim.communicate(timeout=60)
        assert sim.returncode == 0, sim_err
        out, err = recorder.communicate(timeout=30)
        assert recorder.returncode == 0, err
    finally:
        for proc in (recorder,):
            if proc.poll() is None:
                proc.terminate()
                proc.wait(10)
    assert "written to" in out
    done = subprocess.run([sys.executable, "-m", "stage.cli", "analyze", str(rec), "--rig",
                           str(rig), "--sensors", LEFT_SIDE, "--sensors", "all", "--report",
                           str(report), "--json"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    data = json.loads(done.stdout)
    g = data["subsets"]["all"]["gait"]
    assert g["used"] >= 7                                            # one pass of 10 steps
    assert g["step_length"]["all"]["mean"] == pytest.approx(0.70, abs=0.03)
    assert g["step_width"]["all"]["mean"] == pytest.approx(0.12, abs=0.03)
    assert g["cadence"] == pytest.approx(110, rel=0.05)
    assert report.exists()

    browser.call("Page.navigate", url=report.as_uri())
    browser.wait("document.readyState === 'complete' && "
                 "document.querySelectorAll('svg.chart').length > 0", what="the report")
    page = browser.js("""({
        sections: [...document.querySelectorAll('section')].map(s => s.id),
        charts: document.querySelectorAll('svg.chart').length,
        cards: [...document.querySelectorAll('.card[data-subset]')].map(c => c.dataset.subset),
        used: JSON.parse(document.getElementById('analysis').textContent)
              .subsets.all.gait.used})""")
    assert page["sections"] == ["summary", "footprints", "events", "steps", "angles", "motion",
                                "kpi", "coverage"]
    assert page["charts"] >= 10 and page["cards"] == ["left", "all"] and page["used"] == g["used"]
    for colour, name in ((LEFT_COLOUR, "left"), (RIGHT_COLOUR, "right")):
        # a footprint drawn where the layout says: hit-test it, then read the screen there
        spot = browser.js(f"""(() => {{
            const foot = document.querySelector('#footprints ellipse[fill="{colour}"]');
            foot.scrollIntoView({{block: 'center'}});
            const r = foot.getBoundingClientRect();
            const x = r.left + r.width * 0.2, y = r.top + r.height / 2;
            return {{x, y, hit: document.elementFromPoint(x, y) === foot,
                     px: x + window.scrollX, py: y + window.scrollY}};}})()""")
        assert spot["hit"], f"the {name} footprint is covered"
        shot = browser.call("Page.captureScreenshot", format="png",
                            clip={"x": spot["px"], "y": spot["py"], "width": 1, "height": 1,
                                  "scale": 1})
        rgb = _pixel(base64.b64decode(shot["data"]))
        want = tuple(int(0.75 * int(colour[k:k + 2], 16) + 0.25 * 255) for k in (1, 3, 5))
        assert all(abs(a - b) <= 30 for a, b in zip(rgb, want)), (name, rgb, want)
    metrics = browser.call("Page.getLayoutMetrics")
    size = metrics["cssContentSize"]
    shot = browser.call("Page.captureScreenshot", format="png", captureBeyondViewport=True,
                        clip={"x": 0, "y": 0, "width": size["width"],
                              "height": min(size["height"], 6000), "scale": 1})
    ARTIFACTS.mkdir(exist_ok=True)
    (ARTIFACTS / "analysis_report.png").write_bytes(base64.b64decode(shot["data"]))


def test_a_recording_with_no_walking_or_hardly_any_data_still_reports(tmp_path, capsys):
    rec, report = tmp_path / "short.rec", tmp_path / "short.html"
    Simulator(load_scenario("walkway"), seed=1).record(str(rec), 0.5)   # a few frames
    assert main(["analyze", str(rec), "--report", str(report), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["subsets"]["all"]["gait"]["steps"] == 0
    assert data["subsets"]["all"]["gait"]["speed"] is None       # NaN becomes null in JSON
    assert "<svg" in report.read_text()


def test_a_recording_in_which_nobody_was_seen_is_one_line(tmp_path, capsys):
    rec = tmp_path / "empty.rec"
    Simulator(load_scenario("walkway"), seed=1).record(str(rec), 0.2)  # before anyone is found
    assert main(["analyze", str(rec)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("stage: no skeletons from kinect-l1") and "nobody was seen" in err
