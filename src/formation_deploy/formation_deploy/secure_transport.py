"""Secure mode's transport: a Fast DDS XML profile per process (TCP with mutual TLS, nothing else).

Every process of a secure run gets, through its environment:

- ``FASTRTPS_DEFAULT_PROFILES_FILE``: a profile whose only transport is TCPv4 with TLS (its
  certificate and key from ``formation-keys``, the formation's CA as the only trust anchor),
  ``useBuiltinTransports=false`` (no UDP, no shared memory), a listening port of its own, and as
  initial peers the processes whose port is lower than its own (the higher port connects: with
  Fast DDS 2.14.5 two processes that list each other never connect; found by experiment).
- ``OPENSSL_CONF``: an OpenSSL configuration whose ``system_default`` section sets
  ``VerifyMode = Peer,Require``. Fast DDS 2.14.5 applies the profile's ``verify_mode`` only to
  the connections a process opens (and only its first flag), so the accepting side never asks for
  a certificate: without this file a process without any certificate, or with one of another CA,
  is accepted (docs/security.md, "Evidence").
- ``ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT``: under ``LOCALHOST`` the rmw adds its own UDP
  and shared-memory transports to the profile's; ``ROS_STATIC_PEERS`` is dropped for the same reason.

Before anything starts, :func:`check_run_keys` checks every process's certificate and key
(present, signed by the formation's CA, valid now and for the run's expected wall time, key mode
0600) and names the first file with a problem: a certificate refused later is a TLS handshake
failure that only the processes' logs show.

Ports are derived from the formation: ``base`` for the simulator, ``base + 1 + k`` for the k-th
agent of the file, then the recorder and the replay. The hosts default to 127.0.0.1 (one
machine); a multi-host run gives each process's address (docs/security.md).
"""

from __future__ import annotations

import datetime as dt
import math
import os
import shutil
import socket
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape

from formation_core.faults import write_atomic
from formation_deploy.keys import KeysError, cert_path, check_keys, init_keys, key_path, process_names
from formation_deploy.transport_check import SECURE_FLAG

#: Default first port of a multi-host secure run (one port per process above it).
DEFAULT_PORT_BASE = 7700
LOOPBACK = "127.0.0.1"
_TRANSPORT_ID = "formation_tls"
#: Environment variables that would add or change transports behind the profile's back.
_DROPPED = (
    "ROS_STATIC_PEERS",
    "FASTDDS_BUILTIN_TRANSPORTS",
    "RMW_FASTRTPS_USE_QOS_FROM_XML",
    "FASTDDS_DEFAULT_PROFILES_FILE",
)
OPENSSL_CONF = """\
# formation secure mode: every TLS context of this process verifies its peer and requires a certificate
openssl_conf = formation_openssl
[formation_openssl]
ssl_conf = formation_ssl
[formation_ssl]
system_default = formation_tls
[formation_tls]
VerifyMode = Peer,Require
MinProtocol = TLSv1.2
"""


class SecureTransportError(ValueError):
    """Secure mode cannot be configured (the message names the option or file)."""


#: a run's expected wall time is at most this many times its simulated duration (a lockstep run
#: on a busy machine runs slower than real time) …
RUN_TIME_FACTOR = 3.0
#: … plus this long for discovery and writing the outputs [wall s]
RUN_TIME_EXTRA_S = 600.0


def expected_run_s(duration_s: float) -> float:
    """The wall seconds a run of ``duration_s`` simulated seconds is expected to take at most."""
    return RUN_TIME_FACTOR * duration_s + RUN_TIME_EXTRA_S


def check_run_keys(keys: Path, names: Sequence[str], duration_s: float, *, now: dt.datetime | None = None) -> None:
    """The pre-flight of a secure run: SecureTransportError naming the first file with a problem
    (missing, not signed by ``keys``'s CA, expired, not yet valid, expiring before the run's
    expected end, a private key readable by others), and how many more there are."""
    if not keys.is_dir():
        raise SecureTransportError(f"{keys}: not a key directory (formation-keys init {keys} --formation FILE)")
    try:
        problems = check_keys(keys, names, now=now, run_s=expected_run_s(duration_s))
    except KeysError as exc:
        raise SecureTransportError(str(exc)) from None
    if problems:
        more = f" (and {len(problems) - 1} more: formation-keys check {keys})" if len(problems) > 1 else ""
        raise SecureTransportError(f"{problems[0]}{more}")


