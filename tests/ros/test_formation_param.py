"""formation-param list|get|set on a running agent: a live gain is set and logged, a read-only one refused."""

from __future__ import annotations

import subprocess

from ros_helpers import PAPER, executable, read_log, wait_for_line

NODE = "/agent_1/formation_agent"


def _param(env: dict[str, str], *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    cmd = [executable("formation-param"), "--timeout", str(timeout), *args]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout + 60, start_new_session=True)


def test_set_get_list_and_refusals(procs, ros_env: dict[str, str]) -> None:
    """set gamma 2 (an integer, made a float) succeeds and the agent logs it; get reads it back; list shows
    read-only and live; agent_id is refused with a clear message and exit 1; an absent node exits 3."""
    agent = procs.agent(PAPER, "1")
    res = _param(ros_env, "set", NODE, "gamma", "2")
    assert res.returncode == 0, res.stdout + res.stderr + read_log(agent)
    assert res.stdout.strip() == f"{NODE}: gamma = 2.0"
    assert wait_for_line(agent, "parameter gamma set to 2.0", timeout=30), read_log(agent)
    res = _param(ros_env, "get", NODE, "gamma")
    assert (res.returncode, res.stdout.strip()) == (0, "2.0"), res.stderr
    res = _param(ros_env, "list", NODE)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert "gamma = 2.0  (live)" in lines and "agent_id = '1'  (read-only)" in lines, lines
    res = _param(ros_env, "set", NODE, "agent_id", "2")
    assert res.returncode == 1, res.stdout + res.stderr
    assert f"{NODE} refused agent_id = '2'" in res.stderr and "read-only" in res.stderr, res.stderr
    assert "parameter agent_id set" not in read_log(agent)
    res = _param(ros_env, "set", NODE, "gamma", "-1")
    assert res.returncode == 1 and "-1.0 must be > 0" in res.stderr, res.stderr
    res = _param(ros_env, "get", NODE, "no_such")
    assert res.returncode == 1 and "has no parameter 'no_such'" in res.stderr, res.stderr
    res = _param(ros_env, "get", "/agent_9/formation_agent", "gamma", timeout=2.0)
    assert res.returncode == 3 and "no node /agent_9/formation_agent answered" in res.stderr, res.stderr
