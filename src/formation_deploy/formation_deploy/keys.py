"""The formation's CA and one key pair per process for secure mode (library; the command line is
:mod:`formation_deploy.keys_cli`).

Secure mode (docs/security.md) runs every process over TLS with mutual certificate verification
against the formation's CA. :func:`init_keys` creates, with the ``cryptography`` library:

- ``ca.pem`` (the CA certificate every process trusts) and ``ca.key`` (its private key: needed
  only to issue certificates; keep it off the robots);
- ``<name>.pem`` and ``<name>.key`` for every process: ``simulator``, ``agent_<id>`` per agent,
  ``recorder`` and ``replay``. ECDSA P-256 keys; certificates for both TLS roles (each process
  connects to some peers and accepts others).

Private keys are written with mode 0600 (readable by their owner only). :func:`check_keys`
verifies every certificate against the CA, that each key matches its certificate, the modes, and
the expiry. Rotation: create a new directory and restart every process with it (a certificate of
the old CA is refused by the new one).
"""

from __future__ import annotations

import datetime as dt
import os
import stat
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from formation_core.errors import FormationError

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
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
    except OSError as exc:
        return [Problem(path, f"cannot be read ({exc.strerror})")]
    if mode & 0o077:
        return [Problem(path, f"private key readable by others (mode {mode:04o}, expected 0600)")]
    return []


def check_keys(
    keys: Path,
    names: Sequence[str],
    *,
    min_days: float = 7.0,
    now: dt.datetime | None = None,
    run_s: float | None = None,
) -> list[Problem]:
    """Every problem of ``keys`` for ``names`` (empty: valid for at least ``min_days`` more days,
    or with ``run_s``, for the ``run_s`` wall seconds a run is expected to last)."""
    now = now or dt.datetime.now(dt.UTC)
    need = dt.timedelta(days=min_days) if run_s is None else dt.timedelta(seconds=run_s)
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
            hash_algorithm = cert.signature_hash_algorithm  # None for a signature scheme without one (Ed25519)
            try:
                if hash_algorithm is None:
                    raise InvalidSignature
                ca_public.verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(hash_algorithm))
            except (InvalidSignature, ValueError, TypeError):  # ValueError, TypeError: an RSA signature
                problems.append(Problem(cfile, "not signed by this directory's CA (ca.pem)"))
            if cert.issuer != ca.subject:
                problems.append(Problem(cfile, f"issuer {cert.issuer.rfc4514_string()} is not the CA"))
            if not kfile.is_file():
                problems.append(Problem(kfile, "missing"))
            else:
                problems += _check_mode(kfile)
                try:
                    key = serialization.load_pem_private_key(kfile.read_bytes(), password=None)
                except (OSError, ValueError, TypeError) as exc:
                    problems.append(Problem(kfile, f"not a readable unencrypted PEM private key ({exc})"))
                else:
                    if key.public_key() != cert.public_key():
                        problems.append(Problem(kfile, f"does not match {cfile.name}"))
        left = cert.not_valid_after_utc - now
        if left <= dt.timedelta(0):
            problems.append(Problem(cfile, f"expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC"))
        elif left < need and run_s is not None:
            problems.append(
                Problem(
                    cfile,
                    f"expires on {cert.not_valid_after_utc:%Y-%m-%d %H:%M:%S} UTC, in {left.total_seconds():.0f} s: "
                    f"before the end of the run (expected within {run_s:.0f} s)",
                )
            )
        elif left < need:
            problems.append(Problem(cfile, f"expires in {left.total_seconds() / 86400:.1f} days (< {min_days:g})"))
        if cert.not_valid_before_utc > now:
            problems.append(Problem(cfile, f"not valid before {cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC"))
    return problems
