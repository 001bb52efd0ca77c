"""formation-launch without ROS processes: its own part of summary.json (the agents' fault counts merged
in), and every run it refuses before anything starts (exit 2, one line, OUT untouched)."""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import json
import os
import re
import subprocess
from pathlib import Path

import pytest
from bin_helpers import executable

from formation_core.faults import FaultLog, write_json
from formation_core.verdict import ExitCode, Incomplete
from formation_deploy.keys import init_keys, process_names
from formation_sim.launch.launcher import RESERVE_BYTES, SpaceReserve, agent_faults_file, merge_agent_faults


def test_agent_fault_files_are_merged_and_missing_ones_named(tmp_path: Path) -> None:
    sim = FaultLog()
    sim.add(0.1, "1", "resent_step")
    agent1 = FaultLog()
    agent1.add(0.3, "1", "refused_bad_quaternion", "norm 2")
    agent1.add(0.4, "1", "refused_bad_quaternion", "norm 0")
    agent1.add(0.5, "1", "reset", "/clock jumped by -0.5 s")
    write_json(agent_faults_file(tmp_path, "1"), agent1.as_dict())
    write_json(agent_faults_file(tmp_path, "2"), {})  # an agent without faults
    summary = {"faults": sim.as_dict()}
    merge_agent_faults(summary, tmp_path, ["1", "2", "3"])
    assert set(summary["faults"]["1"]) == {"resent_step", "refused_bad_quaternion", "reset"}
    refused = summary["faults"]["1"]["refused_bad_quaternion"]
    assert (refused["count"], refused["first_t"], refused["last_t"]) == (2, 0.3, 0.4)
    assert summary["agent_faults_unknown"] == ["3"]  # killed before it could write its counts


def _launch(paper_path: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    cmd = [executable("formation-launch"), str(paper_path), "--quiet", "--no-plots", *args]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)


def _refused(r: subprocess.CompletedProcess, expected: str) -> None:
    """Exit 2, nothing on stdout, one line on stderr that matches ``expected``, no traceback."""
    assert (r.returncode, r.stdout) == (2, ""), (r.returncode, r.stdout, r.stderr)
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
    assert re.match(rf"formation-launch: INVALID: {expected}", r.stderr), r.stderr


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--duration", "1e-12"], r"--duration 1e-12 s is shorter than one control period"),
        (["--duration", "1e12"], r"--duration 1e\+12 s is longer than any run"),
        (["--control-rate", "5e8", "--allow-low-rate"], r"simulation.duration in .* at a physics rate of 5e\+08 Hz "
         r"\(--control-rate\) is 2.5e\+09 steps"),
        (["--control-rate", "2e9", "--allow-low-rate"], r"control rate 2e\+09 Hz \(--control-rate\) has a period under "
         r"a nanosecond"),
    ],
)  # fmt: skip
def test_impossible_durations_and_rates_exit_2_and_leave_out_untouched(
    paper_path: Path, tmp_path: Path, args: list[str], expected: str
) -> None:
    """Each impossible duration or rate: exit 2 with one line naming the option; OUT (new or empty) untouched."""
    new, empty = tmp_path / "new", tmp_path / "empty"
    empty.mkdir()
    _refused(_launch(paper_path, *args, "--out", str(new)), expected)
    _refused(_launch(paper_path, *args, "--out", str(empty)), expected)
    assert not new.exists() and list(empty.iterdir()) == []


def test_out_that_is_a_file_or_unwritable_exits_2_in_one_line(paper_path: Path, tmp_path: Path) -> None:
    """--out FILE says it is a file; a place nobody may write (/proc/sys) says so: no traceback, nothing made."""
    afile = tmp_path / "afile"
    afile.write_text("mine")
    _refused(_launch(paper_path, "--out", str(afile)), rf"output directory {afile} is a file, not a directory$")
    _refused(_launch(paper_path, "--out", "/proc/sys/formation-out"), r".*/proc/sys is not writable")
    assert afile.read_text() == "mine"