@dataclass(frozen=True)
class Peer:
    """One process of a secure run: its key name, host and listening port."""

    name: str
    host: str
    port: int


def peers_of(
    agent_ids: Sequence[str], *, port_base: int = DEFAULT_PORT_BASE, hosts: Mapping[str, str] | None = None
) -> dict[str, Peer]:
    """Every process of the formation with its port (from the file's agent order) and host."""
    names = process_names(agent_ids)
    if not 1024 <= port_base <= 65535 - len(names):
        raise SecureTransportError(f"port base: {port_base} leaves no room for {len(names)} ports in 1024..65535")
    hosts = dict(hosts or {})
    unknown = sorted(set(hosts) - set(names))
    if unknown:
        raise SecureTransportError(f"hosts: unknown process name(s) {', '.join(unknown)} (known: {', '.join(names)})")
    return {n: Peer(n, hosts.get(n, LOOPBACK), port_base + k) for k, n in enumerate(names)}


def single_host_port_start(domain_id: int) -> int:
    """Where a single-host secure run looks for free ports: one block of 100 per ROS_DOMAIN_ID, below
    Linux's ephemeral port range (32768…)."""
    return 10000 + 100 * (domain_id % 200)


def free_port_base(count: int, start: int, *, host: str = LOOPBACK, step: int = 100) -> int:
    """The first base from ``start`` (by ``step``) whose ``count`` TCP ports are all free on ``host``."""
    for base in range(start, 32768 - count, step):
        if all(_port_free(host, base + k) for k in range(count)):
            return base
    raise SecureTransportError(f"no {count} free TCP ports from {start} on {host}")


def _port_free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def profile_xml(me: Peer, peers: Mapping[str, Peer], keys: Path, *, listen: str | None = None) -> str:
    """The Fast DDS profile of process ``me``: TLS over TCP only, connecting to the lower ports."""
    keys = keys.resolve()
    initial = "".join(
        f"<locator><tcpv4><address>{escape(p.host)}</address><physical_port>{p.port}</physical_port></tcpv4></locator>"
        for p in peers.values()
        if p.port < me.port
    )
    peers_xml = f"<initialPeersList>{initial}</initialPeersList>" if initial else ""
    # announcements sent while a TLS connection is still being set up are lost: repeat them often at
    # first (20 × 0.25 s) instead of waiting for the periodic one (3 s)
    announce = (
        "<discovery_config><initialAnnouncements><count>20</count>"
        "<period><nanosec>250000000</nanosec></period></initialAnnouncements></discovery_config>"
    )
    builtin = f"<builtin>{announce}{peers_xml}</builtin>"
    whitelist = f"<interfaceWhiteList><address>{escape(listen)}</address></interfaceWhiteList>" if listen else ""
    return f"""<?xml version="1.0" encoding="UTF-8" ?>
<!-- formation secure mode: process {escape(me.name)} (generated; docs/security.md) -->
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>{_TRANSPORT_ID}</transport_id>
        <type>TCPv4</type>
        {whitelist}
        <listening_ports><port>{me.port}</port></listening_ports>
        <enable_tcp_nodelay>true</enable_tcp_nodelay>
        <tls>
          <verify_file>{escape(str(cert_path(keys, "ca")))}</verify_file>
          <cert_chain_file>{escape(str(cert_path(keys, me.name)))}</cert_chain_file>
          <private_key_file>{escape(str(key_path(keys, me.name)))}</private_key_file>
          <verify_mode><verify>VERIFY_PEER</verify><verify>VERIFY_FAIL_IF_NO_PEER_CERT</verify></verify_mode>
          <options>
            <option>DEFAULT_WORKAROUNDS</option><option>NO_COMPRESSION</option><option>NO_SSLV2</option>
            <option>NO_SSLV3</option><option>NO_TLSV1</option><option>NO_TLSV1_1</option>
          </options>
          <handshake_role>DEFAULT</handshake_role>
        </tls>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="formation_secure" is_default_profile="true">
      <rtps>
        <userTransports><transport_id>{_TRANSPORT_ID}</transport_id></userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
        {builtin}
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def write_process_config(
    name: str, peers: Mapping[str, Peer], keys: Path, directory: Path, *, listen: str | None = None
) -> dict[str, str]:
    """Write ``name``'s profile and OpenSSL configuration into ``directory``; return its environment additions."""
    if name not in peers:
        raise SecureTransportError(f"process {name!r} is not one of {', '.join(peers)}")
    for needed in (cert_path(keys, "ca"), cert_path(keys, name), key_path(keys, name)):
        if not needed.is_file():
            raise SecureTransportError(f"{needed}: missing (formation-keys init {keys} --formation FILE)")
    directory.mkdir(parents=True, exist_ok=True)
    # one file per process, replaced atomically: processes starting together never read a half-written one
    profile, conf = directory / f"{name}.xml", directory / f"{name}.openssl.cnf"
    write_atomic(profile, profile_xml(peers[name], peers, keys, listen=listen).encode("utf-8"), mode=0o600)
    write_atomic(conf, OPENSSL_CONF.encode("utf-8"), mode=0o600)
    return {
        SECURE_FLAG: "1",  # the nodes refuse to run if the profile did not apply (transport_check)
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT",
        "FASTRTPS_DEFAULT_PROFILES_FILE": str(profile.resolve()),
        "OPENSSL_CONF": str(conf.resolve()),
    }


