"""formation-compose: the compose file of a formation file, and the checked-in docker/compose.yaml."""

from __future__ import annotations

import copy
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml
from bin_helpers import executable

from formation_deploy.compose import MARK, main

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "config" / "paper_5agents.yaml"
CHECKED_IN = REPO / "docker" / "compose.yaml"
IN_IMAGE = "/opt/formation/formations/paper_5agents.yaml"


def services(path: Path) -> dict[str, Any]:
    return yaml.safe_load(path.read_text())["services"]


def test_checked_in_compose_file_is_the_generator_output(capsys: pytest.CaptureFixture[str]) -> None:
    """docker/compose.yaml equals `formation-compose config/paper_5agents.yaml --out docker/compose.yaml`."""
    status = main([str(PAPER), "--out", str(CHECKED_IN), "--context", str(REPO), "--check"])
    assert status == 0, capsys.readouterr().out


def test_paper_services_are_the_simulator_and_its_five_agents() -> None:
    """Exactly sim + agent_1..agent_5, one image, the right commands, discovery settings as environment."""
    s = services(CHECKED_IN)
    assert sorted(s) == ["agent_1", "agent_2", "agent_3", "agent_4", "agent_5", "sim"]
    assert s["sim"]["command"][:2] == ["sim.sh", IN_IMAGE]
    assert s["sim"]["command"][2] == "--out"
    for i in range(1, 6):
        assert s[f"agent_{i}"]["command"] == ["agent.sh", IN_IMAGE, str(i)]
    assert len({svc["image"] for svc in s.values()}) == 1
    for svc in s.values():
        assert set(svc["environment"]) == {"ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS"}
        assert svc["build"] == {"context": "..", "dockerfile": "docker/Dockerfile"}
        assert f"../config/paper_5agents.yaml:{IN_IMAGE}:ro" in svc["volumes"]
    assert "../out:/opt/formation/out" in s["sim"]["volumes"]
    assert sorted(s["sim"]["depends_on"]) == [f"agent_{i}" for i in range(1, 6)]


def test_any_formation_file(tmp_path: Path, paper_doc: dict[str, Any]) -> None:
    """A three-agent formation with string ids gives three agent services, paths relative to the output."""
    doc = copy.deepcopy(paper_doc)
    doc["name"] = "trio"
    doc["agents"] = doc["agents"][:3]
    for a, new_id in zip(doc["agents"], ["a", "b", "c"]):
        a["id"] = new_id
    doc["edges"] = [{"tail": "a", "head": "b"}, {"tail": "a", "head": "c"}]
    (tmp_path / "cfg").mkdir()
    formation = tmp_path / "cfg" / "trio.yaml"
    formation.write_text(yaml.safe_dump(doc))
    out = tmp_path / "deploy" / "compose.yaml"
    assert main([str(formation), "--out", str(out), "--context", "none", "--host-network"]) == 0
    text = out.read_text()
    assert text.startswith(MARK)
    s = services(out)
    assert sorted(s) == ["agent_a", "agent_b", "agent_c", "sim"]
    assert s["agent_b"]["command"] == ["agent.sh", "/opt/formation/formations/trio.yaml", "b"]
    assert all(svc["network_mode"] == "host" and svc["ipc"] == "host" for svc in s.values())
    assert all("build" not in svc for svc in s.values())
    assert "../cfg/trio.yaml:/opt/formation/formations/trio.yaml:ro" in s["agent_a"]["volumes"]
    assert str(tmp_path) not in text  # no absolute host paths


def test_invalid_formation_file_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An invalid file exits 2 with a message naming the problem, and writes nothing."""
    bad = tmp_path / "bad.yaml"
    bad.write_text("agents: []\nedges: []\n")
    out = tmp_path / "compose.yaml"
    assert main([str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("formation-compose: error:")
    assert not out.exists()


def test_refuses_to_overwrite_a_file_it_did_not_write(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An existing compose file without the generator's mark is kept unless --force."""
    out = tmp_path / "compose.yaml"
    out.write_text("services: {}\n")
    assert main([str(PAPER), "--out", str(out)]) == 2
    assert str(out) in capsys.readouterr().err
    assert out.read_text() == "services: {}\n"
    assert main([str(PAPER), "--out", str(out), "--force"]) == 0
    assert out.read_text().startswith(MARK)