def test_read_only_out_exits_2_in_one_line(paper_path: Path, tmp_path: Path) -> None:
    """An existing empty OUT on a read-only file system (a read-only bind mount): exit 2, one line, no traceback."""
    out = tmp_path / "ro"
    out.mkdir()
    if subprocess.run(["mount", "--bind", "-o", "ro", str(out), str(out)], capture_output=True).returncode != 0:
        pytest.skip("a read-only bind mount needs CAP_SYS_ADMIN")
    try:
        _refused(
            _launch(paper_path, "--out", str(out)), rf"output directory {out}: {out} is on a read-only file system$"
        )
    finally:
        subprocess.run(["umount", str(out)], check=True)
    assert list(out.iterdir()) == []


@pytest.mark.parametrize("case", ["expired", "key 0644"])
def test_secure_run_with_a_bad_certificate_exits_2_before_anything_starts(
    paper_path: Path, tmp_path: Path, case: str
) -> None:
    """--secure --keys with expired certificates (the directory issued 2 days ago for 1 day: the CA first, 8 more)
    or agent 3's key of mode 0644: exit 2 naming the file, OUT left empty (no logs/), no process started."""
    keys = tmp_path / "keys"
    if case == "expired":
        init_keys(
            keys, process_names(["1", "2", "3", "4", "5"]), days=1, now=dt.datetime.now(dt.UTC) - dt.timedelta(days=2)
        )
        expected = rf"--secure: {keys}/ca\.pem: expired on .* \(and 8 more: formation-keys check {keys}\)$"
    else:
        init_keys(keys, process_names(["1", "2", "3", "4", "5"]))
        (keys / "agent_3.key").chmod(0o644)
        expected = rf"--secure: {keys}/agent_3\.key: private key readable by others \(mode 0644, expected 0600\)$"
    out = tmp_path / "out"
    out.mkdir()
    _refused(_launch(paper_path, "--secure", "--keys", str(keys), "--out", str(out), "--duration", "0.1"), expected)
    assert list(out.iterdir()) == []


def test_space_reserve_is_never_a_file_in_out(tmp_path: Path) -> None:
    """The reserve for the final summary holds its bytes without a name in OUT (a SIGKILLed launcher leaves none)."""
    reserve = SpaceReserve(tmp_path, size=RESERVE_BYTES)
    assert list(tmp_path.iterdir()) == []
    assert reserve.allocated >= RESERVE_BYTES  # written out, not sparse: the bytes are really held
    reserve.release()
    assert list(tmp_path.iterdir()) == []


def test_progress_line_shows_the_eta_when_the_simulator_gives_one() -> None:
    """The launcher's progress: simulated time, real-time factor, worst margin and, once the simulator
    has stepped, the wall seconds still to go."""
    from formation_sim.launch.launcher import progress_text

    line = "progress t=1.2500/5 rtf=0.031 worst_margin=+0.0514 eta=121"
    assert progress_text(line) == "  sim t=1.2500/5 s  real-time factor 0.031  worst margin +0.0514  ETA 121 s"
    assert progress_text("progress t=0.0000/5 rtf=0.000 worst_margin=+inf").endswith("worst margin +inf")


