"""Finding view plugins (``stage.views.v1``) and listing every plugin group.

The entry-point machinery is ``stage.registry``; this module adds what a view
plugin must provide and how a view is made from it.
"""

from __future__ import annotations

import logging
from typing import Any

from ..registry import PluginInfo, entry_points, load
from ..sensors.source import GROUP as SOURCES_GROUP, check_source_factory
from .base import GROUP, View

log = logging.getLogger("stage.views")

#: Every plugin group `stage plugins` lists, with what each entry point must give.
GROUPS: dict[str, str] = {
    GROUP: "views",
    SOURCES_GROUP: "sources",
}


def check_view_factory(obj: Any) -> str | None:
    """None when ``obj`` can make views: a View subclass, or a callable returning one."""
    if isinstance(obj, type):
        return None if issubclass(obj, View) else (
            f"{obj.__module__}.{obj.__qualname__} is not a subclass of stage.views.View")
    return None if callable(obj) else f"{obj!r} is neither a View subclass nor a callable"


def discover_views(load_them: bool = True) -> dict[str, PluginInfo]:
    """Every installed view plugin by name, loaded (and checked) unless told not to."""
    out: dict[str, PluginInfo] = {}
    for info in entry_points(GROUP):
        if load_them:
            load(info, check_view_factory)
        out.setdefault(info.name, info)
    return out


def discover_all() -> dict[str, list[PluginInfo]]:
    """Every group `stage plugins` shows, each entry point loaded (imported, not started)."""
    checks = {GROUP: check_view_factory, SOURCES_GROUP: check_source_factory}
    return {group: [load(info, checks.get(group)) for info in entry_points(group)]
            for group in GROUPS}


def make_view(info: PluginInfo, **options: Any) -> View:
    """Build a view from a loaded plugin; raises what the factory raises."""
    view = info.obj(**options)
    if not isinstance(view, View):
        raise TypeError(f"{info.value} returned {type(view).__name__}, not a stage.views.View")
    view.name = info.name
    return view
