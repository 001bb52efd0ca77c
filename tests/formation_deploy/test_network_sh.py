"""ros2_ws/lib/network.sh (sim.sh, agent.sh): discovery on this host unless asked, --secure environment."""

from __future__ import annotations

import datetime as dt
import os
import subprocess
from pathlib import Path

from formation_deploy.keys import init_keys, process_names

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "config" / "paper_5agents.yaml"
SHOW = (
    "ROS_AUTOMATIC_DISCOVERY_RANGE ROS_STATIC_PEERS FASTRTPS_DEFAULT_PROFILES_FILE FASTDDS_BUILTIN_TRANSPORTS"
    " OPENSSL_CONF"
)
PROFILES = REPO / "src" / "formation_msgs_py" / "formation_msgs_py"


def _options(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Source network.sh, parse ``args`` for agent_1, print the resulting variables and REST."""
    script = (
        f'ROOT="{REPO}"; . "$ROOT/ros2_ws/lib/network.sh"; '
        f'formation_network_options agent_1 "{PAPER}" "$@" || exit $?; '
        f'for v in {SHOW}; do echo "$v=${{!v-}}"; done; echo "REST=${{REST[*]-}}"'
    )
    base = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "FASTRTPS", "FASTDDS", "OPENSSL"))}
    return subprocess.run(
        ["bash", "-c", script, "bash", *args], env={**base, **(env or {})}, capture_output=True, text=True, timeout=60
    )


def _vars(r: subprocess.CompletedProcess) -> dict[str, str]:
    return dict(line.split("=", 1) for line in r.stdout.splitlines())


def test_default_is_this_host_and_lan_is_explicit() -> None:
    """No option: this host, as UDP on 127.0.0.1 (LOCALHOST carried out by the loopback profile under
    SYSTEM_DEFAULT); --network lan: SUBNET, UDP only; an explicit environment value is kept; a profile
    of the environment's own is left alone with LOCALHOST; other args pass on."""
    assert _vars(_options("--ros-args", "-p", "x:=1")) == {
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT",
        "ROS_STATIC_PEERS": "",
        "FASTRTPS_DEFAULT_PROFILES_FILE": str(PROFILES / "fastdds_loopback.xml"),
        "FASTDDS_BUILTIN_TRANSPORTS": "",
        "OPENSSL_CONF": "",
        "REST": "--ros-args -p x:=1",
    }
    lan = _vars(_options("--network", "lan"))
    assert lan["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET" and lan["FASTDDS_BUILTIN_TRANSPORTS"] == "UDPv4"
    assert lan["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(PROFILES / "fastdds_profile.xml")
    kept = _options(env={"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"})
    assert _vars(kept)["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    own = _vars(_options(env={"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"}))
    assert own["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert own["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/etc/mine.xml"


def test_bad_network_and_hosts_without_secure_exit_2() -> None:
    """--network wan and --hosts without --secure are refused with exit 2 and the reason."""
    r = _options("--network", "wan")
    assert r.returncode == 2 and "expected host or lan, got 'wan'" in r.stderr
    r = _options("--port-base", "9000")
    assert r.returncode == 2 and "need --secure" in r.stderr


def test_secure_selects_the_profile_and_drops_static_peers(tmp_path: Path) -> None:
    """--secure KEYS: agent_1's profile and OpenSSL configuration, SYSTEM_DEFAULT range, no static peers."""
    keys = tmp_path / "keys"
    init_keys(keys, process_names(["1", "2", "3", "4", "5"]))
    r = _options("--secure", str(keys), "--port-base", "9100", env={"ROS_STATIC_PEERS": "10.1.1.1"})
    assert r.returncode == 0, r.stderr
    v = _vars(r)
    assert v["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT" and v["ROS_STATIC_PEERS"] == ""
    profile = Path(v["FASTRTPS_DEFAULT_PROFILES_FILE"])
    assert profile == (keys / "profiles" / "agent_1.xml").resolve()
    assert "<port>9101</port>" in profile.read_text() and Path(v["OPENSSL_CONF"]).is_file()


def test_secure_with_an_expired_or_loose_key_exits_2_naming_the_file(tmp_path: Path) -> None:
    """--secure KEYS whose agent_1 certificate expired yesterday, or whose key is mode 0644: exit 2, one line
    naming the file and the problem, no profile written; a certificate valid for 1 day refuses a 2-day --duration."""
    issued = dt.datetime.now(dt.UTC) - dt.timedelta(days=2)
    old = tmp_path / "old"
    init_keys(old, process_names(["1", "2", "3", "4", "5"]), days=1, now=issued)
    r = _options("--secure", str(old))
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert f"{old / 'agent_1.pem'}: expired on " in r.stderr or f"{old / 'ca.pem'}: expired on " in r.stderr
    assert not (old / "profiles").exists()
    loose = tmp_path / "loose"
    init_keys(loose, process_names(["1", "2", "3", "4", "5"]))
    (loose / "agent_1.key").chmod(0o644)
    r = _options("--secure", str(loose))
    assert r.returncode == 2, r.stderr
    assert (
        r.stderr
        == f"formation-keys: {loose / 'agent_1.key'}: private key readable by others (mode 0644, expected 0600)\n"
    )
    short = tmp_path / "short"
    init_keys(short, process_names(["1", "2", "3", "4", "5"]), days=1)
    assert _options("--secure", str(short), "--duration", "60").returncode == 0
    r = _options("--secure", str(short), "--duration", "172800")
    assert r.returncode == 2 and "before the end of the run" in r.stderr, r.stderr
    assert _vars(_options("--secure", str(short), "--duration=60"))["REST"] == "--duration=60"