def test_an_intruder_only_an_agent_saw_makes_the_run_untrusted(tmp_path: Path) -> None:
    """An agent's intruder (the simulator's graph never saw it) enters summary.json's security and
    turns a PASS into INCOMPLETE, untrusted input, exit 4; a run INCOMPLETE for its own reason keeps
    it, with the intruder added; no agent report changes nothing."""
    from formation_deploy.publisher_watch import security_file
    from formation_sim.launch.launcher import merge_agent_security

    pose = "/agent_3/relative_pose/agent_1"
    intruder = {
        "topic": pose,
        "agent": "3",
        "node": "/member",
        "gid": "01.0f",
        "first_seen": 5.4,
        "last_seen": 8.0,
        "reason": "not a process of the formation",
    }
    quiet = {"policy": "report", "intruders": [], "refused_messages": {}, "applied_while_intruder": {}, "withdrawn": []}
    seen = {**quiet, "intruders": [intruder], "applied_while_intruder": {pose: 12}}
    write_json(security_file(agent_faults_file(tmp_path, "3")), seen)
    write_json(security_file(agent_faults_file(tmp_path, "1")), quiet)

    passed = {"verdict": "PASS", "exit_status": 0, "incomplete_reason": None, "funnels_held": True, "security": quiet}
    merge_agent_security(passed, tmp_path, ["1", "2", "3"])
    assert (passed["verdict"], passed["exit_status"], passed["funnels_held"]) == ("INCOMPLETE", 4, None)
    assert passed["incomplete_reason"].startswith("untrusted input: 1 intruder(s) (policy report): node /member")
    assert f"on {pose} (12 applied, 0 refused)" in passed["incomplete_reason"]

    lagging = {"verdict": "INCOMPLETE", "exit_status": 4, "incomplete_reason": "lag budget exceeded", "security": quiet}
    merge_agent_security(lagging, tmp_path, ["3"])
    assert lagging["incomplete_reason"].startswith("lag budget exceeded; untrusted input: 1 intruder(s)")

    alone = {"verdict": "PASS", "exit_status": 0, "incomplete_reason": None, "security": quiet}
    merge_agent_security(alone, tmp_path, ["1", "2"])
    assert (alone["verdict"], alone["exit_status"]) == ("PASS", 0)


def test_hang_timeout_covers_the_longest_silence_of_a_working_simulator(paper_path: Path, tmp_path: Path) -> None:
    """Default --hang-timeout: the longer of the discovery timeout (30 s + 1 per agent, or the option) and,
    in lockstep, the step timeout, plus HANG_MARGIN; the option wins."""
    from formation_core.options import RunOptions
    from formation_core.spec import load_formation
    from formation_sim.launch.launcher import HANG_MARGIN, Launcher

    spec = load_formation(paper_path)

    def timeout(mode: str, **options: float) -> float:
        args = RunOptions(command="launch", mode=mode, **options)
        return Launcher(spec, args, tmp_path, {}).hang_timeout()

    n = len(spec.agents)
    assert timeout("lockstep") == max(30.0 + n, spec.simulation.step_timeout) + HANG_MARGIN
    assert timeout("lockstep", discovery_timeout=400.0) == 400.0 + HANG_MARGIN
    assert timeout("realtime", discovery_timeout=2.0) == 2.0 + HANG_MARGIN  # no step timeout in realtime
    assert timeout("lockstep", hang_timeout=7.0) == 7.0


def test_the_stop_grace_grows_with_the_processes_stopped_at_once() -> None:
    """2.5 s up to six processes (the paper run), 0.1 s more per process beyond: 6.1 s for 42."""
    from formation_sim.launch.launcher import stop_grace

    assert stop_grace(6) == stop_grace(1) == 2.5
    assert abs(stop_grace(42) - 6.1) < 1e-9  # float sum: 2.5 + 0.1 · 36


