"""A progress line on stderr for the bag tools' passes over a bag (every few seconds, with an ETA)."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """Reports ``done`` of ``total`` items to ``stream`` at most every ``every`` seconds.

    Silent for a pass shorter than ``every``; call :meth:`update` as often as wanted (it reads the
    clock every ``stride`` items), :meth:`finish` at the end (one closing line if anything was printed).
    """

    def __init__(
        self,
        prog: str,
        what: str,
        total: int,
        *,
        unit: str = "messages",
        every: float = 3.0,
        stride: int = 4096,
        stream: TextIO | None = None,
    ) -> None:
        self.prog, self.what, self.total, self.unit, self.every, self.stride = prog, what, total, unit, every, stride
        self.stream = stream if stream is not None else sys.stderr
        self.started = self.last = time.monotonic()
        self.printed = False
        self._next = stride

    def update(self, done: int) -> None:
        """``done`` items so far."""
        if done < self._next:
            return
        self._next = done + self.stride
        now = time.monotonic()
        if now - self.last < self.every:
            return
        self.last = now
        elapsed = now - self.started
        frac = done / self.total if self.total else 0.0
        eta = f", ETA {elapsed * (1 - frac) / frac:.0f} s" if 0 < frac < 1 else ""
        print(
            f"{self.prog}: {self.what}: {100 * frac:.0f} % ({done} of {self.total} {self.unit}), {elapsed:.0f} s{eta}",
            file=self.stream,
            flush=True,
        )
        self.printed = True

    def finish(self, done: int) -> None:
        """The closing line (only after a progress line)."""
        if self.printed:
            elapsed = time.monotonic() - self.started
            print(f"{self.prog}: {self.what}: {done} {self.unit} in {elapsed:.1f} s", file=self.stream, flush=True)
