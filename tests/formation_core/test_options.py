"""Run options: declared once, every bad rate, duration, timeout or seed is exit 2 with one line."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from bin_helpers import executable

from formation_core import options
from formation_core.options import OPTIONS, RunOptions

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "config" / "paper_5agents.yaml"

NUMERIC = [o for o in OPTIONS if o.kind in (options.positive, options.nonnegative, options.seed, options.byte_count)]
BAD = {
    options.positive: ["0", "-1", "nan", "inf", "-inf", "1e400", "abc"],
    options.nonnegative: ["-1", "nan", "inf", "abc"],
    options.seed: ["-1", "1.5", "nan", "abc"],
    options.byte_count: ["0", "-1", "1.5", "1e9", "abc"],
}


def _parser(command: str):
    return options.build_parser(command, f"formation-{command}", "test")


@pytest.mark.parametrize(
    ("command", "flag", "value"),
    [(c, o.flag, v) for o in NUMERIC for c in sorted(o.commands) for v in BAD[o.kind]],
)
def test_bad_numeric_option_exits_2_with_one_line(command, flag, value, capsys) -> None:
    """Every command refuses a non-finite, zero, negative or non-numeric value before reading the file."""
    with pytest.raises(SystemExit) as exc:
        options.parse(command, _parser(command), [str(PAPER), f"{flag}={value}"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith(f"formation-{command}: error: argument {flag}: {value!r}"), err


def test_good_options_become_a_frozen_run_options() -> None:
    """Values are typed; overrides name the simulation keys; the object is immutable."""
    opts = options.parse(
        options.SIM, _parser(options.SIM), [str(PAPER), "--control-rate", "1e3", "--seed", "7", "--settle", "0"]
    )
    assert opts.control_rate == 1000.0 and opts.seed == 7 and opts.settle == 0.0
    assert opts.overrides() == {"control_rate": 1000.0, "seed": 7}
    with pytest.raises(AttributeError):
        opts.seed = 3  # type: ignore[misc]


def test_max_bag_size_goes_to_the_simulator_only_when_given() -> None:
    """formation-launch --max-bag-size BYTES is passed on to formation-sim; without it the bag is one file."""
    parse = lambda *argv: options.parse(options.LAUNCH, _parser(options.LAUNCH), [str(PAPER), *argv])  # noqa: E731
    assert parse().max_bag_size is None and "--max-bag-size" not in parse().child_argv(options.SIM)
    argv = parse("--max-bag-size", "50000000").child_argv(options.SIM)
    assert argv[argv.index("--max-bag-size") + 1] == "50000000"


def test_scheduling_is_normal_unless_batch_is_asked_and_nothing_else(capsys) -> None:
    """formation-launch --scheduling: normal by default (batch halves a run's speed on a busy machine),
    batch on request, any other word exit 2."""
    parse = lambda *argv: options.parse(options.LAUNCH, _parser(options.LAUNCH), [str(PAPER), *argv])  # noqa: E731
    assert parse().scheduling == "normal"
    assert parse("--scheduling", "batch").scheduling == "batch"
    assert "--scheduling" not in parse("--scheduling", "batch").child_argv(options.SIM)  # the launcher's only
    with pytest.raises(SystemExit) as exc:
        parse("--scheduling", "fifo")
    assert exc.value.code == 2
    assert "argument --scheduling: invalid choice: 'fifo'" in capsys.readouterr().err


def test_launch_passes_its_options_to_the_simulator_unchanged() -> None:
    """formation-launch's child command line parses, in formation-sim, to the same values."""
    argv = [str(PAPER), "--mode", "realtime", "--control-rate", "100", "--duration", "0.1", "--seed", "3",
            "--command-timeout", "0.2", "--ground-truth-rate", "50", "--measurement-qos", "best-effort",
            "--allow-low-rate", "--no-plots", "--no-record", "--netns", "off"]  # fmt: skip
    launch = options.parse(options.LAUNCH, _parser(options.LAUNCH), argv)
    sim = options.parse(options.SIM, _parser(options.SIM), [str(PAPER), *launch.child_argv(options.SIM)])
    for o in OPTIONS:
        if o.forward and options.SIM in o.commands and options.LAUNCH in o.commands:
            assert getattr(sim, o.dest) == getattr(launch, o.dest), o.flag
    assert sim.measurement_qos == "best-effort" and sim.allow_low_rate and sim.no_plots and sim.mode == "realtime"


def test_every_run_options_field_is_declared_or_internal() -> None:
    """One declaration: RunOptions has a field for each option and nothing else but command/file/schema."""
    import dataclasses

    fields = {f.name for f in dataclasses.fields(RunOptions)}
    assert fields - {o.dest for o in OPTIONS} == {"command", "file", "schema"}
    assert {o.dest for o in OPTIONS} <= fields


@pytest.mark.parametrize(
    ("script", "extra"),
    [
        ("formation-check", ["--control-rate", "0"]),
        ("formation-check", ["--control-rate", "nan"]),
        ("formation-headless", ["--control-rate", "0"]),
        ("formation-headless", ["--duration", "nan"]),
        ("formation-headless", ["--seed", "-1"]),
        ("formation-sim", ["--control-rate", "inf"]),
        ("formation-launch", ["--duration", "-5"]),
        ("formation-launch", ["--step-timeout", "0"]),
    ],
)
def test_console_scripts_refuse_bad_options_without_traceback(script, extra, tmp_path) -> None:
    """The installed commands: exit 2, one line naming the option, no traceback, nothing written."""
    out = [] if script == "formation-check" else ["--out", str(tmp_path / "o")]
    r = subprocess.run(
        [executable(script), str(PAPER), *extra, *out],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr + r.stdout
    assert r.stderr.count("\n") == 1 and f"argument {extra[0]}" in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()


def test_run_sh_refuses_a_nan_control_rate() -> None:
    """ros2_ws/run.sh (formation-launch): exit 2 and one line, nothing started."""
    r = subprocess.run(
        [str(REPO / "ros2_ws" / "run.sh"), "--control-rate", "nan"], capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "argument --control-rate: 'nan' is not finite" in r.stderr


@pytest.mark.parametrize(
    ("script", "extra", "message"),
    [
        ("formation-sim", ["--measurement-qos", "best-effort"], "is for realtime runs only"),
        ("formation-launch", ["--measurement-qos", "best-effort"], "is for realtime runs only"),
        ("formation-headless", ["--control-rate", "1000"], "control rate too low"),
        ("formation-headless", [], "exists and is not empty"),
    ],
)
def test_preflight_refuses_what_cannot_run(script, extra, message, tmp_path) -> None:
    """The one pre-flight of every runner: QoS that cannot work, a rate below the need, a non-empty OUT."""
    out = tmp_path / "o"
    if message.startswith("exists"):
        out.mkdir()
        (out / "keep.txt").write_text("x")
    r = subprocess.run(
        [executable(script), str(PAPER), "--out", str(out), *extra], capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert "Traceback" not in r.stderr + r.stdout


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("simple", options.Discovery()),
        ("server", options.Discovery("server")),
        ("server:10.0.0.5:11811", options.Discovery("server", "10.0.0.5", 11811)),
        ("server:sim:7000", options.Discovery("server", "sim", 7000)),
    ],
)
def test_discovery_values(text: str, expected: options.Discovery) -> None:
    """--discovery takes simple, server and server:HOST:PORT; its text form reads back the same."""
    parsed = options.discovery(text)
    assert parsed == expected
    if parsed.port is not None:
        assert options.discovery(str(parsed)) == parsed
        assert parsed.address() == text.removeprefix("server:")


@pytest.mark.parametrize("text", ["multicast", "server:", "server:host", "server::11811", "server:h:0", "server:h:x"])
def test_bad_discovery_is_exit_2_naming_the_value(text: str, capsys: pytest.CaptureFixture[str]) -> None:
    """A --discovery value that is none of the three forms ends formation-launch with exit 2, naming it."""
    with pytest.raises(SystemExit) as exc:
        options.parse(options.LAUNCH, _parser(options.LAUNCH), [str(PAPER), "--discovery", text])
    assert exc.value.code == 2
    assert repr(text) in capsys.readouterr().err


def test_server_without_port_uses_fast_dds_default_outside_the_launcher() -> None:
    """A server given without a port is reached on Fast DDS's default port 11811 (the launcher picks its own)."""
    assert options.Discovery("server").address() == "127.0.0.1:11811"
    assert str(options.Discovery()) == "simple"
