"""The Pure Data example patch as a real peer: `pd -nogui` opens examples/puredata/
stage-receive.pd ([netreceive -u -b] + [oscparse]) and prints every message a show sends
it -- the piece's own OSC messages, the piece events and the skeleton stream -- which must
be every message the OSC view sent, each with its values."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import pytest

from helpers import Peer, free_udp_port
from stage.app.show import Show, ShowOptions

REPO = Path(__file__).resolve().parents[1]
PATCH = REPO / "examples" / "puredata" / "stage-receive.pd"

pytestmark = [pytest.mark.integration,
              pytest.mark.skipif(shutil.which("pd") is None,
                                 reason="needs Pure Data (apt-get install puredata-core; "
                                        ".ci/run installs it)")]


class PureData:
    """``pd -nogui`` with the example patch listening on ``port``; its prints are lines."""

    def __init__(self, port: int, log: Path) -> None:
        self.log = log
        self.handle = open(log, "wb")
        self.proc = subprocess.Popen(["pd", "-nogui", "-noaudio", "-nomidi", "-stderr", "-open",
                                      str(PATCH), "-send", f"stage-port {port}"],
                                     stdout=self.handle, stderr=subprocess.STDOUT)
        with Peer() as probe:          # ready once it prints what we send
            deadline = time.monotonic() + 20
            while "stage: probe 1" not in self.text():
                assert self.proc.poll() is None, self.text()
                assert time.monotonic() < deadline, f"pd never answered: {self.text()}"
                probe.send_message(("127.0.0.1", port), "/stage/probe", 1)
                time.sleep(0.1)

    def text(self) -> str:
        return self.log.read_bytes().decode("utf-8", "replace")

    def lines(self) -> list[str]:
        return [line for line in self.text().splitlines()
                if line and not line.startswith("stage: probe")]

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        self.handle.close()


def test_pure_data_receives_the_piece_and_the_skeletons(tmp_path):
    # Liminal, its OSC output asking for the skeleton stream too
    piece = tmp_path / "liminal.yaml"
    piece.write_text((REPO / "pieces" / "liminal.yaml").read_text().replace(
        "  space: osc ", "  space: {type: osc, skeletons: true} "))
    shutil.copy(REPO / "pieces" / "liminal.sim.yaml", tmp_path)
    port = free_udp_port()
    pd = PureData(port, tmp_path / "pd.log")
    try:
        show = Show(ShowOptions(piece=str(piece), sim="", offline=True, duration=10.0, seed=1,
                                osc=[("127.0.0.1", port)], midi_file=str(tmp_path / "x.mid"),
                                plugins=False), out=open(tmp_path / "console.txt", "w"))
        result = show.run()
        (osc,) = [s.view for s in show.host.slots if s.name == "osc"]
        sent = osc.counts["messages"]
        deadline = time.monotonic() + 10
        while len(pd.lines()) < sent and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(0.3)                                   # nothing more comes
        lines = pd.lines()
    finally:
        pd.close()
    assert osc.counts["send_errors"] == 0 and sent > 300
    assert len(lines) == sent                             # every message, once
    by = {}
    for line in lines:
        head, _, rest = line.partition(": ")
        by.setdefault(head, []).append(rest.split())
    pans = [float(v[1]) for v in by["liminal"] if v[0] == "pan"]
    sent_pans = [e.args[0] for e in result.recorded.events
                 if type(e).__name__ == "OscOut" and e.address == "/liminal/pan"]
    assert pans == pytest.approx(sent_pans, abs=1e-6)     # the values, in order
    assert ["dancer", "1", "1"] in by["liminal"]
    # /stage/section: Pd shows the space in the symbol "I. Threshold" escaped
    assert "stage: section I.\\ Threshold 0  start" in lines
    assert by["newUser"][0][0] == "1"
    heads = [float(v[0]) for v in by["head-y"]]           # /jointCoordinates: the Head's y
    assert len(heads) > 100 and all(1.3 < h < 1.8 for h in heads)
