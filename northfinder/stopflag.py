"""StopFlag: SIGINT/SIGTERM raise a flag that a run checks between device exchanges.

On the ground floor (no northfinder imports) because every kind of run uses it: the turntable
sequence, the swaying and the GNSS alignments.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from typing import Any


class StopFlag:
    """Signal handlers that only raise a flag (the first time) so that no I/O is torn in half."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def __bool__(self) -> bool:
        return self.signum is not None

    def _handler(self, signum: int, frame: Any) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt  # second signal: stop now
        self.signum = signum

    @contextlib.contextmanager
    def installed(self) -> Iterator[StopFlag]:
        """Install SIGINT and SIGTERM handlers for the duration (main thread only)."""
        old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            for s in old:
                signal.signal(s, self._handler)
            yield self
        finally:
            for s, h in old.items():
                signal.signal(s, h)