def secure_environment(base: Mapping[str, str], additions: Mapping[str, str]) -> dict[str, str]:
    """``base`` without the variables that would bypass the profile, plus ``additions``."""
    env = {k: v for k, v in base.items() if k not in _DROPPED}
    env.update(additions)
    return env


def exports(additions: Mapping[str, str]) -> str:
    """Shell lines that apply ``additions`` and unset the bypassing variables (for sim.sh / agent.sh)."""
    lines = [f"unset {' '.join(_DROPPED)}"]
    lines += [f"export {k}={_shell_quote(v)}" for k, v in additions.items()]
    return "\n".join(lines) + "\n"


def _shell_quote(value: str) -> str:
    return "'" + value.replace("'", "'\"'\"'") + "'"


def private_dir(parent: Path) -> Path:
    """``parent`` created with mode 0700 (profiles name key files; nobody else needs to read them)."""
    parent.mkdir(parents=True, exist_ok=True)
    os.chmod(parent, 0o700)
    return parent


@dataclass
class SecureRun:
    """Secure mode of one single-host run (formation-launch --secure): an environment per process.

    Without a key directory, a CA and keys are made for this run only in a private temporary
    directory, removed by :meth:`close` (with the profiles).
    """

    environments: dict[str, dict[str, str]]
    peers: dict[str, Peer]
    workdir: Path
    ephemeral_keys: bool

    @classmethod
    def prepare(
        cls,
        agent_ids: Sequence[str],
        base_env: Mapping[str, str],
        *,
        keys: Path | None,
        port_start: int,
        duration_s: float,
    ) -> SecureRun:
        """Check ``keys`` (:func:`check_run_keys`) for a run of ``duration_s`` simulated seconds, then
        write every process's profile; raises SecureTransportError (nothing left behind) or OSError."""
        names = process_names(agent_ids)
        ephemeral = keys is None
        if keys is not None:
            check_run_keys(keys, names, duration_s)
        workdir = Path(tempfile.mkdtemp(prefix="formation-secure-"))  # mode 0700
        try:
            if keys is None:
                keys = workdir / "keys"
                days = 2 + math.ceil(expected_run_s(duration_s) / 86400)
                init_keys(keys, names, days=days)
            base = free_port_base(len(names), port_start)
            peers = peers_of(agent_ids, port_base=base)
            profiles = workdir / "profiles"
            envs = {
                n: secure_environment(base_env, write_process_config(n, peers, keys, profiles, listen=LOOPBACK))
                for n in names
            }
        except BaseException:
            shutil.rmtree(workdir, ignore_errors=True)
            raise
        return cls(envs, peers, workdir, ephemeral)

    def describe(self) -> dict[str, object]:
        """For summary.json: transport, ports, whether the keys were made for this run."""
        ports = [p.port for p in self.peers.values()]
        return {"transport": "TCPv4+TLS (mutual)", "ports": [min(ports), max(ports)], "run_keys": self.ephemeral_keys}

    def close(self) -> None:
        shutil.rmtree(self.workdir, ignore_errors=True)
