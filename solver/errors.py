"""The exception hierarchy of slidecal.

Every message says what was wrong and how to fix it, in one line, so that the command line can
print it as it is (``slidecal: <message>``) without a traceback.
"""

from __future__ import annotations


class SlidecalError(Exception):
    """Base class of every error slidecal raises on purpose."""


class InputError(SlidecalError):
    """Bad input: a file, a field or an argument is missing, malformed or inconsistent.

    ``where`` names the file and field (``session.yaml: frames[3].T_base_tool``) when known.
    """

    def __init__(self, message: str, where: str | None = None) -> None:
        self.where = where
        super().__init__(f"{where}: {message}" if where else message)


class DegenerateError(SlidecalError):
    """The data (or a plan) cannot determine the requested parameters (docs/METHOD.md Sec. 7)."""


class HardwareFault(SlidecalError):
    """The robot or a camera reported a fault (protective stop, lost connection, time-out)."""
