"""Plugins found through entry points, whatever they provide (views, sources).

Built-ins are found exactly like third-party plugins: through the metadata of
installed distributions. Loading imports the module; a plugin that fails to
import, or does not provide what its group expects, is reported with the
reason and skipped, never fatal.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, Callable

from . import DISTRIBUTION

log = logging.getLogger("stage.plugins")


@dataclass
class PluginInfo:
    """One entry point and what became of loading it."""

    group: str
    name: str
    value: str                  # "module:attribute"
    distribution: str | None    # the installed distribution that declares it
    version: str | None
    loaded: bool = False
    error: str | None = None    # why it did not load (one line)
    obj: Any = field(default=None, repr=False)

    @property
    def module(self) -> str:
        return self.value.split(":", 1)[0].strip()

    @property
    def description(self) -> str:
        text = getattr(self.obj, "description", None) or (getattr(self.obj, "__doc__", None) or "")
        return text.strip().splitlines()[0] if isinstance(text, str) and text.strip() else ""

    def as_dict(self) -> dict[str, Any]:
        return {"group": self.group, "name": self.name, "value": self.value,
                "module": self.module, "distribution": self.distribution,
                "version": self.version, "loaded": self.loaded, "error": self.error,
                "description": self.description if self.loaded else ""}


def entry_points(group: str) -> list[PluginInfo]:
    """The entry points of ``group`` (not loaded), one per name.

    When two distributions declare the same name, stage's own keeps it (a plugin
    cannot silently replace a built-in view), otherwise the first on ``sys.path``;
    the other is listed with an error saying so.
    """
    found: dict[str, PluginInfo] = {}
    duplicates: list[PluginInfo] = []
    points = list(metadata.entry_points(group=group))
    points.sort(key=lambda e: (e.name, not _is_ours(getattr(e, "dist", None))))
    for ep in points:
        dist = getattr(ep, "dist", None)
        info = PluginInfo(group, ep.name, ep.value, dist.name if dist else None,
                          dist.version if dist else None)
        if ep.name in found:
            if found[ep.name].value != ep.value or found[ep.name].distribution != info.distribution:
                info.error = (f"name '{ep.name}' is already taken by {found[ep.name].value} "
                              f"({found[ep.name].distribution}); this one is ignored")
                duplicates.append(info)
            continue
        found[ep.name] = info
    return [*found.values(), *duplicates]


def _is_ours(dist: metadata.Distribution | None) -> bool:
    """Whether ``dist`` is stage's own distribution, however its name is spelled (PEP 503)."""
    name = getattr(dist, "name", None)
    return name is not None and re.sub(r"[-_.]+", "-", name).lower() == DISTRIBUTION


def load(info: PluginInfo, check: Callable[[Any], str | None] | None = None) -> PluginInfo:
    """Import ``info``'s object; on failure set ``error`` (one line). Never raises."""
    if info.error is not None:
        return info
    try:
        module, _, attr = info.value.partition(":")
        obj = __import__(module.strip(), fromlist=["_"])
        for part in filter(None, attr.strip().split(".")):
            obj = getattr(obj, part)
    except Exception as exc:  # a broken plugin is reported, whatever it raised
        info.error = f"{type(exc).__name__}: {exc}".strip().splitlines()[0]
        log.debug("plugin %s (%s) failed to import", info.name, info.value, exc_info=True)
        return info
    problem = check(obj) if check else None
    if problem:
        info.error = problem
        return info
    info.obj, info.loaded = obj, True
    return info
