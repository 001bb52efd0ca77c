"""The transports of a run's processes (formation_sim.launch.dds_env.transport_environment): UDP
only, never Fast DDS's shared memory; LOCALHOST carried out by the loopback profile."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest

from formation_core.options import Discovery
from formation_sim.launch.dds_env import (
    FASTDDS_LOOPBACK_PROFILE,
    FASTDDS_PROFILE,
    discovery_client_environment,
    shell_lines,
    transport_environment,
)

NS = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
LOOPBACK = str(FASTDDS_LOOPBACK_PROFILE)
GENERAL = str(FASTDDS_PROFILE)


@pytest.mark.parametrize("requested", [None, "", "LOCALHOST"])
def test_localhost_becomes_the_loopback_profile_and_is_stable(requested: str | None) -> None:
    """LOCALHOST (or no range) without static peers: SYSTEM_DEFAULT + the loopback profile (the rmw's
    LOCALHOST would add shared memory); applying it again changes nothing."""
    base = {"FASTDDS_BUILTIN_TRANSPORTS": "DEFAULT"}
    if requested is not None:
        base["ROS_AUTOMATIC_DISCOVERY_RANGE"] = requested
    env = transport_environment(base)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == LOOPBACK
    assert "FASTDDS_BUILTIN_TRANSPORTS" not in env  # the profile names its one transport
    assert transport_environment(env) == env
    assert "FASTRTPS_DEFAULT_PROFILES_FILE" not in base  # the caller's mapping is left alone


@pytest.mark.parametrize("requested", ["SUBNET", "SYSTEM_DEFAULT", "OFF"])
def test_other_ranges_keep_their_range_with_udp_only(requested: str) -> None:
    env = transport_environment({"ROS_AUTOMATIC_DISCOVERY_RANGE": requested})
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == requested
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == GENERAL
    assert env["FASTDDS_BUILTIN_TRANSPORTS"] == "UDPv4"
    assert transport_environment(env) == env


def test_static_peers_keep_the_rmw_localhost_range() -> None:
    """ROS_STATIC_PEERS reach other hosts only under the rmw's LOCALHOST (or SUBNET): kept, with UDP
    asked for (the rmw adds its shared memory there all the same: docs/ros2.md, "Transports")."""
    env = transport_environment({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_STATIC_PEERS": "10.0.0.2"})
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == GENERAL


def test_a_profile_of_the_users_own_is_left_alone() -> None:
    base = {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"}
    assert transport_environment(base) == {**base, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


def test_a_discovery_client_uses_udp_on_every_interface() -> None:
    """A client (of a server that may be on another host) leaves the loopback profile for the general
    one with UDP only, in the range SYSTEM_DEFAULT."""
    host = transport_environment({})
    env = discovery_client_environment(host, Discovery("server", "10.0.0.1", 7000))
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == GENERAL
    assert env["FASTDDS_BUILTIN_TRANSPORTS"] == "UDPv4"


def test_the_loopback_profile_is_udp_on_127_0_0_1_only() -> None:
    """The participant profile every LOCALHOST process loads by default: builtin transports off, one
    UDPv4 transport whitelisted to 127.0.0.1, unicast discovery to 127.0.0.1, no multicast locator;
    its data writer profile is the general profile's, element for element."""
    root = ET.parse(FASTDDS_LOOPBACK_PROFILE).getroot()
    (participant,) = root.findall("f:participant", NS)
    assert participant.get("is_default_profile") == "true"
    rtps = participant.find("f:rtps", NS)
    assert rtps.findtext("f:useBuiltinTransports", namespaces=NS) == "false"
    (transport_id,) = [e.text for e in rtps.findall("f:userTransports/f:transport_id", NS)]
    (descriptor,) = root.findall("f:transport_descriptors/f:transport_descriptor", NS)
    assert descriptor.findtext("f:transport_id", namespaces=NS) == transport_id
    assert descriptor.findtext("f:type", namespaces=NS) == "UDPv4"
    assert [a.text for a in descriptor.findall("f:interfaceWhiteList/f:address", NS)] == ["127.0.0.1"]
    builtin = rtps.find("f:builtin", NS)
    for where in ("metatrafficUnicastLocatorList", "initialPeersList"):
        assert [a.text for a in builtin.findall(f"f:{where}/f:locator/f:udpv4/f:address", NS)] == ["127.0.0.1"]
    assert builtin.find("f:metatrafficMulticastLocatorList", NS) is None

    def writer(path) -> bytes:
        (w,) = ET.parse(path).getroot().findall("f:data_writer", NS)
        return ET.tostring(w)

    assert writer(FASTDDS_LOOPBACK_PROFILE) == writer(FASTDDS_PROFILE)


def test_shell_lines_turn_one_environment_into_the_other() -> None:
    before = {"KEEP": "1", "GONE": "x", "CHANGED": "a b"}
    after = {"KEEP": "1", "CHANGED": "it's", "NEW": "$HOME"}
    script = shell_lines(before, after) + '\necho "$KEEP|${GONE-unset}|$CHANGED|$NEW"'
    shown = subprocess.run(["sh", "-c", script], capture_output=True, text=True, env=before, timeout=30)
    assert shown.stdout.strip() == "1|unset|it's|$HOME"


def test_the_transports_command_prints_what_network_sh_evaluates() -> None:
    cmd = [sys.executable, "-m", "formation_sim.launch.dds_env", "transports"]
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "PATH": "/usr/bin:/bin"}
    if "PYTHONPATH" in os.environ:  # the sources this test imports (a mutation check's copy), not the installed
        env["PYTHONPATH"] = os.environ["PYTHONPATH"]
    lines = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60, check=True).stdout
    script = lines + '\necho "$ROS_AUTOMATIC_DISCOVERY_RANGE|$FASTRTPS_DEFAULT_PROFILES_FILE"'
    shown = subprocess.run(["sh", "-c", script], capture_output=True, text=True, env=env, timeout=30)
    assert shown.stdout.strip() == f"SYSTEM_DEFAULT|{LOOPBACK}"
    bad = subprocess.run([*cmd[:-1], "nothing"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "usage" in bad.stderr
