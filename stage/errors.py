"""The one exception tree of stage. User-facing errors carry a one-line message."""

from __future__ import annotations


class StageError(Exception):
    """Base of every error stage raises on purpose."""


class ConfigError(StageError):
    """A rig or piece file is wrong; the message names file:line:column."""

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


class TransportError(StageError):
    """A socket or port could not be opened (address in use, no such port)."""


class ProtocolError(StageError):
    """An OSC datagram is malformed; ``reason`` is the drop counter it goes to."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
