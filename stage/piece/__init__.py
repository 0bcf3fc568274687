"""Pieces: the composer's YAML language, its loader and checker, and its runtime.

    from stage.piece import load_piece, PieceRuntime
    piece = load_piece("pieces/liminal.yaml")        # ConfigError: file:line:column
    runtime = PieceRuntime(piece, sink, seed=1)      # an engine listener
    engine.listeners.append(runtime)

The format is defined once in ``stage.piece.language``; the JSON Schema
shipped for editors (``piece.schema.json``) is generated from it.
"""

from .loader import load_piece, loads_piece
from .model import Mapping, Phrase, Piece, Section, Trigger, Zone
from .runtime import FanoutSink, PieceRuntime, RecordingSink

__all__ = ["load_piece", "loads_piece", "Piece", "Section", "Trigger", "Mapping", "Phrase", "Zone",
           "PieceRuntime", "RecordingSink", "FanoutSink"]
