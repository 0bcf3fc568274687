"""The sources interface (entry-point group ``stage.sources.v1``).

A source produces sensor datagrams in the Client-to-Server API: the built-in
simulator (``sim``), a recording (``replay``), the real-sensor clients
(``webcam``, ``kinect2``, ``azure``), or a third party's. Built-ins are
registered by entry points exactly like third-party sources, and every
command finds a source by name through ``load_source``.

Every source runs **live**: ``start(target)`` sends to a server over UDP on
the source's own thread until ``stop()`` or its end (``done`` is set then).
A source that knows its own timing (the simulator, a recording) also runs
**offline**: ``items()`` yields ``(arrival_s, sender, datagram)`` from time 0,
deterministically, for an in-process engine on a manual clock.

A third-party source subclasses ``Source`` (or ``ThreadedSource``, which owns
the thread), sets ``name`` and ``description``, and declares it::

    [project.entry-points."stage.sources.v1"]
    mysensor = "mypackage.sensor:MySensorSource"

The class is called with keyword options (``load_source(name, **options)``).
"""

from __future__ import annotations

import logging
import threading
from typing import Any, ClassVar, Iterator

from ..errors import ConfigError, StageError
from ..registry import PluginInfo, entry_points, load
from ..rig import Rig

log = logging.getLogger("stage.sources")

GROUP = "stage.sources.v1"

#: (arrival seconds from the start, sender address, datagram)
Item = tuple[float, tuple[str, int], bytes]


class Source:
    """A stream of Client-to-Server datagrams (see the module docstring)."""

    #: the name it is registered under
    name: ClassVar[str] = ""
    #: one line for `stage plugins`
    description: ClassVar[str] = ""
    #: True when ``items()`` works (deterministic offline runs)
    offline: ClassVar[bool] = False

    def __init__(self) -> None:
        self.done = threading.Event()
        self.sent = 0

    def describe(self) -> str:
        """What this source is, for the console (``simulator 'default', seed 1``)."""
        return self.name

    def rig(self) -> Rig | None:
        """The rig that goes with this source (a simulator's exact one, a recording's own)."""
        return None

    @property
    def duration(self) -> float | None:
        """Seconds of material, if the source ends by itself."""
        return None

    @property
    def start_time(self) -> float:
        """Offline: where the material begins in the time of ``items()`` (seconds)."""
        return 0.0

    def items(self) -> Iterator[Item]:
        """Offline: every datagram with its arrival time (seconds from 0), in arrival order."""
        raise StageError(f"the {self.name} source cannot run offline (ahead of time)")

    def start(self, target: tuple[str, int]) -> "Source":
        """Live: send to ``target`` over UDP on the source's own thread; returns self."""
        raise NotImplementedError

    def stop(self) -> None:
        """End a live run (idempotent); waits briefly for the thread."""

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the source ends by itself (True) or ``timeout`` passes (False)."""
        return self.done.wait(timeout)


class ThreadedSource(Source):
    """A source whose live run is one function on its own thread (``_run``)."""

    def __init__(self) -> None:
        super().__init__()
        self.stop_event = threading.Event()
        self._thread: threading.Thread | None = None

    def _run(self, target: tuple[str, int], stop: threading.Event) -> None:
        """Send until ``stop`` is set or the material ends."""
        raise NotImplementedError

    def start(self, target: tuple[str, int]) -> "ThreadedSource":
        def run() -> None:
            try:
                self._run(target, self.stop_event)
            except StageError as exc:  # a missing library, a camera that did not open
                log.error("%s source stopped: %s", self.name, exc)
                self.error = str(exc)
            except Exception:  # the show must not die with its source; say why it stopped
                log.exception("%s source stopped", self.name)
                self.error = "internal error (see the log)"
            finally:
                self.done.set()
        self.error: str | None = None
        self._thread = threading.Thread(target=run, name=f"stage-source-{self.name}",
                                        daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self.stop_event.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)


def check_source_factory(obj: Any) -> str | None:
    """None when ``obj`` can make sources: a Source subclass, or a callable returning one."""
    if isinstance(obj, type):
        return None if issubclass(obj, Source) else (
            f"{obj.__module__}.{obj.__qualname__} is not a subclass of stage.sensors.Source")
    return None if callable(obj) else f"{obj!r} is neither a Source subclass nor a callable"


def discover_sources() -> dict[str, PluginInfo]:
    """Every installed source plugin by name, loaded and checked (never raises)."""
    out: dict[str, PluginInfo] = {}
    for info in entry_points(GROUP):
        load(info, check_source_factory)
        out.setdefault(info.name, info)
    return out


def load_source(name: str, **options: Any) -> Source:
    """Build the source registered as ``name`` with ``options``.

    Unknown name: ConfigError listing the installed ones. A source that fails
    to load: StageError with the reason (e.g. a missing optional library).
    """
    found = discover_sources()
    info = found.get(name)
    if info is None:
        known = ", ".join(sorted(found)) or "none"
        raise ConfigError(f"no source named '{name}' is installed (installed: {known}; "
                          "see `stage plugins`)")
    if not info.loaded:
        raise StageError(f"the {name} source failed to load: {info.error}")
    source = info.obj(**options)
    if not isinstance(source, Source):
        raise StageError(f"{info.value} returned {type(source).__name__}, not a Source")
    return source
