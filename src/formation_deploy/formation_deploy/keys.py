"""``formation-keys init|check|profile DIR --formation FILE``: the formation's CA and one key pair per process.

Secure mode (docs/security.md) runs every process over TLS with mutual certificate verification
against the formation's CA. ``init`` creates, with the ``cryptography`` library:

- ``ca.pem`` (the CA certificate every process trusts) and ``ca.key`` (its private key: needed
  only to issue certificates; keep it off the robots);
- ``<name>.pem`` and ``<name>.key`` for every process: ``simulator``, ``agent_<id>`` per agent,
  ``recorder`` and ``replay``. ECDSA P-256 keys; certificates for both TLS roles (each process
  connects to some peers and accepts others).

Private keys are written with mode 0600 (readable by their owner only). ``check`` verifies every
certificate against the CA, that each key matches its certificate, the modes, and the expiry
(exit 1 if one expires within ``--min-days``). Rotation: ``init`` a new directory and restart
every process with it (a certificate of the old CA is refused by the new one). ``profile``
writes one process's transport profile (formation_deploy.secure_transport) and prints the shell
lines that select it; ``sim.sh`` and ``agent.sh --secure`` use it.

Exit status: 0 valid, 1 a check failed, 2 invalid input (file, directory).
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import stat
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from formation_msgs_py.errors import FormationError, FormationSpecError

EXIT_OK, EXIT_FAILED, EXIT_INVALID = 0, 1, 2
CA_NAME = "ca"
DEFAULT_DAYS = 365
#: Processes that are not agents and may join a secure run.
SERVICE_NAMES = ("simulator", "recorder", "replay")
#: Allowed clock skew between hosts at issue time [s]: certificates are valid from this long ago.
_BACKDATE = dt.timedelta(minutes=5)


class KeysError(FormationError):
    """A key directory cannot be created or is unusable (the message names the file)."""


def process_names(agent_ids: Sequence[str]) -> list[str]:
    """The key names of a formation's processes: simulator, agent_<id> for each agent, recorder, replay."""
    return ["simulator", *(f"agent_{a}" for a in agent_ids), "recorder", "replay"]


def cert_path(keys: Path, name: str) -> Path:
    return keys / f"{name}.pem"


def key_path(keys: Path, name: str) -> Path:
    return keys / f"{name}.key"


def _write_private(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    """PEM, unencrypted (the processes start unattended), mode 0600 from creation on."""
    data = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)


def _name(common_name: str) -> x509.Name:
    organization = x509.NameAttribute(NameOID.ORGANIZATION_NAME, "formation")
    return x509.Name([organization, x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def init_keys(keys: Path, names: Sequence[str], *, days: int = DEFAULT_DAYS, now: dt.datetime | None = None) -> None:
    """Create the CA and one key pair per name in the new or empty directory ``keys``."""
    if days <= 0:
        raise KeysError(f"--days: must be > 0, got {days}")
    if keys.exists() and any(keys.iterdir()):
        raise KeysError(f"{keys}: not empty; keys are never overwritten (choose a new directory to rotate)")
    keys.mkdir(parents=True, exist_ok=True, mode=0o700)
    start = (now or dt.datetime.now(dt.UTC)) - _BACKDATE
    end = start + _BACKDATE + dt.timedelta(days=days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_subject = _name("formation CA")
    ca_cert = (
        x509.CertificateBuilder()
        .subject_name(ca_subject)
        .issuer_name(ca_subject)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True
        )  # key_cert_sign, crl_sign
        .sign(ca_key, hashes.SHA256())
    )
    _write_private(key_path(keys, CA_NAME), ca_key)
    cert_path(keys, CA_NAME).write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))
    for name in names:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(_name(name))
            .issuer_name(ca_subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(start)
            .not_valid_after(end)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.KeyUsage(True, False, False, False, False, False, False, False, False), critical=True
            )  # digital_signature
            .add_extension(
                x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                critical=False,
            )
            .sign(ca_key, hashes.SHA256())
        )
        _write_private(key_path(keys, name), key)
        cert_path(keys, name).write_bytes(cert.public_bytes(serialization.Encoding.PEM))


@dataclass(frozen=True)
class Problem:
    """One failed check: the file and what is wrong with it."""

    path: Path
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}"


def _load_cert(path: Path) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except (OSError, ValueError) as exc:
        raise KeysError(f"{path}: not a readable PEM certificate ({exc})") from exc


def _check_mode(path: Path) -> list[Problem]:
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        return [Problem(path, f"private key readable by others (mode {mode:04o}, expected 0600)")]
    return []


