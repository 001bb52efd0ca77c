"""formation-keys: the CA and one key pair per process, their modes, checks and expiry."""

from __future__ import annotations

import datetime as dt
import stat
from pathlib import Path

import pytest

from formation_deploy.keys import (
    EXIT_FAILED,
    EXIT_INVALID,
    EXIT_OK,
    KeysError,
    check_keys,
    init_keys,
    process_names,
)
from formation_deploy.keys_cli import main

PAPER = Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml"
NAMES = ["simulator", "agent_1", "recorder"]


def test_process_names_cover_every_process_of_a_run() -> None:
    """The simulator, one name per agent in file order, the recorder and the replay."""
    assert process_names(["1", "7"]) == ["simulator", "agent_1", "agent_7", "recorder", "replay"]


def test_init_writes_private_keys_readable_by_their_owner_only(tmp_path: Path) -> None:
    """Every .key file is mode 0600; the certificates check clean against the CA."""
    keys = tmp_path / "keys"
    init_keys(keys, NAMES)
    assert sorted(p.name for p in keys.iterdir()) == sorted(
        ["ca.pem", "ca.key", *(f"{n}.pem" for n in NAMES), *(f"{n}.key" for n in NAMES)]
    )
    for key in keys.glob("*.key"):
        assert stat.S_IMODE(key.stat().st_mode) == 0o600, key
    assert check_keys(keys, NAMES) == []


def test_init_never_overwrites(tmp_path: Path) -> None:
    """A non-empty directory is refused, naming it (rotation goes to a new directory)."""
    init_keys(tmp_path / "k", NAMES)
    with pytest.raises(KeysError, match="not empty"):
        init_keys(tmp_path / "k", NAMES)


def test_check_finds_a_certificate_of_another_ca(tmp_path: Path) -> None:
    """A certificate copied in from another CA's directory is reported as not signed by this CA."""
    init_keys(tmp_path / "a", NAMES)
    init_keys(tmp_path / "b", NAMES)
    for suffix in ("pem", "key"):
        (tmp_path / "a" / f"agent_1.{suffix}").write_bytes((tmp_path / "b" / f"agent_1.{suffix}").read_bytes())
    messages = [str(p) for p in check_keys(tmp_path / "a", NAMES)]
    assert messages == [f"{tmp_path / 'a' / 'agent_1.pem'}: not signed by this directory's CA (ca.pem)"]


def test_check_finds_loose_modes_mismatched_keys_and_missing_files(tmp_path: Path) -> None:
    """Mode 0644 on a key, a key of another process, and a missing certificate: one problem each."""
    keys = tmp_path / "k"
    init_keys(keys, NAMES)
    (keys / "recorder.key").chmod(0o644)
    (keys / "simulator.key").chmod(0o600)
    (keys / "simulator.key").write_bytes((keys / "agent_1.key").read_bytes())
    (keys / "agent_1.pem").unlink()
    messages = sorted(str(p) for p in check_keys(keys, NAMES))
    assert messages == sorted(
        [
            f"{keys / 'recorder.key'}: private key readable by others (mode 0644, expected 0600)",
            f"{keys / 'simulator.key'}: does not match simulator.pem",
            f"{keys / 'agent_1.pem'}: missing",
        ]
    )


def test_check_reports_expiry(tmp_path: Path) -> None:
    """Certificates of 10 days: fine 2 days in with --min-days 7, 'expires in' at day 5, 'expired' at day 11."""
    keys = tmp_path / "k"
    issued = dt.datetime(2026, 1, 1, tzinfo=dt.UTC)
    init_keys(keys, ["simulator"], days=10, now=issued)
    assert check_keys(keys, ["simulator"], now=issued + dt.timedelta(days=2)) == []
    soon = check_keys(keys, ["simulator"], now=issued + dt.timedelta(days=5))
    assert len(soon) == 2 and all("expires in 5.0 days (< 7)" in str(p) for p in soon)  # CA and simulator
    late = check_keys(keys, ["simulator"], now=issued + dt.timedelta(days=11))
    assert len(late) == 2 and all("expired on 2026-01-11" in str(p) for p in late)


def test_cli_init_check_and_exit_codes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """formation-keys init then check exit 0; a tampered key exits 1; a bad formation file exits 2."""
    keys = tmp_path / "k"
    assert main(["init", str(keys), "--formation", str(PAPER)]) == EXIT_OK
    assert (keys / "agent_5.pem").is_file() and (keys / "replay.key").is_file()
    assert main(["check", str(keys), "--formation", str(PAPER)]) == EXIT_OK
    (keys / "agent_5.key").chmod(0o640)
    assert main(["check", str(keys), "--formation", str(PAPER)]) == EXIT_FAILED
    assert "agent_5.key: private key readable by others" in capsys.readouterr().err
    assert main(["check", str(keys), "--formation", str(tmp_path / "nope.yaml")]) == EXIT_INVALID
