"""Progress on the terminal: frame i of n, the current step, the time left.

Quiet when the stream is not a terminal (CI logs, pipes) or when asked; never used by solvers.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """One status line, rewritten in place (``\\r``), finished with a newline by :meth:`done`.

    ``quiet``: None decides from ``stream.isatty()``.
    """

    def __init__(self, total: int, stream: TextIO | None = None, quiet: bool | None = None):
        self.total = int(total)
        self.stream = stream if stream is not None else sys.stderr
        if quiet is None:
            isatty = getattr(self.stream, "isatty", None)
            quiet = not (isatty is not None and isatty())
        self.quiet = quiet
        self._t0 = time.monotonic()
        self._done = 0
        self._width = 0

    def time_left_s(self) -> float | None:
        """Wall time left, extrapolated from the frames done so far (None before the first)."""
        if self._done == 0:
            return None
        per = (time.monotonic() - self._t0) / self._done
        return per * (self.total - self._done)

    def step(self, index: int, what: str) -> None:
        """Show ``frame index+1 of total: what`` and the time left."""
        left = self.time_left_s()
        eta = f", about {left:.0f} s left" if left is not None else ""
        self._show(f"frame {index + 1} of {self.total}: {what}{eta}")

    def frame_done(self) -> None:
        """Count one frame as done (for the time estimate)."""
        self._done += 1

    def message(self, text: str) -> None:
        """A status line that is not about a frame (connecting, solving)."""
        self._show(text)

    def _show(self, text: str) -> None:
        if self.quiet:
            return
        pad = max(0, self._width - len(text))
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()
        self._width = len(text)

    def done(self, text: str = "") -> None:
        """End the line (and print ``text`` on its own line)."""
        if self.quiet:
            return
        self._show(text)
        self.stream.write("\n")
        self.stream.flush()
        self._width = 0