def check_keys(
    keys: Path, names: Sequence[str], *, min_days: float = 7.0, now: dt.datetime | None = None
) -> list[Problem]:
    """Every problem of ``keys`` for ``names`` (empty: valid for at least ``min_days`` more days)."""
    now = now or dt.datetime.now(dt.UTC)
    problems: list[Problem] = []
    ca_file = cert_path(keys, CA_NAME)
    if not ca_file.is_file():
        return [Problem(ca_file, "missing (formation-keys init DIR)")]
    ca = _load_cert(ca_file)
    ca_public = ca.public_key()
    assert isinstance(ca_public, ec.EllipticCurvePublicKey)
    if key_path(keys, CA_NAME).exists():
        problems += _check_mode(key_path(keys, CA_NAME))
    for name in [CA_NAME, *names]:
        cfile, kfile = cert_path(keys, name), key_path(keys, name)
        if not cfile.is_file():
            problems.append(Problem(cfile, "missing"))
            continue
        cert = ca if name == CA_NAME else _load_cert(cfile)
        if name != CA_NAME:
            try:
                ca_public.verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
            except InvalidSignature:
                problems.append(Problem(cfile, "not signed by this directory's CA (ca.pem)"))
            if cert.issuer != ca.subject:
                problems.append(Problem(cfile, f"issuer {cert.issuer.rfc4514_string()} is not the CA"))
            if not kfile.is_file():
                problems.append(Problem(kfile, "missing"))
            else:
                problems += _check_mode(kfile)
                key = serialization.load_pem_private_key(kfile.read_bytes(), password=None)
                if key.public_key() != cert.public_key():
                    problems.append(Problem(kfile, f"does not match {cfile.name}"))
        left = cert.not_valid_after_utc - now
        if left <= dt.timedelta(0):
            problems.append(Problem(cfile, f"expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC"))
        elif left < dt.timedelta(days=min_days):
            problems.append(Problem(cfile, f"expires in {left.total_seconds() / 86400:.1f} days (< {min_days:g})"))
        if cert.not_valid_before_utc > now:
            problems.append(Problem(cfile, f"not valid before {cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC"))
    return problems


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="formation-keys",
        description="The formation's CA and one key pair per process for secure mode (docs/security.md). "
        "Exit status: 0 valid, 1 a check failed, 2 invalid input.",
    )
    sub = p.add_subparsers(dest="command", required=True)
    init = sub.add_parser("init", help="create the CA and the keys of every process in a new directory")
    check = sub.add_parser("check", help="verify the certificates, keys, modes and expiry")
    for q in (init, check):
        q.add_argument("dir", type=Path, help="key directory")
        q.add_argument("--formation", type=Path, required=True, help="formation file (its agents get keys)")
    init.add_argument("--days", type=int, default=DEFAULT_DAYS, help=f"validity in days (default {DEFAULT_DAYS})")
    check.add_argument("--min-days", type=float, default=7.0, help="fail if a certificate expires sooner (default 7)")
    profile = sub.add_parser(
        "profile",
        help="write one process's secure transport profile and print the shell lines that select it "
        "(what sim.sh / agent.sh --secure eval)",
    )
    profile.add_argument("dir", type=Path, help="key directory")
    profile.add_argument("name", help="process: simulator, agent_<id>, recorder or replay")
    profile.add_argument("--formation", type=Path, required=True, help="formation file (ports follow its agents)")
    profile.add_argument("--out", type=Path, required=True, help="directory for the profile and openssl.cnf")
    profile.add_argument("--hosts", type=Path, help="YAML mapping process name -> host (default: all 127.0.0.1)")
    profile.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="NAME=ADDR",
        help="one process's host (repeat; wins over --hosts)",
    )
    profile.add_argument("--port-base", type=int, help="first port, the same on every host (default 7700)")
    profile.add_argument("--listen", help="local address to listen on (default: this process's host)")
    return p


def _profile(args: argparse.Namespace, agent_ids: Sequence[str]) -> str:
    import yaml

    from formation_deploy.secure_transport import DEFAULT_PORT_BASE, exports, peers_of, write_process_config

    hosts: dict[str, str] = {}
    if args.hosts is not None:
        try:
            loaded = yaml.safe_load(args.hosts.read_text(encoding="utf-8")) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise KeysError(f"{args.hosts}: not a readable YAML file ({exc})") from exc
        if not isinstance(loaded, dict) or not all(isinstance(v, str) for v in loaded.values()):
            raise KeysError(f"{args.hosts}: expected a mapping of process name to host, got {loaded!r}")
        hosts = {str(k): v for k, v in loaded.items()}
    for item in args.host:
        name, sep, addr = item.partition("=")
        if not sep or not name or not addr:
            raise KeysError(f"--host: expected NAME=ADDR, got {item!r}")
        hosts[name] = addr
    peers = peers_of(agent_ids, port_base=args.port_base or DEFAULT_PORT_BASE, hosts=hosts)
    if args.name not in peers:
        raise KeysError(f"process {args.name!r} is not one of {', '.join(peers)}")
    listen = args.listen or peers[args.name].host
    return exports(write_process_config(args.name, peers, args.dir, args.out, listen=listen))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from formation_msgs_py.spec import load_formation  # numpy: not for --help

    try:
        agent_ids = load_formation(args.formation).agent_ids
        names = process_names(agent_ids)
        if args.command == "profile":
            print(_profile(args, agent_ids), end="")
            return EXIT_OK
        if args.command == "init":
            init_keys(args.dir, names, days=args.days)
            print(f"formation-keys: CA and {len(names)} key pairs in {args.dir}/ ({', '.join(names)})")
            print(f"formation-keys: {key_path(args.dir, CA_NAME)} signs certificates only: keep it off the robots")
            return EXIT_OK
        problems = check_keys(args.dir, names, min_days=args.min_days)
    except (FormationSpecError, KeysError, ValueError) as exc:
        print(f"formation-keys: {exc}", file=sys.stderr)
        return EXIT_INVALID
    for problem in problems:
        print(f"formation-keys: {problem}", file=sys.stderr)
    if problems:
        return EXIT_FAILED
    print(f"formation-keys: {len(names)} key pairs in {args.dir}/ valid and signed by its CA")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
