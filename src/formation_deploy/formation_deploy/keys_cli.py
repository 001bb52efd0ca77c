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
lines that select it, after checking that process's certificate and key for the run (signed by
the CA, valid now and until the run's expected end, key mode 0600: exit 2 naming the file
otherwise); ``sim.sh``, ``agent.sh``, ``record.sh`` and ``replay.sh --secure`` use it.

Exit status: 0 valid, 1 a check failed, 2 invalid input (file, directory).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from formation_core.errors import FormationSpecError
from formation_deploy.keys import (
    CA_NAME,
    DEFAULT_DAYS,
    EXIT_FAILED,
    EXIT_INVALID,
    EXIT_OK,
    KeysError,
    check_keys,
    init_keys,
    key_path,
    process_names,
)
from formation_deploy.secure_transport import (
    DEFAULT_PORT_BASE,
    check_run_keys,
    exports,
    peers_of,
    write_process_config,
)


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
    profile.add_argument(
        "--duration",
        type=float,
        help="the run's simulated duration [s] (default: the formation file's): the process's certificate "
        "must stay valid for the run's expected wall time",
    )
    return p


def _profile(args: argparse.Namespace, agent_ids: Sequence[str], duration_s: float) -> str:
    import yaml

    # before anything starts: a certificate refused later is a TLS handshake failure seen only in logs
    check_run_keys(args.dir, [args.name], duration_s)
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
    from formation_core.spec import load_formation  # numpy: not for --help

    try:
        spec = load_formation(args.formation)
        agent_ids = spec.agent_ids
        names = process_names(agent_ids)
        if args.command == "profile":
            duration = spec.simulation.duration if args.duration is None else args.duration
            print(_profile(args, agent_ids, duration), end="")
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
