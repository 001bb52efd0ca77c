"""The suite's own leftover watch (tests/process_hygiene.py) survives processes that end while it looks."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from process_hygiene import live_descendants


def test_a_process_gone_between_two_reads_is_skipped(monkeypatch) -> None:
    """A child whose /proc/PID/cmdline vanishes after its stat was read is left out, not a KeyError
    (a KeyError there ends the watch thread, which then watches nothing)."""
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        real = Path.read_bytes

        def vanishing(self: Path) -> bytes:
            if self == Path(f"/proc/{child.pid}/cmdline"):
                raise FileNotFoundError(self)
            return real(self)

        monkeypatch.setattr(Path, "read_bytes", vanishing)
        assert child.pid not in live_descendants(os.getpid())
        monkeypatch.undo()
        assert child.pid in live_descendants(os.getpid())
    finally:
        child.kill()
        child.wait(timeout=10)
