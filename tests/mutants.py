"""Mutation check of the judge and the controller: each mutant below is applied to a copy of src/, the
tests named after mutants (``test_mutant_*``) run against the copy, interpreted (``NUMBA_DISABLE_JIT=1``:
no compilation), and a table says which tests kill each mutant. A mutant no test kills fails the check.

    .venv/bin/python tests/mutants.py             # every mutant; exit status 1 if one survives
    .venv/bin/python tests/mutants.py torque sign # the mutants whose name contains one of the words

Each mutant is an edit a careless change could make at one of the judge's or the controller's
boundaries; its test is named ``test_mutant_<name>__…`` (tests/formation_sim/test_recorder.py,
tests/formation_agent/test_controller.py).
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
TEST_FILES = ("tests/formation_sim/test_recorder.py", "tests/formation_agent/test_controller.py")


@dataclass(frozen=True)
class Mutant:
    """Replace ``before`` (exactly one occurrence) by ``after`` in ``path`` (relative to src/)."""

    name: str
    path: str
    before: str
    after: str


JUDGE = "formation_msgs_py/formation_msgs_py/judge.py"
CONTROLLER = "formation_agent/formation_agent/controller.py"
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
)


def copy_sources(into: Path) -> list[Path]:
    """src/ copied into ``into`` (sources only); returns the package folders to put on PYTHONPATH."""
    shutil.copytree(REPO / "src", into, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", ".*"))
    return sorted(d for d in into.iterdir() if (d / d.name / "__init__.py").is_file())


def run_tests(packages: list[Path], report: Path) -> dict[str, bool]:
    """The ``test_mutant_*`` tests against the sources in ``packages``: {test id: passed}."""
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1", "PYTHONPATH": os.pathsep.join(map(str, packages))}
    subprocess.run(
        [sys.executable, "-m", "pytest", *TEST_FILES, "-k", "test_mutant_", "-q", "-p", "no:cacheprovider",
         f"--junitxml={report}"],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600, check=False,
    )  # fmt: skip
    results = {}
    for case in ET.parse(report).iter("testcase"):
        failed = any(child.tag in ("failure", "error") for child in case)
        results[case.get("name", "")] = not failed
    return results


def imported_from(packages: list[Path]) -> list[str]:
    """Where the mutated modules are imported from with ``packages`` on PYTHONPATH (must be the copy)."""
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1", "PYTHONPATH": os.pathsep.join(map(str, packages))}
    code = "import formation_msgs_py.judge as a, formation_agent.controller as b, formation_sim.core.recorder as c\n"
    code += "print(a.__file__); print(b.__file__); print(c.__file__)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return out.stdout.split()


def main(argv: list[str]) -> int:
    chosen = [m for m in MUTANTS if not argv or any(word in m.name for word in argv)]
    rows = []
    with tempfile.TemporaryDirectory(prefix="formation-mutants-") as tmp:
        original = Path(tmp) / "original"
        packages = copy_sources(original)
        if not all(path.startswith(str(original)) for path in imported_from(packages)):
            print("mutants: the copy of src/ is not what the tests import", file=sys.stderr)
            return 2
        baseline = run_tests(packages, Path(tmp) / "baseline.xml")
        if not baseline or not all(baseline.values()):
            print(f"mutants: the tests fail without a mutant: {sorted(t for t, ok in baseline.items() if not ok)}")
            return 2
        print(f"baseline: {len(baseline)} test_mutant_* tests pass on the unmutated sources")
        for i, mutant in enumerate(chosen):
            copy = Path(tmp) / f"mutant{i}"
            packages = copy_sources(copy)
            target = copy / mutant.path
            text = target.read_text()
            if text.count(mutant.before) != 1:
                print(f"mutants: {mutant.name}: {mutant.before!r} is not once in {mutant.path}", file=sys.stderr)
                return 2
            target.write_text(text.replace(mutant.before, mutant.after))
            results = run_tests(packages, Path(tmp) / f"mutant{i}.xml")
            killers = sorted({name.split("[")[0] for name, ok in results.items() if not ok})
            named = any(f"test_mutant_{mutant.name}__" in k for k in killers)
            rows.append((mutant.name, mutant.path.split("/", 1)[1], killers, named))
            shutil.rmtree(copy)
    width, file_width = max(len(r[0]) for r in rows), max(len(r[1]) for r in rows)
    print(f"{'mutant':<{width}}  {'in':<{file_width}}  killed by (* the test named after it)")
    for name, path, killers, _ in rows:
        by = ", ".join(("* " if f"test_mutant_{name}__" in k else "") + k for k in killers) or "NOT KILLED"
        print(f"{name:<{width}}  {path:<{file_width}}  {by}")
    survivors = [r[0] for r in rows if not r[2] or not r[3]]
    print(f"{len(rows) - len(survivors)} of {len(rows)} mutants killed by their named tests")
    return 1 if survivors else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