def test_paths_beside_the_compose_file_start_with_dot_slash(tmp_path: Path) -> None:
    """A formation file and results beside the compose file are written ``./NAME``: Compose reads a
    volume source without ``./`` or ``../`` as a named volume, not as a host directory."""
    formation = tmp_path / "paper.yaml"
    formation.write_text(PAPER.read_text())
    out = tmp_path / "compose.yaml"
    assert main([str(formation), "--out", str(out), "--context", "none", "--results", str(tmp_path / "out")]) == 0
    s = services(out)
    assert s["sim"]["volumes"] == [
        "./paper.yaml:/opt/formation/formations/paper.yaml:ro",
        "./out:/opt/formation/out",
    ]
    for svc in s.values():
        for volume in svc["volumes"]:
            assert volume.startswith(("./", "../")), volume


def test_keeps_a_different_generated_file_unless_forced(
    tmp_path: Path, paper_doc: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    """An existing --out generated from another formation file (or with other options) is kept, exit 2,
    the message naming its source and --force; the same output again is 'up to date' (exit 0)."""
    out = tmp_path / "compose.yaml"
    assert main([str(PAPER), "--out", str(out), "--context", "none"]) == 0
    first = out.read_text()
    assert main([str(PAPER), "--out", str(out), "--context", "none"]) == 0
    assert "up to date" in capsys.readouterr().out
    other = tmp_path / "trio.yaml"
    doc = copy.deepcopy(paper_doc)
    doc["name"], doc["agents"], doc["edges"] = "trio", doc["agents"][:3], doc["edges"][:2]
    other.write_text(yaml.safe_dump(doc))
    assert main([str(other), "--out", str(out), "--context", "none"]) == 2
    err = capsys.readouterr().err
    assert "generated from paper_5agents.yaml" in err and "--force" in err
    assert out.read_text() == first
    assert main([str(PAPER), "--out", str(out), "--context", "none", "--host-network"]) == 2
    assert out.read_text() == first
    assert main([str(other), "--out", str(out), "--context", "none", "--force"]) == 0
    assert sorted(services(out)) == ["agent_1", "agent_2", "agent_3", "sim"]


def test_check_reports_a_stale_file(tmp_path: Path) -> None:
    """--check exits 1 and prints a diff when the file differs from the generator's output."""
    out = tmp_path / "compose.yaml"
    assert main([str(PAPER), "--out", str(out)]) == 0
    out.write_text(out.read_text().replace('"1"]', '"9"]'))
    assert main([str(PAPER), "--out", str(out), "--check"]) == 1


def test_console_script_help() -> None:
    """formation-compose --help works from the project's environment."""
    exe = executable("formation-compose")
    result = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0
    assert "--out" in result.stdout


def test_commands_match_the_ros2_ws_scripts() -> None:
    """The services' commands are what ros2_ws/sim.sh and agent.sh accept (their --help)."""
    sim_sh, agent_sh = REPO / "ros2_ws" / "sim.sh", REPO / "ros2_ws" / "agent.sh"
    sim_help = subprocess.run([str(sim_sh), "--help"], capture_output=True, text=True, timeout=120).stdout
    agent_help = subprocess.run([str(agent_sh), "--help"], capture_output=True, text=True, timeout=60).stdout
    s = services(CHECKED_IN)
    for option in (a for a in s["sim"]["command"] if a.startswith("--")):
        assert option in sim_help, option
    assert "agent.sh FILE AGENT_ID" in agent_help


def _compose_cli() -> list[str] | None:
    """A compose CLI that validates files offline: docker compose v2, or Debian's docker-compose v1."""
    if shutil.which("docker"):
        v2 = subprocess.run(["docker", "compose", "version"], capture_output=True, text=True, timeout=30)
        if v2.returncode == 0:
            return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    return None


@pytest.mark.parametrize("host_network", [False, True], ids=["bridge", "host-network"])
def test_compose_cli_accepts_the_file(host_network: bool) -> None:
    """`docker compose config` (no engine needed) accepts the generated file."""
    cli = _compose_cli()
    if cli is None:
        pytest.skip("no compose CLI (docker compose v2 or docker-compose)")
    out = REPO / "docker" / f".test-compose-{os.getpid()}.yaml"  # beside the real one: same relative paths
    try:
        args = [str(PAPER), "--out", str(out), "--context", str(REPO)] + (["--host-network"] if host_network else [])
        assert main(args) == 0
        if cli == ["docker-compose"]:  # v1 predates the top-level `name` of the Compose Specification
            out.write_text("".join(line for line in out.read_text().splitlines(True) if not line.startswith("name:")))
        result = subprocess.run([*cli, "-f", str(out), "config"], capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, result.stderr
        assert "agent_5" in result.stdout
    finally:
        out.unlink(missing_ok=True)


def test_secure_compose_gives_each_service_only_its_own_key(tmp_path: Path) -> None:
    """--secure KEYS: fixed addresses on a private network, sim.sh/agent.sh --secure with every host,
    and each service mounts ca.pem and its own pair only."""
    out = tmp_path / "compose.yaml"
    keys = tmp_path / "keys"
    assert main([str(PAPER), "--out", str(out), "--context", str(REPO), "--secure", str(keys)]) == 0
    doc = yaml.safe_load(out.read_text())
    assert doc["networks"]["formation"]["ipam"]["config"] == [{"subnet": "172.30.77.0/24"}]
    sim, agent3 = doc["services"]["sim"], doc["services"]["agent_3"]
    assert agent3["networks"]["formation"]["ipv4_address"] == "172.30.77.13"
    assert agent3["command"][:5] == [
        "agent.sh",
        "/opt/formation/formations/paper_5agents.yaml",
        "3",
        "--secure",
        "/opt/formation/keys",
    ]
    assert "simulator=172.30.77.10" in agent3["command"] and "agent_3=172.30.77.13" in sim["command"]
    keyfiles = sorted(v.split(":")[0] for v in agent3["volumes"] if "/keys/" in v)
    assert keyfiles == ["./keys/agent_3.key", "./keys/agent_3.pem", "./keys/ca.pem"]
    assert all(v.endswith(":ro") for v in agent3["volumes"])
    assert main([str(PAPER), "--out", str(out), "--host-network", "--secure", str(keys), "--force"]) == 2


def test_discovery_server_makes_sim_sh_serve_and_every_agent_its_client(tmp_path: Path) -> None:
    """--discovery server: sim.sh starts the server on the service 'sim' (127.0.0.1 with --host-network),
    every agent.sh joins it on Fast DDS's default port; --secure with it is refused (exit 2)."""
    out = tmp_path / "compose.yaml"
    assert main([str(PAPER), "--out", str(out), "--context", "none", "--discovery", "server"]) == 0
    s = services(out)
    assert s["sim"]["command"][-2:] == ["--discovery", "server:sim:11811"]
    assert all(s[f"agent_{i}"]["command"][3:] == ["--discovery", "server:sim:11811"] for i in range(1, 6))
    args = [str(PAPER), "--out", str(out), "--context", "none", "--host-network", "--force"]
    assert main([*args, "--discovery", "server"]) == 0
    assert services(out)["agent_2"]["command"][3:] == ["--discovery", "server:127.0.0.1:11811"]
    assert main([*args, "--discovery", "server:10.1.2.3:7000"]) == 0
    assert services(out)["sim"]["command"][-1] == "server:10.1.2.3:7000"
    assert main([*args, "--discovery", "simple"]) == 0
    assert "--discovery" not in out.read_text()
    keys = ["--secure", str(tmp_path / "keys"), "--discovery", "server"]
    assert main([str(PAPER), "--out", str(out), "--context", "none", "--force", *keys]) == 2
