"""The engine: one thread that owns all live state (see ``engine.py``)."""

from .engine import Engine, Inbound, Transport

__all__ = ["Engine", "Inbound", "Transport"]
