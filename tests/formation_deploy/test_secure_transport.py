"""Secure mode's transport profiles: ports from the formation, TLS-only transports, the environment."""

from __future__ import annotations

import datetime as dt
import re
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization

from formation_deploy.keys import init_keys, process_names
from formation_deploy.secure_transport import (
    OPENSSL_CONF,
    SecureRun,
    SecureTransportError,
    check_run_keys,
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


#: a run of 60 simulated seconds is expected to take at most 3 × 60 s + 600 s of wall time
RUN_S = 60.0
NOW = dt.datetime(2026, 6, 1, 12, 0, tzinfo=dt.UTC)


def _keys(tmp_path: Path, name: str = "keys", **kw) -> Path:
    keys = tmp_path / name
    init_keys(keys, process_names(["1", "2"]), **kw)
    return keys


def _reissue(keys: Path, name: str, start: dt.datetime, end: dt.datetime) -> None:
    """Replace ``name``'s certificate by one of the same CA and key valid from ``start`` to ``end``."""
    ca_key = serialization.load_pem_private_key((keys / "ca.key").read_bytes(), password=None)
    ca = x509.load_pem_x509_certificate((keys / "ca.pem").read_bytes())
    old = x509.load_pem_x509_certificate((keys / f"{name}.pem").read_bytes())
    cert = (
        x509.CertificateBuilder()
        .subject_name(old.subject)
        .issuer_name(ca.subject)
        .public_key(old.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .sign(ca_key, hashes.SHA256())  # type: ignore[arg-type]
    )
    (keys / f"{name}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def test_valid_keys_pass_the_run_check(tmp_path: Path) -> None:
    """Keys of 365 days issued now: nothing to say."""
    check_run_keys(_keys(tmp_path, now=NOW), process_names(["1", "2"]), RUN_S, now=NOW)


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("expired", r"agent_2\.pem: expired on 2026-05-31 12:00 UTC"),
        ("not yet valid", r"agent_2\.pem: not valid before 2026-07-01 12:00 UTC"),
        (
            "expires during the run",
            r"agent_2\.pem: expires on .* in 600 s: before the end of the run \(expected within 780 s\)",
        ),
        ("other CA", r"agent_2\.pem: not signed by this directory's CA \(ca\.pem\)"),
        ("key 0644", r"agent_2\.key: private key readable by others \(mode 0644, expected 0600\)"),
        ("missing", r"agent_2\.pem: missing"),
    ],
)
def test_run_check_names_the_file_and_the_problem(tmp_path: Path, case: str, message: str) -> None:
    """Expired, not-yet-valid, expiring before the run's expected end, another CA's, a key readable by
    others, a missing certificate: one line naming agent 2's file (the others are fine)."""
    names = process_names(["1", "2"])
    keys = _keys(tmp_path, now=NOW)
    validity = {
        "expired": (NOW - dt.timedelta(days=31), NOW - dt.timedelta(days=1)),
        "not yet valid": (NOW + dt.timedelta(days=30), NOW + dt.timedelta(days=60)),
        "expires during the run": (NOW - dt.timedelta(days=1), NOW + dt.timedelta(seconds=600)),
    }
    if case in validity:
        _reissue(keys, "agent_2", *validity[case])
    elif case == "other CA":
        other = _keys(tmp_path, "other", now=NOW)
        for suffix in ("pem", "key"):  # agent 2's pair from another CA directory
            (keys / f"agent_2.{suffix}").write_bytes((other / f"agent_2.{suffix}").read_bytes())
    elif case == "key 0644":
        (keys / "agent_2.key").chmod(0o644)
    else:
        (keys / "agent_2.pem").unlink()
    with pytest.raises(SecureTransportError) as info:
        check_run_keys(keys, names, RUN_S, now=NOW)
    text = str(info.value)
    assert "\n" not in text and re.match(rf"{re.escape(str(keys))}/{message}", text), text


def test_several_problems_name_the_first_and_count_the_rest(tmp_path: Path) -> None:
    """Two loose keys: the first is named, the other counted, with the command that lists them."""
    keys = _keys(tmp_path, now=NOW)
    (keys / "agent_1.key").chmod(0o640)
    (keys / "agent_2.key").chmod(0o644)
    with pytest.raises(SecureTransportError, match=r"agent_1\.key: .* \(and 1 more: formation-keys check "):
        check_run_keys(keys, process_names(["1", "2"]), RUN_S, now=NOW)


def test_secure_run_refused_before_anything_is_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SecureRun.prepare with a loose key: refused, and no profile directory is left in the temporary directory."""
    keys = _keys(tmp_path)
    (keys / "simulator.key").chmod(0o644)
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    with pytest.raises(SecureTransportError, match=r"simulator\.key: private key readable by others"):
        SecureRun.prepare(["1", "2"], {}, keys=keys, port_start=20000, duration_s=RUN_S)
    assert list(scratch.iterdir()) == []