def _completed(tmp_path: Path, violation_t: float | None, stop: Incomplete | None = None) -> tuple[int, dict, str]:
    """(exit status, summary.json, printed verdict) of a realtime launch of the paper's formation whose
    simulator ran its 10 s and whose agent 3, after answering the step of t = 3.12 s, was killed."""
    from formation_core.options import RunOptions
    from formation_core.spec import load_formation
    from formation_sim.launch import launcher as launch

    fv = None if violation_t is None else {"t": violation_t, "kind": "velocity", "agent": "3", "channel": "vx"}
    simulator = {
        "formation": "paper_5agents",
        "mode": "ros2-realtime",
        "control_rate": 100.0,
        "verdict": "PASS" if fv is None else "FAIL",
        "incomplete_reason": None,
        "exit_status": 0 if fv is None else 1,
        "requested_duration": 10.0,
        "duration": 10.0,
        "funnels_held": fv is None,
        "first_violation": fv,
        "worst_margin": 0.3 if fv is None else -0.2,
        "faults": {},
        "last_answer_t": {"1": 10.0, "2": 10.0, "3": 3.12, "4": 10.0, "5": 10.0},
    }
    (tmp_path / "logs").mkdir(parents=True)
    write_json(tmp_path / "summary.json", simulator)
    env = {"ROS_DOMAIN_ID": "7", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    spec = load_formation(Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml")
    run = launch.Launcher(spec, RunOptions(command="launch", mode="realtime"), tmp_path, env)
    run.timing = {"start": 0.0, "stop_from": 11.0, "stopped": 12.0}
    run.stop = stop
    run.agent_died.append(launch.Death("3", "agent_3 was killed by SIGKILL"))
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = launch._finish(run, None)
    return code, json.loads((tmp_path / "summary.json").read_text()), printed.getvalue()


DEATH = (
    "agent_3 was killed by SIGKILL after answering the step of t=3.1200 s; "
    "the realtime run went on with its wrench held, then zeroed"
)


def test_a_violation_after_an_agent_died_in_a_realtime_run_is_incomplete(tmp_path: Path) -> None:
    """The run went on after agent 3 died; a violation followed: INCOMPLETE, exit 3, the death (agent,
    signal, its last step) named first, the violation kept as information."""
    code, summary, printed = _completed(tmp_path, 3.89)
    assert (code, summary["verdict"], summary["exit_status"]) == (3, "INCOMPLETE", 3), printed
    assert summary["incomplete_reason"] == DEATH
    assert summary["first_violation"]["t"] == 3.89
    assert f"INCOMPLETE: {DEATH} (a violation seen at t=3.8900 s: velocity 3 (vx), worst margin -0.2)" in printed
    assert "stopped early" not in printed


def test_a_violation_before_an_agent_died_in_a_realtime_run_is_fail(tmp_path: Path) -> None:
    """A violation while every agent was still answering stays FAIL (exit 1), the death after it named;
    the run did not stop early and the verdict does not say it did."""
    code, summary, printed = _completed(tmp_path, 2.5)
    assert (code, summary["verdict"], summary["exit_status"]) == (1, "FAIL", 1), printed
    assert summary["incomplete_reason"] == DEATH
    assert f"FAIL: first violation at t=2.5000 s: velocity 3 (vx); then {DEATH}\n" in printed


def test_an_agent_death_without_a_violation_and_an_interrupt_after_it(tmp_path: Path) -> None:
    """No violation: INCOMPLETE, exit 3, the death named; interrupted later: both named, the death
    first, exit 130."""
    code, summary, printed = _completed(tmp_path / "quiet", None)
    assert (code, summary["verdict"], summary["incomplete_reason"]) == (3, "INCOMPLETE", DEATH), printed
    stop = Incomplete(ExitCode.INTERRUPTED, "interrupted (SIGINT)")
    code, summary, printed = _completed(tmp_path / "interrupted", 3.89, stop)
    assert (code, summary["verdict"]) == (130, "INCOMPLETE"), printed
    assert summary["incomplete_reason"] == f"{DEATH}; interrupted (SIGINT)"


def test_the_simulators_own_stop_is_kept_after_the_deaths_without_the_untrusted_input() -> None:
    """The simulator's reason (lag budget; interrupted keeps 130) comes without the untrusted input,
    which the verdict names again; a PASS, a reason-less FAIL or untrusted input alone give none."""
    from formation_sim.launch.launcher import simulator_stop

    lag, untrusted = "realtime lag budget exceeded: 31 s behind", "untrusted input: 1 intruder(s)"
    lagging = {"verdict": "INCOMPLETE", "exit_status": 4, "incomplete_reason": f"{lag}; {untrusted}"}
    assert simulator_stop(lagging, untrusted) == Incomplete(ExitCode.INCOMPLETE, lag)
    interrupted = {"verdict": "FAIL", "exit_status": 130, "incomplete_reason": "interrupted (SIGINT)"}
    assert simulator_stop(interrupted, None) == Incomplete(ExitCode.INTERRUPTED, "interrupted (SIGINT)")
    assert simulator_stop({"verdict": "FAIL", "exit_status": 1, "incomplete_reason": None}, None) is None
    assert (
        simulator_stop({"verdict": "INCOMPLETE", "exit_status": 4, "incomplete_reason": untrusted}, untrusted) is None
    )
