"""Network addresses as users write them: ``HOST:PORT``, and allow-lists of networks.

``Networks`` is an allow-list as the rig file spells it (``allow: {sensors:
[...], views: [...]}``, docs/security.md): IPv4 addresses, networks in CIDR
form, and two words -- ``loopback`` (127.0.0.0/8) and ``local`` (the
networks this machine's interfaces are directly on: the rig's own subnet).
The default, ``[loopback, local]``, lets in this machine and the sensors and
views on its own network segment, and nobody routed from elsewhere.
"""

from __future__ import annotations

import ipaddress
import socket
import struct
import sys
from typing import Iterable

#: The allow-list a rig gets when it names none (docs/security.md).
DEFAULT_ALLOW = ("loopback", "local")


def parse_hostport(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """'host:port' or 'port' -> (host, port); ValueError with a readable message."""
    host, _, port = str(text).rpartition(":")
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError(f"'{text}' is not HOST:PORT with a port from 1 to 65535")
    return host or default_host, int(port)


def canonical_ipv4(host: str) -> str | None:
    """The dotted-quad form of a numeric IPv4 address however it is written, else None.

    ``127.1``, ``0x7f000001``, ``2130706433`` and ``127.000.000.001`` are all
    127.0.0.1 to the C library, so they must be one address here too (a view
    registered 13 ways must get one copy). "localhost" is 127.0.0.1; other
    names are not resolved (that would block on DNS): None.
    """
    text = host.strip()
    if text.lower() == "localhost":
        return "127.0.0.1"
    if not text or len(text) > 64 or not all(c in "0123456789abcdefxABCDEFX." for c in text):
        return None
    try:
        return socket.inet_ntoa(socket.inet_aton(text))
    except OSError:
        return None


def local_networks() -> list[ipaddress.IPv4Network]:
    """The IPv4 networks this machine is directly on (its interfaces' subnets).

    Linux: the routing table's on-link routes (/proc/net/route); elsewhere the
    host name's addresses, each as a /24 (a usual LAN), documented as such.
    """
    nets: list[ipaddress.IPv4Network] = []
    if sys.platform.startswith("linux"):
        try:
            with open("/proc/net/route", encoding="ascii") as f:
                next(f)
                for line in f:
                    parts = line.split()
                    if len(parts) < 8:
                        continue
                    dest, gateway, mask = (int(parts[k], 16) for k in (1, 2, 7))
                    if gateway != 0 or mask == 0:
                        continue  # via a router, or the default route: not our segment
                    # the file holds little-endian 32-bit words
                    net = socket.inet_ntoa(struct.pack("<I", dest))
                    bits = bin(mask).count("1")
                    nets.append(ipaddress.IPv4Network(f"{net}/{bits}", strict=False))
        except (OSError, ValueError, StopIteration):
            pass
    if not nets:
        try:
            addrs = {a[4][0] for a in socket.getaddrinfo(socket.gethostname(), None,
                                                          socket.AF_INET)}
        except OSError:
            addrs = set()
        for addr in addrs:
            if not addr.startswith("127."):
                nets.append(ipaddress.IPv4Network(f"{addr}/24", strict=False))
    return nets


class Networks:
    """An allow-list of IPv4 networks; ``allows(ip)`` is the check (cached, bounded)."""

    _CACHE = 1024

    def __init__(self, entries: Iterable[str] = DEFAULT_ALLOW) -> None:
        self.entries = tuple(str(e) for e in entries)
        nets: list[ipaddress.IPv4Network] = []
        for entry in self.entries:
            nets.extend(parse_network(entry))
        self.networks = tuple(dict.fromkeys(nets))
        self._any = any(n.prefixlen == 0 for n in self.networks)
        self._cache: dict[str, bool] = {}

    def allows(self, ip: str) -> bool:
        if self._any:
            return True
        hit = self._cache.get(ip)
        if hit is not None:
            return hit
        try:
            address = ipaddress.IPv4Address(ip)
            ok = any(address in net for net in self.networks)
        except ValueError:
            ok = False
        if len(self._cache) >= self._CACHE:  # spoofed sources must not grow memory
            self._cache.clear()
        self._cache[ip] = ok
        return ok

    def describe(self) -> str:
        return ", ".join(str(n) for n in self.networks) or "nobody"

    def __repr__(self) -> str:
        return f"Networks({list(self.entries)!r})"


def parse_network(entry: str) -> list[ipaddress.IPv4Network]:
    """One allow-list entry -> networks; ValueError with a readable message."""
    text = str(entry).strip()
    low = text.lower()
    if low == "loopback":
        return [ipaddress.IPv4Network("127.0.0.0/8")]
    if low == "local":
        return local_networks()
    if low in ("any", "all"):
        return [ipaddress.IPv4Network("0.0.0.0/0")]
    if low == "localhost":
        return [ipaddress.IPv4Network("127.0.0.1/32")]
    try:
        return [ipaddress.IPv4Network(text, strict=False)]
    except ValueError:
        raise ValueError(f"'{text}' is not an IPv4 address, a network (10.0.0.0/24), "
                         "'loopback', 'local' or 'any'") from None
