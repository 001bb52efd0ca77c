"""Secure mode's transport profiles: ports from the formation, TLS-only transports, the environment."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from formation_deploy.keys import init_keys, process_names
from formation_deploy.secure_transport import (
    OPENSSL_CONF,
    SecureTransportError,
    exports,
    peers_of,
    secure_environment,
    write_process_config,
)

NS = {"d": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}


def test_ports_follow_the_file_order_and_hosts_are_checked() -> None:
    """simulator = base, agent k = base + 1 + k, then recorder and replay; an unknown host name is refused."""
    peers = peers_of(["1", "2"], port_base=9000, hosts={"agent_2": "10.0.0.7"})
    assert [(p.name, p.host, p.port) for p in peers.values()] == [
        ("simulator", "127.0.0.1", 9000),
        ("agent_1", "127.0.0.1", 9001),
        ("agent_2", "10.0.0.7", 9002),
        ("recorder", "127.0.0.1", 9003),
        ("replay", "127.0.0.1", 9004),
    ]
    with pytest.raises(SecureTransportError, match="agent_9"):
        peers_of(["1"], hosts={"agent_9": "10.0.0.9"})
    with pytest.raises(SecureTransportError, match="port base: 65534"):
        peers_of(["1"], port_base=65534)


def test_profile_is_tls_over_tcp_only_and_connects_to_lower_ports(tmp_path: Path) -> None:
    """Agent 2's profile: TCPv4 with TLS (its own key, the CA), no builtin transports, peers below its port."""
    keys = tmp_path / "keys"
    init_keys(keys, process_names(["1", "2"]))
    peers = peers_of(["1", "2"], port_base=9000)
    env = write_process_config("agent_2", peers, keys, tmp_path / "profiles", listen="127.0.0.1")
    root = ET.parse(env["FASTRTPS_DEFAULT_PROFILES_FILE"]).getroot()
    transport = root.find(".//d:transport_descriptor", NS)
    assert transport is not None
    assert transport.findtext("d:type", namespaces=NS) == "TCPv4"
    assert transport.findtext("d:listening_ports/d:port", namespaces=NS) == "9002"
    assert transport.findtext("d:tls/d:cert_chain_file", namespaces=NS) == str((keys / "agent_2.pem").resolve())
    assert transport.findtext("d:tls/d:private_key_file", namespaces=NS) == str((keys / "agent_2.key").resolve())
    assert transport.findtext("d:tls/d:verify_file", namespaces=NS) == str((keys / "ca.pem").resolve())
    verify = [v.text for v in transport.findall("d:tls/d:verify_mode/d:verify", NS)]
    assert verify == ["VERIFY_PEER", "VERIFY_FAIL_IF_NO_PEER_CERT"]
    assert root.findtext(".//d:rtps/d:useBuiltinTransports", namespaces=NS) == "false"
    ports = [p.text for p in root.findall(".//d:initialPeersList/d:locator/d:tcpv4/d:physical_port", NS)]
    assert ports == ["9000", "9001"]
    assert Path(env["OPENSSL_CONF"]).read_text() == OPENSSL_CONF
    assert "VerifyMode = Peer,Require" in OPENSSL_CONF
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"


def test_simulator_profile_has_no_initial_peers(tmp_path: Path) -> None:
    """The lowest port only accepts (an empty initialPeersList would make Fast DDS drop the whole profile)."""
    keys = tmp_path / "keys"
    init_keys(keys, process_names(["1"]))
    env = write_process_config("simulator", peers_of(["1"]), keys, tmp_path / "p")
    assert "initialPeersList" not in Path(env["FASTRTPS_DEFAULT_PROFILES_FILE"]).read_text()


def test_missing_key_is_named(tmp_path: Path) -> None:
    """A process whose key was not issued is refused with the missing file's path."""
    keys = tmp_path / "keys"
    init_keys(keys, ["simulator"])
    with pytest.raises(SecureTransportError, match=r"agent_1\.pem: missing"):
        write_process_config("agent_1", peers_of(["1"]), keys, tmp_path / "p")


def test_environment_drops_what_would_bypass_the_profile() -> None:
    """Static peers, builtin-transport and XML-QoS overrides are removed; the shell form unsets them too."""
    base = {"ROS_STATIC_PEERS": "10.0.0.2", "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4", "HOME": "/root"}
    env = secure_environment(base, {"OPENSSL_CONF": "/x/openssl.cnf"})
    assert env == {"HOME": "/root", "OPENSSL_CONF": "/x/openssl.cnf"}
    text = exports({"OPENSSL_CONF": "/x/it's.cnf"})
    assert text.splitlines()[0].startswith("unset ROS_STATIC_PEERS FASTDDS_BUILTIN_TRANSPORTS")
    assert "export OPENSSL_CONF='/x/it'\"'\"'s.cnf'" in text
