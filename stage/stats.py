"""Counters that cross threads: drops per client and reason, latency samples."""

from __future__ import annotations

import threading
from collections import defaultdict

import numpy as np


#: the key drops are counted under once ``max_keys`` keys exist, and for senders that
#: are not allowed at all: whoever sends junk from many ports or ids gets one line
OTHER = "(other)"
#: a key longer than this is cut (keys are client ids or "ip:port", both short when honest)
MAX_KEY_CHARS = 64


class DropCounter:
    """Counts dropped messages per client (or source address) and reason.

    Written by the receiver and engine threads, read by the stats query and
    the once-a-minute log line; a lock keeps the counts exact. Memory is
    bounded: at most ``max_keys`` keys (plus the clients the engine names
    with ``keep``); drops of any other key are counted under ``OTHER``, so
    every drop is still counted, whatever ids or source ports arrive.
    """

    def __init__(self, max_keys: int = 256) -> None:
        self.max_keys = max_keys
        self._lock = threading.Lock()
        self._counts: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
        self._reported: dict[tuple[str, str], int] = {}
        self._kept: set[str] = set()

    def add(self, client: str, reason: str, n: int = 1) -> None:
        if len(client) > MAX_KEY_CHARS:
            client = client[:MAX_KEY_CHARS - 1] + "~"
        with self._lock:
            counts = self._counts.get(client)
            if counts is None:
                if len(self._counts) >= self.max_keys and client not in self._kept:
                    client = OTHER
                counts = self._counts[client]
            counts[reason] += n

    def keep(self, client: str) -> None:
        """Count ``client`` under its own key even beyond ``max_keys`` (a known sensor)."""
        with self._lock:
            self._kept.add(client)

    def forget(self, client: str) -> None:
        """A client the engine no longer knows: its counts join ``OTHER``."""
        with self._lock:
            self._kept.discard(client)
            counts = self._counts.pop(client, None)
            if counts:
                other = self._counts[OTHER]
                for reason, n in counts.items():
                    other[reason] += n
                    key = (client, reason)
                    done = self._reported.pop(key, 0)
                    self._reported[(OTHER, reason)] = self._reported.get((OTHER, reason), 0) + done

    def __len__(self) -> int:
        with self._lock:
            return len(self._counts)

    def snapshot(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {c: dict(r) for c, r in self._counts.items()}

    def total(self, reason: str | None = None) -> int:
        with self._lock:
            return sum(n for r in self._counts.values() for k, n in r.items()
                       if reason is None or k == reason)

    def since_last_report(self) -> dict[str, dict[str, int]]:
        """The counts added since the previous call (for the per-minute log line)."""
        out: dict[str, dict[str, int]] = {}
        with self._lock:
            for client, reasons in self._counts.items():
                for reason, n in reasons.items():
                    before = self._reported.get((client, reason), 0)
                    if n > before:
                        out.setdefault(client, {})[reason] = n - before
                        self._reported[(client, reason)] = n
        return out


def format_drops(drops: dict[str, dict[str, int]]) -> str:
    return "; ".join(f"{client}: " + ", ".join(f"{r} {n}" for r, n in sorted(reasons.items()))
                     for client, reasons in sorted(drops.items()))


class LatencyWindow:
    """The last ``size`` latency samples (seconds), for p50/p99 on demand."""

    def __init__(self, size: int = 4096) -> None:
        self._buf = np.zeros(size)
        self._n = 0

    @property
    def count(self) -> int:
        """Samples added since the start (not only those still kept)."""
        return self._n

    def add(self, seconds: float) -> None:
        self._buf[self._n % len(self._buf)] = seconds
        self._n += 1

    def summary_ms(self, since: int | None = None) -> dict[str, float]:
        """p50, p99 and max (ms) of the samples kept, or of those added after the
        ``since``-th (``count`` at an earlier moment; as many of them as are still kept)."""
        n = min(self._n, len(self._buf))
        if since is not None:
            n = min(n, max(self._n - since, 0))
        if n == 0:
            return {"n": 0}
        end = self._n % len(self._buf)
        idx = (end - 1 - np.arange(n)) % len(self._buf)     # the newest n samples
        v = self._buf[idx] * 1e3
        return {"n": self._n if since is None else n, "p50": float(np.percentile(v, 50)),
                "p99": float(np.percentile(v, 99)), "max": float(v.max())}
