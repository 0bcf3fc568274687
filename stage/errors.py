"""The one exception tree of stage. User-facing errors carry a one-line message.

    StageError                a run-time failure: `stage` exits 1
    ├── BadInput              the user's command line or files are wrong: `stage` exits 2
    │   ├── ConfigError       a rig, piece, scenario, motion file or option value
    │   ├── RecordingError    a recording that cannot be read or written
    │   └── MusicError        a note, chord or phrase written wrongly
    ├── TransportError        a socket or MIDI port that cannot be opened
    └── CalibrationError      data that cannot give a transform

The ``stage`` command maps the class to its exit status (``BadInput`` -> 2, any
other ``StageError`` -> 1), so a command raises and never converts errors itself.
Malformed OSC datagrams are not errors: the decoder drops and counts them by reason.
"""

from __future__ import annotations


class StageError(Exception):
    """Base of every error stage raises on purpose; by itself a run-time failure (exit 1)."""


class BadInput(StageError):
    """The user's command line or files are wrong (exit 2); base of the errors below it."""


class ConfigError(BadInput):
    """A rig, piece, scenario or option is wrong, at file:line:column (bad input, exit 2)."""

    def __init__(self, message: str, *, path: str | None = None, line: int | None = None,
                 column: int | None = None) -> None:
        self.path, self.line, self.column = path, line, column
        where = ""
        if path is not None:
            where = path
            if line is not None:
                where += f":{line}"
                if column is not None:
                    where += f":{column}"
            where += ": "
        super().__init__(where + message)
        self.bare_message = message


class RecordingError(BadInput):
    """A file is not a stage recording or cannot be read or written (bad input, exit 2)."""


class MusicError(BadInput):
    """A note, chord or phrase is written wrongly; the loader adds where (bad input, exit 2)."""


class TransportError(StageError):
    """A socket or MIDI port cannot be opened: in use, no such port (run-time failure, exit 1)."""


class CalibrationError(StageError):
    """The data give no transform: too few pairs, degenerate poses (run-time failure, exit 1)."""


__all__ = ["StageError", "BadInput", "ConfigError", "RecordingError", "MusicError",
           "TransportError", "CalibrationError"]
