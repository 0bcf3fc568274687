"""Server-to-View output: the registered views and the datagrams each fused person sends them.

The paper's Server-to-View API (section 4.1): ``/newUser id x y z`` when a
person is found, ``/jointCoordinates id (jointName x y z confidence)*`` per
fused frame, ``/handState id hand state`` when a hand's vote changes and
``/lostUser id``. Ids are the fused persons', never the clients'. Runs on the
engine thread; the transport must not block.

Views come from the rig and the command line (static: kept for the whole
show) or from ``/registerView`` (docs/security.md): the target must be in
the rig's ``allow: views`` list and numeric (``127.1`` and ``127.0.0.1``
are one view), the table is capped (``limits.max_views``), a registration
lasts ``limits.view_ttl_s`` unless renewed (a view that re-registers
periodically keeps working, as Kuatro views do), and a view the kernel
reports unreachable ``limits.view_send_errors`` times in a row is dropped.
So nobody outside the allow-list can make the server send anything, and
nobody inside it can make the server send for ever to a closed port.

By default a view gets every update of every person as it is fused. A view
that registers with a rate (``/registerView ip port rateHz``) instead gets
``/jointCoordinates`` of every person at that rate, each predicted to the
moment it is sent (``due``, called by the engine's timer).

A view may also ask for a forecast (``/registerView ip port rateHz forecastS``,
rate 0 for every update; the rig's ``forecast: views_s`` for the rig's and the
command line's views): it then gets each body predicted that far past its
capture time (``stage.engine.forecast``; docs/anticipation.md), bounded, instead
of the body as measured. ``forecasts`` holds who asked for what.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from typing import Iterable, Protocol

import numpy as np

from ..joints import HandState
from ..network import Networks, canonical_ipv4
from ..sensors.protocol import (RegisterView, encode_message, encode_view_hand_state,
                                encode_view_joints, encode_view_lost_user, encode_view_new_user)
from ..settings import LimitSettings
from ..stats import DropCounter, OTHER
from . import jit

log = logging.getLogger("stage.engine")


def _encode_joints(pid: int, joints: np.ndarray, conf: np.ndarray) -> bytes:
    """A fused skeleton's ``/jointCoordinates`` (one per person per update: the compiled
    encoder when the kernels are used, the same bytes as ``encode_view_joints``)."""
    if jit.ready():
        return jit.view_joints(pid, joints, conf)
    return encode_view_joints(pid, joints, conf)


class Transport(Protocol):
    def send(self, data: bytes, address: tuple[str, int]) -> None:
        """Send one datagram; must not block and must not raise."""


@dataclass
class ViewEntry:
    """A view registered over OSC."""

    expires: float
    registered: float
    refused: int = 0          # ICMP refusals since it last (re-)registered
    sent: int = 0


class ViewOutput:
    """The views registered with the server and what is sent to them."""

    def __init__(self, transport: Transport | None, views: Iterable[tuple[str, int]] = (),
                 limits: LimitSettings | None = None, allow: Networks | None = None,
                 drops: DropCounter | None = None, forecast_s: float = 0.0,
                 max_forecast_s: float = 0.2) -> None:
        self.transport = transport
        self.limits = limits or LimitSettings()
        self.allow = allow
        self.drops = drops
        self.static: list[tuple[str, int]] = list(dict.fromkeys(views))
        self.registered: dict[tuple[str, int], ViewEntry] = {}
        self.views: list[tuple[str, int]] = list(self.static)
        #: views that asked for a fixed rate: address -> (rate Hz, next send time or None)
        self.rates: dict[tuple[str, int], tuple[float, float | None]] = {}
        #: views that asked for a forecast: address -> seconds ahead (> 0)
        self.forecasts: dict[tuple[str, int], float] = {}
        self.static_forecast_s = forecast_s
        self.max_forecast_s = max_forecast_s
        if forecast_s > 0:
            self.forecasts.update({v: forecast_s for v in self.static})
        self._targets: dict[float, list[tuple[str, int]]] | None = None
        self.datagrams_out = 0
        self.send_errors = 0
        self.expired = 0
        self.dropped_unreachable = 0
        self.refused = 0

    def _update(self) -> None:
        self.views = self.static + [v for v in self.registered if v not in self.static]
        self._targets = None

    def add_static(self, address: tuple[str, int]) -> None:
        if address not in self.static:
            self.static.append(address)
            if self.static_forecast_s > 0:
                self.forecasts[address] = self.static_forecast_s
            self._update()

    def forecast_targets(self) -> dict[float, list[tuple[str, int]]]:
        """Horizon -> the views taking every update that want bodies that far ahead."""
        if self._targets is None:
            out: dict[float, list[tuple[str, int]]] = {}
            for view, h in self.forecasts.items():
                if view in self.views and view not in self.rates:
                    out.setdefault(h, []).append(view)
            self._targets = out
        return self._targets

    # ------------------------------------------------------------ registration
    def register(self, msg: RegisterView, announced: Iterable[tuple[int, np.ndarray,
                                                                    tuple[HandState, HandState]]],
                 now: float = 0.0, source: str = "?") -> None:
        """``/registerView`` or ``/unregisterView``; a new view learns who is on stage.

        announced: (person id, centre (3,), hands) of every person already found.
        """
        host = canonical_ipv4(msg.host)
        if host is None:
            self._refuse(source, "not_allowed", f"view {msg.host[:64]}:{msg.port} refused: "
                         "give a numeric IPv4 address")
            return
        target = (host, msg.port)
        if not msg.register:
            self.rates.pop(target, None)
            if target not in self.static:
                self.forecasts.pop(target, None)
            self._targets = None
            if self.registered.pop(target, None) is not None:
                self._update()
                log.info("view %s:%d unregistered", *target)
            return
        if self.allow is not None and not self.allow.allows(host):
            self._refuse(source, "not_allowed",
                         f"view {host}:{msg.port} refused: not in the rig's allow: views")
            return
        entry = self.registered.get(target)
        if entry is None:
            if target in self.static:
                return  # already sent to for the whole show
            if len(self.registered) >= self.limits.max_views:
                self._refuse(source, "too_many_views",
                             f"view {host}:{msg.port} refused: {len(self.registered)} views "
                             "registered already (limits: max_views)")
                return
            entry = self.registered[target] = ViewEntry(now + self.limits.view_ttl_s, now)
            self._update()
            log.info("view %s:%d registered (for %g s unless it registers again)", *target,
                     self.limits.view_ttl_s)
        else:
            entry.expires = now + self.limits.view_ttl_s
            entry.refused = 0
        if target not in self.static:
            ahead = min(msg.forecast_s or 0.0, self.max_forecast_s)
            if ahead > 0:
                if self.forecasts.get(target) != ahead:
                    log.info("view %s:%d takes bodies forecast %g s ahead", *target, ahead)
                self.forecasts[target] = ahead
            else:
                self.forecasts.pop(target, None)
        self._targets = None
        if msg.rate_hz:
            if target not in self.rates:
                log.info("view %s:%d takes %g updates a second", *target, msg.rate_hz)
            self.rates[target] = (msg.rate_hz, self.rates.get(target, (0.0, None))[1])
        else:
            self.rates.pop(target, None)
        for pid, centre, hands in announced:
            self.send(encode_view_new_user(pid, centre), target)
            for hand in (0, 1):
                self.send(encode_view_hand_state(pid, hand, hands[hand]), target)

    def _refuse(self, source: str, reason: str, text: str) -> None:
        self.refused += 1
        if self.drops is not None:
            self.drops.add(source, reason)
        # a refusal is logged at most once per 100, so a flood of them cannot fill the log
        if self.refused % 100 == 1:
            log.warning("%s (%d refused so far)", text, self.refused)

    def expire(self, now: float) -> None:
        """Drop registrations that were not renewed in time (engine tick)."""
        gone = [v for v, e in self.registered.items() if now >= e.expires]
        for view in gone:
            del self.registered[view]
            self.rates.pop(view, None)
            self.forecasts.pop(view, None)
            self.expired += 1
            log.info("view %s:%d expired: it did not register again within %g s", *view,
                     self.limits.view_ttl_s)
        if gone:
            self._update()

    def unreachable(self, host: str, port: int) -> None:
        """The kernel says a datagram to (host, port) was refused (nobody listens there)."""
        self.send_errors += 1
        entry = self.registered.get((host, port))
        if entry is None:
            return
        entry.refused += 1
        if entry.refused >= self.limits.view_send_errors:
            del self.registered[(host, port)]
            self.rates.pop((host, port), None)
            self.forecasts.pop((host, port), None)
            self.dropped_unreachable += 1
            self._update()
            log.warning("view %s:%d dropped: its port refused %d datagrams in a row (closed?)",
                        host, port, entry.refused)

    def allowed(self, host: str) -> bool:
        """May replies (stats, health) go to ``host``?"""
        return self.allow is None or self.allow.allows(host)

    def describe(self, now: float) -> list[dict]:
        """Per view: address, kind, seconds left, refusals (stats, health)."""
        out: list[dict] = [{"address": f"{h}:{p}", "static": True} for h, p in self.static]
        for (h, p), e in self.registered.items():
            out.append({"address": f"{h}:{p}", "static": False,
                        "expires_in_s": round(e.expires - now, 1), "refused": e.refused})
        for entry in out:
            h, p = entry["address"].rsplit(":", 1)
            ahead = self.forecasts.get((h, int(p)))
            if ahead:
                entry["forecast_s"] = ahead
        return out

    # ------------------------------------------------------------ messages
    # (nothing is encoded when nobody would receive it: offline runs and view-less servers)
    def new_user(self, pid: int, centre: np.ndarray) -> None:
        if self.views and self.transport is not None:
            self.broadcast(encode_view_new_user(pid, centre))

    def joints(self, pid: int, joints: np.ndarray, conf: np.ndarray,
               targets: list[tuple[str, int]] | None = None,
               encoded: bytes | None = None) -> None:
        """To every view that takes every update (default), or to ``targets``. ``encoded``:
        the message already encoded from these joints (the native core's), not again."""
        if targets is not None:
            data = _encode_joints(pid, joints, conf)
            for view in targets:
                self.send(data, view)
            return
        if not self.views or self.transport is None:
            return
        data = encoded if encoded is not None else _encode_joints(pid, joints, conf)
        if not self.rates and not self.forecasts:
            self.broadcast(data)
            return
        for view in self.views:
            if view not in self.rates and view not in self.forecasts:
                self.send(data, view)

    # ------------------------------------------------------------ fixed rates
    def due(self, now: float) -> list[tuple[str, int]]:
        """The fixed-rate views whose next send is due at ``now`` (and schedule the next)."""
        out = []
        for view, (rate, next_t) in self.rates.items():
            if next_t is None or now >= next_t:
                out.append(view)
                period = 1.0 / rate
                # keep the grid; after a stall, start again from now
                following = now + period if next_t is None or now - next_t > period \
                    else next_t + period
                self.rates[view] = (rate, following)
        return out

    def next_due(self) -> float | None:
        """When the next fixed-rate send is due (None: no such view)."""
        times = [t for _, t in self.rates.values()]
        if not times:
            return None
        return min(float("-inf") if t is None else t for t in times)

    def hand(self, pid: int, hand: int, state: HandState) -> None:
        if self.views and self.transport is not None:
            self.broadcast(encode_view_hand_state(pid, hand, state))

    def lost_user(self, pid: int) -> None:
        if self.views and self.transport is not None:
            self.broadcast(encode_view_lost_user(pid))

    # ------------------------------------------------------------ sending
    def broadcast(self, data: bytes) -> None:
        for view in self.views:
            self.send(data, view)

    def send(self, data: bytes, address: tuple[str, int]) -> None:
        if self.transport is None:
            return
        try:
            self.transport.send(data, address)
            self.datagrams_out += 1
        except OSError:
            self.send_errors += 1


# ---------------------------------------------------------------- the stats reply

def encode_stats(stats: dict, limit: int) -> bytes:
    """``/stage/stats JSON`` in one datagram of at most ``limit`` bytes, whatever the stats.

    When the whole JSON does not fit, the biggest parts are cut down in turn
    (drop keys to totals per reason, clients to the first ones by id,
    persons and views to counts) and ``"truncated"`` says what was left out;
    ``stage stats`` and monitors read the same keys either way.
    """
    data = encode_message("/stage/stats", json.dumps(stats, separators=(",", ":")))
    if len(data) <= limit:
        return data
    out = dict(stats)
    notes: list[str] = []
    drops = out.get("drops") or {}
    if drops:
        totals: dict[str, int] = {}
        for reasons in drops.values():
            for reason, n in reasons.items():
                totals[reason] = totals.get(reason, 0) + n
        out["drops"] = {OTHER: totals}
        notes.append(f"drops of {len(drops)} keys summed by reason")
    clients = out.get("clients") or {}
    for client in clients.values():
        client.pop("drops", None)
    for key in ("views", "persons"):
        value = out.get(key)
        if value and len(value) > 8:
            out[key] = list(value)[:8] if isinstance(value, list) else dict(
                list(value.items())[:8])
            notes.append(f"{key}: first 8 of {len(value)}")
    keep = len(clients)
    while True:
        if keep < len(clients):
            out["clients"] = dict(sorted(clients.items())[:keep])
        note = "; ".join(notes + ([f"clients: first {keep} of {len(clients)}"]
                                  if keep < len(clients) else []))
        out["truncated"] = note + " (the reply must fit one datagram)"
        data = encode_message("/stage/stats", json.dumps(out, separators=(",", ":")))
        if len(data) <= limit or keep == 0:
            break
        keep = keep // 2 if keep > 1 else 0
    if len(data) > limit:  # nothing left to cut but numbers: the bare minimum
        data = encode_message("/stage/stats", json.dumps(
            {"uptime_s": stats.get("uptime_s"), "drops_total": stats.get("drops_total"),
             "counts": stats.get("counts"), "truncated": "only the totals fit one datagram"},
            separators=(",", ":")))
    return data
