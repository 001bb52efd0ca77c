"""Driver of the secure-mode outsider test, run inside a private network namespace (``unshare -n``,
only a loopback: nothing can leave the machine).

    python secure_driver.py WORKDIR DOMAIN_ID

Creates the run's keys and another CA's, starts ``formation-launch --secure --keys`` (realtime
preset, 8 s: long enough for the outsiders, started with it, to join under load) and four
outsiders on the same domain, aimed at the run's ports: ``plain`` (default UDP/shared-memory
transports), ``nocert`` (TLS without a certificate), ``otherca`` (a certificate of another CA)
and, as the control, ``member`` (a certificate of the run's own CA, publishing a harmless
stamp-0 wrench). Prints one JSON line: the launcher's exit status and each outsider's report.

A launch still running after :data:`LAUNCH_TIMEOUT` s is reported as ``"launch": null`` with
``"hung"``, its processes still running then; their native stacks are kept in WORKDIR/stacks/ and,
stopped by SIGABRT, each writes its Python stacks to its log (PYTHONFAULTHANDLER) before the
launcher's process group is stopped.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

from formation_core.spec import load_formation
from formation_deploy.keys import init_keys, process_names
from formation_deploy.secure_transport import (
    Peer,
    peers_of,
    profile_xml,
    secure_environment,
    single_host_port_start,
    write_process_config,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: bin_helpers
from bin_helpers import executable
from process_hygiene import live_descendants
from ros_helpers import stacks

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
REALTIME = REPO / "config" / "realtime_5agents_100hz.yaml"
CERT_LINES = ("<cert_chain_file>", "<private_key_file>")
#: wall s the 8 s run may take: discovery (35 s at most), the run and its lag budget (60 s), stopping
LAUNCH_TIMEOUT = 240.0


def outsider_env(
    base: dict[str, str], kind: str, work: Path, run_keys: Path, other_keys: Path, peers
) -> dict[str, str]:
    if kind == "plain":
        env = dict(base, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
        return env
    me = Peer("replay", "127.0.0.1", max(p.port for p in peers.values()) + 10 + len(kind))
    if kind == "member":  # the run's CA, and it verifies like a member
        additions = write_process_config("replay", {**peers, "replay": me}, run_keys, work / kind)
        return secure_environment(base, additions)
    xml = profile_xml(me, peers, other_keys)
    xml = xml.replace(
        "<verify>VERIFY_PEER</verify><verify>VERIFY_FAIL_IF_NO_PEER_CERT</verify>", "<verify>VERIFY_NONE</verify>"
    )
    if kind == "nocert":
        xml = "\n".join(line for line in xml.splitlines() if not line.strip().startswith(CERT_LINES))
    (work / kind).mkdir(parents=True)
    profile = work / kind / "profile.xml"
    profile.write_text(xml)
    env = secure_environment(
        base, {"FASTRTPS_DEFAULT_PROFILES_FILE": str(profile), "ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT"}
    )
    return env  # no OPENSSL_CONF: an attacker verifies nothing


def main() -> None:
    work, domain = Path(sys.argv[1]), int(sys.argv[2])
    spec = load_formation(REALTIME)
    run_keys, other_keys = work / "keys", work / "other_ca"
    init_keys(run_keys, process_names(spec.agent_ids))
    init_keys(other_keys, process_names(spec.agent_ids))
    base = dict(
        os.environ,
        ROS_DOMAIN_ID=str(domain),
        PYTHONUNBUFFERED="1",
        PYTHONFAULTHANDLER="1",
        ROS_LOG_DIR=str(work / "roslog"),
    )
    base.pop("FASTDDS_BUILTIN_TRANSPORTS", None)
    # the launcher's ports: in a fresh namespace the first block it looks at is free
    peers = peers_of(spec.agent_ids, port_base=single_host_port_start(domain))
    launch_log = open(work / "launch.log", "wb")
    launch = subprocess.Popen(
        [
            executable("formation-launch"),
            str(REALTIME),
            "--secure",
            "--keys",
            str(run_keys),
            "--duration",
            "8",
            "--physics-rate",
            "100",
            # who sees and commands the run is the point here, not its timing: at a 1-minute load of 20
            # the default 1 s lag budget ended the run INCOMPLETE (exit 4) after 0.5 s
            "--lag-budget",
            "60",
            "--no-record",
            "--no-plots",
            "--quiet",
            "--out",
            str(work / "out"),
        ],
        env=base,
        stdout=launch_log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    stop = work / "stop"
    outsiders = {}
    for kind, force, stamp in (
        ("plain", 50.0, 1_000_000),
        ("nocert", 50.0, 1_000_000),
        ("otherca", 50.0, 1_000_000),
        ("member", 0.0, 0),
    ):
        env = outsider_env(base, kind, work / "outsiders", run_keys, other_keys, peers)
        outsiders[kind] = subprocess.Popen(
            [sys.executable, str(HERE / "secure_outsider.py"), f"outsider_{kind}", str(stop), str(force), str(stamp)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=open(work / f"outsider_{kind}.log", "wb"),
            text=True,
            start_new_session=True,
        )
    hung: dict[str, str] = {}
    try:
        try:
            code: int | None = launch.wait(timeout=LAUNCH_TIMEOUT)
        except subprocess.TimeoutExpired:
            code, hung = None, stop_hung(launch, work / "stacks")
    finally:
        stop.touch()
        reports = {}
        for kind, proc in outsiders.items():
            try:
                out, _ = proc.communicate(timeout=30)
                reports[kind] = json.loads(out.strip().splitlines()[-1]) if out.strip() else None
            except subprocess.TimeoutExpired:
                proc.kill()
                reports[kind] = None
        if launch.poll() is None:
            launch.kill()
    print(json.dumps({"launch": code, "outsiders": reports, **({"hung": hung} if hung else {})}), flush=True)


def stop_hung(launch: subprocess.Popen, dest: Path) -> dict[str, str]:
    """The launch and its processes, still running: {pid: command line}; their native stacks into
    ``dest``, then SIGABRT to each (Python stacks into its log) and to the launcher's group."""
    hung = {launch.pid: " ".join(map(str, launch.args)), **live_descendants(launch.pid)}
    dest.mkdir(parents=True, exist_ok=True)
    for pid in hung:
        (dest / f"{pid}.txt").write_text(stacks(pid))
    for pid in hung:
        try:
            os.kill(pid, signal.SIGABRT)
        except ProcessLookupError:
            pass
    try:
        launch.wait(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(launch.pid, signal.SIGKILL)
        launch.wait()
    return {str(pid): cmd[:160] for pid, cmd in hung.items()}


if __name__ == "__main__":
    main()
