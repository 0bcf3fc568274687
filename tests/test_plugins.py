"""Plugins through entry points: the built-ins, third-party views, broken ones, `stage plugins`,
and the tutorial in docs/views.md (its code is taken from the page and run).

Third-party distributions are made on the fly: a folder on ``sys.path`` with a
``*.dist-info`` (METADATA + entry_points.txt) is what pip leaves behind, and
what ``importlib.metadata`` reads.
"""

from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest

import stage
from stage import DISTRIBUTION
from stage.sensors.sim import standing_pose
from stage.clock import ManualClock
from stage.frames import FusedFrame
from stage.views import GROUP, View, ViewHost, discover_views
from test_views import make_body

ROOT = Path(__file__).resolve().parents[1]


def make_distribution(site: Path, name: str, entry_points: dict[str, str],
                      modules: dict[str, str], group: str = GROUP) -> None:
    """An installed distribution as pip leaves it (dist-info + modules) in ``site``."""
    dist = site / f"{name.replace('-', '_')}-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    lines = "\n".join(f"{k} = {v}" for k, v in entry_points.items())
    (dist / "entry_points.txt").write_text(f"[{group}]\n{lines}\n")
    for module, code in modules.items():
        (site / f"{module}.py").write_text(code)


WAVE = '''
from stage.views import View

class Wave(View):
    """waves at everybody"""
    def on_frame(self, frame):
        for pid in frame.new:
            print(f"hello person {pid}", flush=True)
'''

QUIET = '''
from stage.views import View

class Quiet(View):
    description = "runs only when asked"
    autostart = False
'''


@pytest.fixture
def site(tmp_path, monkeypatch):
    site = tmp_path / "site"
    site.mkdir()
    make_distribution(site, "stage-wave", {"wave": "stage_wave:Wave", "quiet": "stage_quiet:Quiet"},
                      {"stage_wave": WAVE, "stage_quiet": QUIET})
    make_distribution(site, "stage-broken", {
        "typo": "stage_typo:Typo",
        "not-a-view": "stage_notview:thing",
        "midi": "stage_notview:thing"},        # a name the built-in MIDI view already has
        {"stage_typo": "import numpyy\n", "stage_notview": "thing = 42\n"})
    monkeypatch.syspath_prepend(str(site))
    return site


def test_the_built_in_views_are_found_through_entry_points_like_any_plugin():
    found = discover_views()
    for name, value in (("midi", "stage_plugins.midi:MidiView"),
                        ("osc", "stage_plugins.osc:OscView"),
                        ("relay", "stage_plugins.relay:RelayView"),
                        ("monitor", "stage_plugins.monitor:MonitorView")):
        info = found[name]
        assert info.value == value and info.distribution == DISTRIBUTION and info.loaded, info
        assert issubclass(info.obj, View) and info.obj.autostart is False


def test_pyproject_declares_what_the_installed_metadata_says():
    text = (ROOT / "pyproject.toml").read_text()
    table = text.split('[project.entry-points."stage.views.v1"]', 1)[1].split("\n[", 1)[0]
    declared = dict(re.findall(r'^(\S+) = "([^"]+)"', table, re.M))
    installed = {name: info.value for name, info in discover_views(load_them=False).items()
                 if info.distribution == DISTRIBUTION}
    assert declared == installed, "reinstall (pip install -e .) after editing entry points"
    # the name importlib.metadata knows stage by ("stage" on PyPI is another project)
    assert re.search(r'^name = "([^"]+)"', text, re.M).group(1) == DISTRIBUTION != "stage"
    assert metadata.version(DISTRIBUTION) == stage.__version__
    # every folder of code or data is installed (scenarios/ has no __init__.py but is read
    # with importlib.resources), plugins/ under its namespaced name stage_plugins
    table = text.split("\n[tool.setuptools]\n", 1)[1].split("\n[", 1)[0]
    listed = set(re.findall(r'"([\w.]+)"', table.split("packages = [", 1)[1].split("]", 1)[0]))
    folders = {str(p.parent.relative_to(ROOT)).replace(os.sep, ".")
               for top in ("stage", "plugins") for p in (ROOT / top).rglob("*")
               if p.is_file() and "__pycache__" not in p.parts}
    assert listed == {re.sub(r"^plugins\b", "stage_plugins", f) for f in folders}
    assert re.search(r'^stage_plugins = "plugins"$',
                     text.split("[tool.setuptools.package-dir]", 1)[1].split("\n[", 1)[0], re.M)


def test_third_party_views_load_and_broken_ones_are_reported(site):
    found = discover_views()
    assert found["wave"].loaded and found["wave"].distribution == "stage-wave"
    assert found["wave"].description == "waves at everybody"
    assert found["typo"].error == "ModuleNotFoundError: No module named 'numpyy'"
    assert "is neither a View subclass nor a callable" in found["not-a-view"].error
    assert found["midi"].distribution == DISTRIBUTION     # a built-in keeps its name


