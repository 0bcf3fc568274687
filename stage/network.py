"""Network addresses as users write them: ``HOST:PORT`` in rig files, pieces and options."""

from __future__ import annotations


def parse_hostport(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """'host:port' or 'port' -> (host, port); ValueError with a readable message."""
    host, _, port = str(text).rpartition(":")
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError(f"'{text}' is not HOST:PORT with a port from 1 to 65535")
    return host or default_host, int(port)
