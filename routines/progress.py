"""Progress of a run: frame i of n, the current step, the time left, and what happened; on a
terminal one status line, elsewhere plain timestamped lines (docs/UNATTENDED.md, "Logs a job can
keep"). :func:`signals_as_interrupt`: Ctrl-C, SIGTERM or SIGHUP as :class:`Interrupted`.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from typing import Any, TextIO


class Progress:
    """Progress output: ``quiet`` prints nothing; ``lines`` forces plain timestamped lines (None:
    when ``stream`` is not a terminal, else one status line rewritten in place)."""

    @classmethod
    def from_option(cls, progress: bool | Progress | None, total: int) -> Progress:
        """The progress of a routine's ``progress`` option: a given :class:`Progress` as it
        is, True/False to force the output on/off, None for on."""
        if isinstance(progress, Progress):
            return progress
        return cls(total, quiet=False if progress is None else not progress)

    def __init__(
        self,
        total: int,
        stream: TextIO | None = None,
        quiet: bool | None = None,
        lines: bool | None = None,
    ):
        self.total = int(total)
        self.stream = stream if stream is not None else sys.stderr
        isatty = getattr(self.stream, "isatty", None)
        tty = bool(isatty is not None and isatty())
        self.quiet = bool(quiet)
        self.lines = (not tty) if lines is None else bool(lines)
        self._t0 = time.monotonic()
        self._done = 0
        self._width = 0

    def step(self, index: int, what: str) -> None:
        """Show ``frame index+1 of total: what`` and the wall time left, extrapolated from the
        frames done so far."""
        left = (time.monotonic() - self._t0) / max(self._done, 1) * (self.total - self._done)
        eta = f", about {left:.0f} s left" if self._done else ""
        self.message(f"frame {index + 1} of {self.total}: {what}{eta}")

    def frame_done(self, detail: str | None = None) -> None:
        """Count one frame as done (for the time estimate); ``detail``: e.g. the corner counts,
        logged in the plain-line mode."""
        self._done += 1
        if detail and self.lines:
            self._line(f"frame {self._done} of {self.total} done: {detail}")

    def event(self, text: str) -> None:
        """Something a log must keep (a retry, a fault, the verdict): its own line always."""
        if not self.lines:
            self.done()
        self._line(text)

    def _line(self, text: str) -> None:
        if self.quiet:
            return
        stamp = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
        self.stream.write(f"{stamp} {text}\n")
        self.stream.flush()

    def message(self, text: str) -> None:
        """The status line (connecting, solving; a frame's step), or a plain line."""
        if self.quiet:
            return
        if self.lines:
            self._line(text)
            return
        pad = max(0, self._width - len(text))
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()
        self._width = len(text)

    def done(self, text: str = "") -> None:
        """End the status line (and print ``text`` on its own line)."""
        if self.quiet:
            return
        if self.lines:
            if text:
                self._line(text)
            return
        if self._width == 0 and not text:
            return
        self.message(text)
        self.stream.write("\n")
        self.stream.flush()
        self._width = 0


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, SIGTERM or SIGHUP: the run stops like on Ctrl-C (robot stopped, frames kept)."""

    def __init__(self, how: str = "Ctrl-C") -> None:
        super().__init__(f"stopped by {how}")
        self.how = how


@contextmanager
def signals_as_interrupt() -> Iterator[None]:
    """Within the block, SIGINT, SIGTERM and SIGHUP raise :class:`Interrupted` (main thread only;
    the previous handlers come back after). SIGINT too, as a process started in the background
    inherits it ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    names = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}
    if hasattr(signal, "SIGHUP"):
        names[signal.SIGHUP] = "SIGHUP"

    def handler(signum: int, _frame: Any) -> None:
        raise Interrupted(names.get(signum, f"signal {signum}"))

    old = {s: signal.signal(s, handler) for s in names}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
