"""Progress of long computations: a small record and a terminal reporter.

Long functions (e.g. :func:`greybox.close_the_loop`) take an optional
``progress`` callable and call it with a :class:`Progress` record at stage
boundaries. Nothing is printed unless the caller asks: the command line
passes a :class:`TerminalProgress` when stderr is a terminal, and a
:class:`LogProgress` (whole lines, at most one every 10 s) when it is not
(a log file, CI).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

from .exceptions import DimensionError

__all__ = ["Progress", "TerminalProgress", "LogProgress", "ProgressClock"]


@dataclass(frozen=True)
class Progress:
    """Where a long computation stands.

    Attributes
    ----------
    stage : str
        What is being done (e.g. "trace channels").
    k : int
        Steps of this stage done so far (0 when it starts).
    K : int
        Steps of this stage in all.
    elapsed : float
        Time since the computation started [s].
    """

    stage: str
    k: int
    K: int
    elapsed: float


class ProgressClock:
    """Sends :class:`Progress` records to a callback (or nowhere), timing from creation.

    Parameters
    ----------
    callback : callable or None
        Called with one :class:`Progress`; None reports nothing.
    """

    def __init__(self, callback=None):
        if callback is not None and not callable(callback):
            raise DimensionError(f"progress must be a callable taking a Progress record, or "
                                 f"None; found {type(callback).__name__}")
        self._callback = callback
        self._t0 = time.perf_counter()

    def __call__(self, stage: str, k: int = 0, K: int = 1) -> None:
        """Report that ``k`` of ``K`` steps of ``stage`` are done."""
        if self._callback is not None:
            self._callback(Progress(stage, int(k), int(K), time.perf_counter() - self._t0))


class TerminalProgress:
    """Progress on one rewritten stderr line, shown only once a run lasts ``delay`` seconds.

    Parameters
    ----------
    stream : file-like, optional
        Where to write (default ``sys.stderr``).
    delay : float
        Stay silent during the first ``delay`` seconds [s].
    """

    def __init__(self, stream=None, delay: float = 2.0):
        self._stream = stream if stream is not None else sys.stderr
        self._delay = float(delay)
        self._shown = False

    def __call__(self, p: Progress) -> None:
        """Show one :class:`Progress` record."""
        if p.elapsed < self._delay:
            return
        self._stream.write(f"\r\x1b[K[{p.elapsed:6.1f} s] {p.stage}: {p.k} of {p.K}")
        self._stream.flush()
        self._shown = True

    def close(self) -> None:
        """End the progress line (if one was shown)."""
        if self._shown:
            self._stream.write("\r\x1b[K")
            self._stream.flush()
            self._shown = False


class LogProgress:
    """Progress as whole lines, for a stream that is not a terminal (a log file, CI).

    A line is written when a stage starts or advances, at most one every
    ``interval`` seconds and none in the first ``interval`` seconds: a short
    run stays silent, a long one shows it is alive.

    Parameters
    ----------
    stream : file-like, optional
        Where to write (default ``sys.stderr``).
    interval : float
        Fewest seconds between two lines [s].
    """

    def __init__(self, stream=None, interval: float = 10.0):
        self._stream = stream if stream is not None else sys.stderr
        self._interval = float(interval)
        self._last = 0.0
        self._shown = None

    def __call__(self, p: Progress) -> None:
        """Write one :class:`Progress` record as a line, unless one was written lately."""
        if p.elapsed - self._last < self._interval or (p.stage, p.k) == self._shown:
            return
        self._stream.write(f"greybox: progress: {p.elapsed:.0f} s, {p.stage} ({p.k} of "
                           f"{p.K})\n")
        self._stream.flush()
        self._last, self._shown = p.elapsed, (p.stage, p.k)

    def close(self) -> None:
        """Nothing to end (each line is whole)."""
