"""What a show can be asked: ``ShowOptions``, every command's options with one default each.

``stage serve``, ``demo``, ``monitor``, ``play``, ``calibrate --live`` and
``replay --offline`` turn their arguments into these; ``stage.app.show.Show``
assembles the show they describe.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from ..calibration import LiveSettings
from ..rig import Rig


@dataclass
class ShowOptions:
    """Everything a command can ask of a show; the defaults are every command's defaults."""

    # where bodies come from (at most one of sim, replay, source)
    sim: str | None = None          # None: no simulator; "" the piece's rehearsal or default
    replay: str | None = None       # a recording
    loop: bool = False              # replay: start again at the end
    source: str | None = None       # another installed source by name (stage.sources.v1)
    source_options: dict[str, Any] = field(default_factory=dict)
    offline: bool = False           # run the engine here on a manual clock (sim or replay)
    speed: float = 1.0              # live sim/replay: x real time (math.inf: as fast as possible)
    host: str | None = None         # listen here (default: the rig's; 127.0.0.1 with a source)
    port: int | None = None         # UDP port (default: the rig's; any free one with a source)
    listen: bool = False            # with a source, still listen where real sensors would send
    # the rig and the engine
    rig: str | None = None          # rig file (saved calibrations go here)
    rig_data: Rig | None = None     # a rig object instead of reading ``rig``
    create_rig: bool = False        # a missing ``rig`` file is started empty (calibrate --live)
    self_healing: bool = True       # calibrate uncalibrated sensors, re-calibrate bumped ones
    freeze_heap: bool = False       # live: start-up's objects out of the collector's walks
    calibration: LiveSettings | None = None
    # the piece
    piece: str | None = None
    seed: int | None = None
    events: str | None = None       # every event as a JSON line
    # what comes out
    views: list[tuple[str, int]] = field(default_factory=list)   # Server-to-View OSC targets
    view_forecast_s: float | None = None  # the views' forecast (None: the rig's views_s)
    midi: str | None = None
    midi_file: str | None = None
    audio: str | None = None        # render the MIDI through FluidSynth into this WAV file
    synth: bool = False             # play the MIDI live through FluidSynth on JACK
    soundfont: str | None = None    # for audio and synth (default: a General MIDI one)
    score: str | None = None        # draw the performance (piano roll) into this PNG
    osc: list[tuple[str, int]] = field(default_factory=list)     # the OSC view's targets
    monitor: bool | int = False     # the live web monitor (True: port 7780; an int: that port)
    monitor_bind: str = "127.0.0.1"
    relay: list[tuple[str, int]] = field(default_factory=list)
    plugins: bool = True            # also run the installed views that start by themselves
    fused: str | None = None        # every fused frame as a JSON line (exact floats)
    status_line: bool = False       # one status line a second on the console
    # health (live shows): checked every second, a summary line a minute, alerts
    health: bool = True
    alert_after_s: float | None = None   # default: the rig's alerts.after_s
    alert_command: str | None = None     # default: the rig's alerts.command
    alert_osc: str | None = None         # HOST:PORT; default: the rig's alerts.osc
    # how it ends
    duration: float | None = None
    end_with_source: bool = True    # a source that ends by itself ends the show
