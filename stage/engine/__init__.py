"""The engine: one thread that owns all live state (see ``engine.py``)."""

from .engine import Engine
from .output import Transport

__all__ = ["Engine", "Transport"]
