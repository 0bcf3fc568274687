"""``stage client SENSOR --check``: what a sensor client needs, what is there, one skeleton.

Each hardware client lists its requirements as ``Item``s (found or not,
with what to do when not); when everything is there it opens the device,
waits a few seconds for a tracked body and prints its 25 joints. The checks
take their probes as arguments, so the report is tested on any machine.
"""

from __future__ import annotations

import ctypes.util
import importlib.metadata
import importlib.util
import os
from dataclasses import dataclass

from ...joints import JOINTS
from .osc import BodyFrame


@dataclass
class Item:
    name: str
    ok: bool
    detail: str = ""


def module_item(module: str, distributions: tuple[str, ...], hint: str,
                find_spec=importlib.util.find_spec) -> Item:
    """Whether ``module`` imports, with the version of the first installed distribution."""
    try:
        spec = find_spec(module)
    except (ImportError, ValueError):
        spec = None
    if spec is None:
        return Item(f"Python module {module}", False, f"missing: {hint}")
    for dist in distributions:
        try:
            return Item(f"Python module {module}", True,
                        f"{dist} {importlib.metadata.version(dist)}")
        except importlib.metadata.PackageNotFoundError:
            continue
    return Item(f"Python module {module}", True, spec.origin or "")


def library_item(name: str, library: str, paths: list[str], hint: str,
                 find_library=ctypes.util.find_library, exists=os.path.exists) -> Item:
    """Whether a native library is on the loader's path or in one of its usual places."""
    found = find_library(library)
    if found:
        return Item(name, True, found)
    for path in paths:
        if exists(path):
            return Item(name, True, path)
    return Item(name, False, f"not found ({library}): {hint}")


def format_skeleton(body: BodyFrame) -> list[str]:
    """One body as 25 lines: joint, x y z in metres (camera space), confidence."""
    return [f"  {name:<14} {x:+.3f} {y:+.3f} {z:+.3f}  conf {c:.1f}"
            for name, (x, y, z), c in zip(JOINTS, body.joints, body.conf)]


def body_items(items: list[Item], first_body, wait_s: float, device: str, cannot_open: str,
               none_hint: str, space: str) -> list[str]:
    """When every item is there, open the device and wait for one tracked body.

    Appends the device's and the body's ``Item`` to ``items`` (a failure to open the
    device is one line, never a traceback) and returns the body's lines for the report.
    """
    if not all(item.ok for item in items):
        return []
    try:
        body, waited = first_body(wait_s)
    except Exception as exc:  # no device, a driver error: one line
        items.append(Item(device, False, f"{cannot_open}: {exc}"))
        return []
    if body is None:
        items.append(Item("a tracked body", False, f"none in {waited:.1f} s: {none_hint}"))
        return []
    items.append(Item("a tracked body", True, f"after {waited:.1f} s; {space}"))
    return format_skeleton(body)


def report(title: str, items: list[Item], extra: list[str] = ()) -> tuple[str, bool]:
    """(text, every item ok)."""
    lines = [title]
    for item in items:
        lines.append(f"  [{'ok' if item.ok else 'missing'}] {item.name}"
                     + (f": {item.detail}" if item.detail else ""))
    lines.extend(extra)
    return "\n".join(lines), all(item.ok for item in items)
