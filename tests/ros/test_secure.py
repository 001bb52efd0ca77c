"""Secure mode end to end: a lockstep run over mutual TLS equals the headless run, outsiders
(no certificate, another CA's certificate, plain UDP) neither see its topics nor reach the simulator,
and a member's certificate the others refuse is named in the verdict."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from ros_helpers import PAPER, assert_equals_headless, executable, secure_run_beside_outsiders

from formation_core.spec import load_formation
from formation_deploy.keys import init_keys, process_names
from formation_sim.launch.dds_env import netns_available

#: formation-launch with the certificate pre-flight (check_run_keys) switched off: the only way a
#: certificate the others refuse still reaches a running process (the launcher refuses it otherwise)
LAUNCH_UNCHECKED = (
    "import sys\n"
    "import formation_deploy.secure_transport as st\n"
    "st.check_run_keys = lambda *args, **kwargs: None\n"
    "from formation_sim.launch.launcher import main\n"
    "sys.exit(main(sys.argv[1:]))\n"
)


def test_secure_lockstep_equals_headless(ros_env: dict[str, str], tmp_path: Path) -> None:
    """0.08 s of the paper preset through TLS (keys made for the run) equals run_headless, bit for bit."""
    out = tmp_path / "out"
    cmd = [executable("formation-launch"), str(PAPER), "--secure", "--out", str(out), "--no-plots", "--quiet"]
    cmd += ["--no-record", "--duration", "0.08", "--record-rate", "10000"]
    r = subprocess.run(cmd, env=ros_env, capture_output=True, text=True, timeout=240, start_new_session=True)
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["launch"]["secure"]["transport"] == "TCPv4+TLS (mutual)"
    assert summary["launch"]["discovery_range"] == "SYSTEM_DEFAULT"
    assert "tls_handshake_failures" not in (summary.get("security") or {})
    assert_equals_headless(out / "trajectory.npz", 0.08)


def test_a_certificate_the_others_refuse_is_named_in_the_verdict(ros_env: dict[str, str], tmp_path: Path) -> None:
    """Agent 3 with another CA's certificate, past a bypassed pre-flight: the run ends INCOMPLETE (exit
    3, agents not matched), and its reason, summary.json and the printed verdict name the failed TLS
    handshakes that agents 4 and 5 (which connect to agent 3's port) logged."""
    keys, other = tmp_path / "keys", tmp_path / "other_ca"
    names = process_names(load_formation(PAPER).agent_ids)
    init_keys(keys, names)
    init_keys(other, names)
    for suffix in ("pem", "key"):
        shutil.copy2(other / f"agent_3.{suffix}", keys / f"agent_3.{suffix}")
    out = tmp_path / "out"
    cmd = [sys.executable, "-c", LAUNCH_UNCHECKED, str(PAPER), "--secure", "--keys", str(keys), "--out", str(out)]
    cmd += ["--no-plots", "--quiet", "--no-record", "--duration", "0.01"]
    r = subprocess.run(cmd, env=ros_env, capture_output=True, text=True, timeout=240, start_new_session=True)
    assert r.returncode == 3, r.stdout + r.stderr
    summary = json.loads((out / "summary.json").read_text())
    failures = summary["security"]["tls_handshake_failures"]
    assert failures and set(failures) <= {"agent_4", "agent_5"}, failures
    assert all(f["count"] >= 1 and f["last"].startswith("Handshake failed: ") for f in failures.values()), failures
    reason = summary["incomplete_reason"]
    assert "not matched within" in reason and "; TLS handshake failed (agent_" in reason, reason
    assert "a certificate the others refuse" in reason and "formation-keys check" in reason, reason
    assert "TLS handshake failed (agent_" in r.stdout, r.stdout


def test_outsiders_neither_see_nor_command_a_secure_run(ros_domain_id: int, tmp_path: Path) -> None:
    """In a private network namespace: plain, certificate-less and other-CA outsiders see no topic of the
    run and their 50 N wrench never reaches the simulator; a member of the run's CA (the control) is
    connected and reported as an intruder by node name."""
    reason = netns_available()
    if reason is not None:
        pytest.skip(reason)
    run = secure_run_beside_outsiders(tmp_path, ros_domain_id)
    assert not run.failures(), (run.failures(), run.describe())


def test_agent_refuses_to_run_when_its_secure_profile_does_not_apply(ros_env: dict[str, str], tmp_path: Path) -> None:
    """A profile Fast DDS cannot parse (it falls back to UDP): the agent exits 2 and names the profile."""
    broken = tmp_path / "agent_1.xml"
    broken.write_text(
        "<dds><profiles><participant profile_name='x' is_default_profile='true'><rtps><builtin>"
        "<initialPeersList></initialPeersList></builtin></rtps></participant></profiles></dds>"
    )
    env = dict(ros_env, FORMATION_SECURE="1", FASTRTPS_DEFAULT_PROFILES_FILE=str(broken))
    cmd = [executable("formation-agent"), "--ros-args", "-p", f"formation_file:={PAPER}", "-p", "agent_id:='1'"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60, start_new_session=True)
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"the profile {broken} did not apply" in r.stderr
