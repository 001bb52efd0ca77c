"""Mutation check: each mutant below is applied to a copy of src/, the test folder of the mutated file's
package runs against the copy, interpreted (``NUMBA_DISABLE_JIT=1``: no compilation): the test named
after the mutant first, then, if it let the mutant live, the whole folder up to its first failure; the
check prints which test killed each mutant. A mutant that no test of the folder kills, or one without
a test named after it, fails the check (exit status 1). ``ros2_ws/test.sh`` runs it after the suite.

    .venv/bin/python tests/mutants.py             # every mutant
    .venv/bin/python tests/mutants.py torque sign # the mutants whose name contains one of the words

Each mutant is an edit a careless change could make at one of the boundaries of the judge, the
controller or the bag reader; its test is named ``test_mutant_<name>__…`` (tests/formation_sim/
test_recorder.py, tests/formation_agent/test_controller.py, tests/formation_bag/test_bag_io.py).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / "tests"
#: a mutated file's test folders where they are not tests/<its distribution> (none today)
FOLDERS: dict[str, tuple[str, ...]] = {}


@dataclass(frozen=True)
class Mutant:
    """Replace ``before`` (exactly one occurrence) by ``after`` in ``path`` (relative to src/)."""

    name: str
    path: str
    before: str
    after: str


JUDGE = "formation_sim/formation_sim/core/judge.py"
CONTROLLER = "formation_agent/formation_agent/controller.py"
READER = "formation_bag/formation_bag/reader.py"
MUTANTS = (
    # the funnel rule: a margin exactly 0 (an error on a bound) is a violation
    Mutant("violation_at_margin_below_zero", JUDGE, "return margin <= 0.0", "return margin < 0.0"),
    # a run is complete within half a control period of its requested duration, not 1.5
    Mutant(
        "duration_short_by_one_and_a_half_periods",
        "formation_sim/formation_sim/core/recorder.py",
        "tol = 0.5 / self.control_rate",
        "tol = 1.5 / self.control_rate",
    ),
    # velocity margins known between samples: the same rule, not a strict comparison
    Mutant(
        "velocity_margin_update_below_zero",
        JUDGE,
        "if self.first_violation is None and outside(mv.min()):",
        "if self.first_violation is None and mv.min() < 0:",
    ),
    # the torque's norm limited by max_force instead of max_torque
    Mutant(
        "torque_limited_by_max_force",
        CONTROLLER,
        "((U, max_force), (U + 3, max_torque))",
        "((U, max_force), (U + 3, max_force))",
    ),
    # u_i = −γ ρ_v⁻¹ r_v T_v with its sign flipped
    Mutant(
        "wrench_sign_flipped", CONTROLLER, "out[U + c] = -gains[GAMMA] / rho_v", "out[U + c] = gains[GAMMA] / rho_v"
    ),
    # rosbags' end_time is one past the last message: the bag's last log time taken as it is
    Mutant(
        "bag_end_time_off_by_one",
        READER,
        "return max((r.end_time - 1 for r in self.readers if r.message_count), default=0)",
        "return max((r.end_time for r in self.readers if r.message_count), default=0)",
    ),
    # segment files ordered by name: NAME_10 before NAME_2
    Mutant("segments_sorted_by_name", READER, "key=_segment_key)", "key=lambda p: p.name)"),
)


def copy_sources(into: Path) -> list[Path]:
    """src/ copied into ``into`` (sources only); returns the package folders to put on PYTHONPATH."""
    shutil.copytree(REPO / "src", into, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", ".*"))
    return sorted(d for d in into.iterdir() if (d / d.name / "__init__.py").is_file())


def named_test(mutant: Mutant) -> Path | None:
    """The test file holding ``test_mutant_<name>__…``, or None."""
    for path in sorted(TESTS.rglob("test_*.py")):
        if f"def test_mutant_{mutant.name}__" in path.read_text(encoding="utf-8"):
            return path
    return None


def folders(mutant: Mutant) -> list[Path]:
    """The test folders a mutant runs against."""
    distribution = mutant.path.split("/", 1)[0]
    return [TESTS / d for d in FOLDERS.get(distribution, (distribution,))]


def _env(packages: list[Path]) -> dict[str, str]:
    return {**os.environ, "NUMBA_DISABLE_JIT": "1", "PYTHONPATH": os.pathsep.join(map(str, packages))}


def run_tests(packages: list[Path], paths: list[Path], report: Path, *extra: str) -> dict[str, bool]:
    """pytest on ``paths`` (in that order) against the sources in ``packages``: {test id: passed}."""
    cmd = [sys.executable, "-m", "pytest", *map(str, paths), "-q", "-p", "no:cacheprovider", *extra]
    try:
        subprocess.run(
            [*cmd, f"--junitxml={report}"], cwd=REPO, env=_env(packages), stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL, timeout=900, check=False, start_new_session=True,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        return {}
    if not report.exists():
        return {}
    results = {}
    for case in ET.parse(report).iter("testcase"):
        failed = any(child.tag in ("failure", "error") for child in case)
        results[f"{case.get('classname', '')}::{case.get('name', '')}"] = not failed
    return results


def imported_from(packages: list[Path], modules: list[str]) -> list[str]:
    """Where ``modules`` are imported from with ``packages`` on PYTHONPATH (must be the copy)."""
    code = "import importlib, sys\nfor m in sys.argv[1:]: print(importlib.import_module(m).__file__)"
    out = subprocess.run([sys.executable, "-c", code, *modules], env=_env(packages), capture_output=True, text=True)
    return out.stdout.split() if out.returncode == 0 else []


def _module(path: str) -> str:
    return ".".join(Path(path).with_suffix("").parts[1:])


def main(argv: list[str]) -> int:
    chosen = [m for m in MUTANTS if not argv or any(word in m.name for word in argv)]
    named = {m.name: named_test(m) for m in chosen}
    if missing := [name for name, path in named.items() if path is None]:
        print(f"mutants: no test named after {', '.join(missing)} (test_mutant_<name>__…)", file=sys.stderr)
        return 1
    rows = []
    with tempfile.TemporaryDirectory(prefix="formation-mutants-") as tmp:
        original = Path(tmp) / "original"
        packages = copy_sources(original)
        modules = sorted({_module(m.path) for m in chosen})
        where = imported_from(packages, modules)
        if len(where) != len(modules) or not all(path.startswith(str(original)) for path in where):
            print("mutants: the copy of src/ is not what the tests import", file=sys.stderr)
            return 2
        files = sorted({path for path in named.values() if path is not None})
        baseline = run_tests(packages, files, Path(tmp) / "baseline.xml", "-k", "test_mutant_")
        if not baseline or not all(baseline.values()):
            print(f"mutants: the tests fail without a mutant: {sorted(t for t, ok in baseline.items() if not ok)}")
            return 2
        print(f"baseline: {len(baseline)} test_mutant_* tests pass on the unmutated sources", flush=True)
        for i, mutant in enumerate(chosen):
            copy = Path(tmp) / f"mutant{i}"
            packages = copy_sources(copy)
            target = copy / mutant.path
            text = target.read_text()
            if text.count(mutant.before) != 1:
                print(f"mutants: {mutant.name}: {mutant.before!r} is not once in {mutant.path}", file=sys.stderr)
                return 2
            target.write_text(text.replace(mutant.before, mutant.after))
            own = named[mutant.name]
            assert own is not None
            # its own test first; the whole folder only if that test let it live (the first failure kills it)
            results = run_tests(packages, [own], Path(tmp) / f"own{i}.xml", "-k", f"test_mutant_{mutant.name}__")
            if all(results.values()):
                results = run_tests(packages, folders(mutant), Path(tmp) / f"mutant{i}.xml", "-x")
            killers = sorted({name.split("[")[0] for name, ok in results.items() if not ok})
            rows.append((mutant.name, mutant.path.split("/", 1)[1], killers))
            print(f"{mutant.name}: {'killed by ' + ', '.join(killers) if killers else 'NOT KILLED'}", flush=True)
            shutil.rmtree(copy)
    survivors = [r[0] for r in rows if not r[2]]
    print(f"{len(rows) - len(survivors)} of {len(rows)} mutants killed")
    return 1 if survivors else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