def test_a_show_runs_autostart_views_and_goes_on_past_broken_ones(site, caplog, capfd):
    clock = ManualClock(0.0)
    with caplog.at_level(logging.WARNING):
        host = ViewHost.for_play([], clock=clock, threaded=False).start()
    names = [slot.name for slot in host.slots]
    assert names == ["wave"]                  # quiet says autostart = False; broken ones skipped
    warnings = "\n".join(r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    assert "view plugin 'typo' (stage_typo:Typo, from stage-broken) failed to load: " \
           "ModuleNotFoundError: No module named 'numpyy'; it is disabled, the show goes on" \
           in warnings
    assert "'not-a-view'" in warnings
    host._on_frame(FusedFrame(0.0, {1: make_body(1)}, (1,), (1,), ()))
    host.pump()
    host.stop()
    assert "hello person 1" in capfd.readouterr().out


def _stage(*args: str, site: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if site is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(site), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return subprocess.run([sys.executable, "-m", "stage.cli", *args], capture_output=True,
                          text=True, env=env, timeout=60)


def test_stage_plugins_lists_views_and_sources_with_origin_and_load_state(site):
    done = _stage("plugins", site=site)
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert out.startswith("views (stage.views.v1)")
    assert "sources (stage.sources.v1)" in out
    rows: dict[str, str] = {}
    for line in out.splitlines():
        if line.startswith("  "):
            rows.setdefault(line.split()[0], line)   # the duplicate 'midi' comes second
    assert re.search(r"wave\s+loaded\s+auto\s+stage-wave 0\.1\s+stage_wave:Wave\s+waves at",
                     rows["wave"])
    assert re.search(r"quiet\s+loaded\s+on request\s+stage-wave 0\.1", rows["quiet"])
    assert re.search(r"midi\s+loaded\s+on request\s+stage-kuatro 0\.1\.0\s+"
                     r"stage_plugins\.midi:MidiView", rows["midi"])
    assert re.search(r"typo\s+FAILED\s+stage-broken 0\.1\s+stage_typo:Typo\s+"
                     r"ModuleNotFoundError: No module named 'numpyy'", rows["typo"])
    assert "name 'midi' is already taken by stage_plugins.midi:MidiView (stage-kuatro)" in out
    assert "3 plugin(s) failed to load" in done.stderr     # typo, not-a-view, the second 'midi'
    assert _stage("plugins", "--check", site=site).returncode == 1
    data = json.loads(_stage("plugins", "--json", site=site).stdout)
    wave = next(i for i in data[GROUP] if i["name"] == "wave")
    assert wave["module"] == "stage_wave" and wave["autostart"] is True and wave["loaded"]
    assert isinstance(data["stage.sources.v1"], list)


def test_stage_plugins_check_passes_on_a_clean_install():
    done = _stage("plugins", "--check")
    assert done.returncode == 0, done.stdout + done.stderr


# ---------------------------------------------------------------- the tutorial, from the docs

def _tutorial_files() -> dict[str, str]:
    text = (ROOT / "docs" / "views.md").read_text()
    tutorial = text.split("## Tutorial", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"^`([\w.]+)`:\n\n```\w+\n(.*?)^```", tutorial, re.M | re.S)
    return dict(blocks)


def test_the_tutorial_view_is_at_most_30_lines_installs_and_prints_raised_hands(tmp_path,
                                                                             monkeypatch, capfd):
    files = _tutorial_files()
    code, pyproject = files["hands_up.py"], files["pyproject.toml"]
    assert len(code.strip().splitlines()) <= 30
    entry = re.search(r'^hands-up = "([^"]+)"', pyproject, re.M).group(1)
    site = tmp_path / "site"
    make_distribution(site, "hands-up", {"hands-up": entry}, {"hands_up": code})
    monkeypatch.syspath_prepend(str(site))
    assert discover_views()["hands-up"].loaded

    clock = ManualClock(0.0)
    host = ViewHost.for_play([], clock=clock, threaded=False).start()
    assert "hands-up" in [s.name for s in host.slots]
    body = make_body(1)
    for k, (left, right) in enumerate([(0.2, 0.2), (3.0, 0.2), (3.0, 0.2), (0.2, 3.0),
                                       (0.2, 0.2), (3.0, 0.2)]):
        body.joints = standing_pose((0.0, 1.0), 0.0, left_arm=left, right_arm=right)
        host._on_frame(FusedFrame(0.1 * k, {1: body}, (1,), (1,) if k == 0 else (), ()))
        host.pump()
    host.stop()
    printed = [line for line in capfd.readouterr().out.splitlines() if "raised" in line]
    assert printed == ["person 1 raised the left hand", "person 1 raised the right hand",
                       "person 1 raised the left hand"]
