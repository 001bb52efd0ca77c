"""Cost of reading formation files and refusing bad input. CPU time, median of 7.

    .venv/bin/python benchmarks/input_bench.py

- load_formation of each preset (the loader: UTF-8, alias budget, duplicate keys, positions);
- refusing a 10 x 10 alias bomb (10^10 nodes once expanded), with its peak Python allocation;
- one agent input check (relative pose) and one simulator wrench check, per message.
"""

from __future__ import annotations

import itertools
import statistics
import time
import tracemalloc
from pathlib import Path

from formation_core.errors import FormationSpecError
from formation_core.loader import parse_document
from formation_core.spec import load_formation
from formation_msgs_py.measurement_checks import InputCheck
from formation_msgs_py.wrench_checks import WrenchCheck

REPO = Path(__file__).resolve().parents[1]


def cpu(fn, n: int = 1) -> float:
    """Median CPU seconds per call of ``fn`` over 7 runs of ``n`` calls."""
    runs = []
    for _ in range(7):
        t0 = time.process_time()
        for _ in range(n):
            fn()
        runs.append((time.process_time() - t0) / n)
    return statistics.median(runs)


def bomb() -> bytes:
    names = "abcdefghij"
    lines = [f"a: &a [{', '.join(['1'] * 10)}]"]
    lines += [f"{b}: &{b} [{', '.join([f'*{a}'] * 10)}]" for a, b in itertools.pairwise(names)]
    return ("\n".join(lines) + "\nagents: *j\n").encode()


def main() -> None:
    for path in sorted((REPO / "config").glob("*.yaml")):
        print(f"load_formation {path.name}: {cpu(lambda p=path: load_formation(p)) * 1e3:.1f} ms")
    raw = bomb()

    def refuse() -> None:
        try:
            parse_document(raw, "bomb.yaml")
        except FormationSpecError:
            return
        raise AssertionError("the bomb was accepted")

    tracemalloc.start()
    refuse()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    print(f"alias bomb ({len(raw)} bytes) refused: {cpu(refuse) * 1e3:.2f} ms, peak allocation {peak / 1e6:.2f} MB")
    check = InputCheck(4.0, 100_000_000)
    pose = (1.0, 2.0, 0.5, 0.0, 0.0, 0.0, 1.0)
    print(f"agent pose check: {cpu(lambda: check.pose('3', 10**9, pose, 10**9), 100_000) * 1e6:.2f} µs")
    wc = WrenchCheck((100.0,), (100.0,), 1000.0, lockstep=True)
    u = (1.0, 2.0, 3.0, 0.1, 0.2, 0.3)
    print(f"simulator wrench check: {cpu(lambda: wc.check(0, 10**9, u, 10**9), 100_000) * 1e6:.2f} µs")


if __name__ == "__main__":
    main()
