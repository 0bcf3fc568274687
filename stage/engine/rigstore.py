"""Saving the rig file without making the engine thread wait for the disk.

The engine thread owns the ``Rig``: it applies a calibration result and
takes a snapshot of the rig there (``Rig.to_dict``: fresh plain lists and
dicts), then hands it to this store, whose one writer thread turns it into
YAML and writes it atomically (temp file, fsync, rename). A slow or full disk delays the file, never a fused frame.
Writes for one path are coalesced: only the newest text is written.
``threaded=False`` writes at once on the caller's thread (tests, offline runs).
"""

from __future__ import annotations

import logging
import os
import shutil
import stat
import threading

import yaml

from ..errors import StageError
from ..rig import Rig
from ..yamlio import write_atomic

log = logging.getLogger("stage.engine")


class RigStore:
    """Writes rig snapshots to their files, newest wins (see the module docstring)."""

    def __init__(self, threaded: bool = True) -> None:
        self.threaded = threaded
        self._pending: dict[str, tuple[dict, str]] = {}   # path -> (snapshot, what)
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._writing = 0
        self.saved = 0
        self.errors = 0

    def save(self, rig: Rig, path: str, what: str = "") -> None:
        """Snapshot ``rig`` now (call on the thread that owns it) and write it to ``path``."""
        snapshot = rig.to_dict()
        if not self.threaded:
            self._write(path, snapshot, what)
            return
        with self._cond:
            self._pending[path] = (snapshot, what)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="stage-rig-writer",
                                                daemon=True)
                self._thread.start()
            self._cond.notify_all()

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until every snapshot handed in so far is written; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._pending and not self._writing, timeout)

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: bool(self._pending))
                path, (snapshot, what) = self._pending.popitem()
                self._writing += 1
            try:
                self._write(path, snapshot, what)
            finally:
                with self._cond:
                    self._writing -= 1
                    self._cond.notify_all()

    def _write(self, path: str, snapshot: dict, what: str) -> None:
        if _read_only(path):
            # an installer who made the rig read-only means it (root could still replace it)
            self.errors += 1
            log.warning("rig %s is read-only: %s is in use but not saved", path,
                        what or "the calibration")
            return
        _keep_original(path)
        try:
            write_atomic(path, yaml.safe_dump(snapshot, sort_keys=False))
        except (OSError, StageError) as exc:
            self.errors += 1
            log.error("could not write the rig %s: %s (the calibration is in use anyway)",
                      path, exc)
            return
        self.saved += 1
        log.info("rig %s updated%s", path, f" with {what}" if what else "")


def _read_only(path: str) -> bool:
    """The file exists and nobody may write it (its mode, not our rights: root may)."""
    try:
        return not os.stat(path).st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH)
    except OSError:
        return False


def _keep_original(path: str) -> None:
    """Before the first rewrite of a rig written by hand (it has comments, which YAML
    rewriting loses), keep it as ``PATH.orig``."""
    original = path + ".orig"
    try:
        if os.path.exists(original):
            return
        with open(path, encoding="utf-8") as f:
            if not any(line.lstrip().startswith("#") for line in f):
                return
        shutil.copy2(path, original)
        log.info("rig %s is rewritten with its calibrations: the hand-written file, with its "
                 "comments, is kept as %s", path, original)
    except OSError:
        return
