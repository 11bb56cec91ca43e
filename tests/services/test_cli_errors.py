"""One error style for the whole command line: every sub-command given a missing file, a bad
configuration and a bad argument answers one line ``error: <what>, <field/value>`` on stderr,
exit status 2, no traceback, and creates nothing (no folder for an output in a missing one)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from services.cli.main import build_parser, main


def leaf_commands() -> set[str]:
    """Every sub-command of ``twin`` ("rtd analyze", "up", ...)."""
    found: set[str] = set()

    def walk(parser: argparse.ArgumentParser, path: list[str]) -> None:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            found.add(" ".join(path))
            return
        for name, sub in subs[0].choices.items():
            walk(sub, [*path, name])

    walk(build_parser(), [])
    return found


#: per sub-command: its arguments with a missing input file ({missing}), a bad configuration or
#: input ({bad}: a file that is not valid YAML), outputs under {tmp}; the commands without an
#: input file write an output folder (created on purpose): given one under a file instead
CASES: dict[str, tuple[str, str]] = {
    "demo": ("--recording {missing}", "--recording {bad}"),
    "record": ("{tmp}/o.mcap --bus-config {missing}", "{tmp}/o.mcap --bus-config {bad}"),
    "replay": ("{missing}", "{bad}"),
    "inspect": ("{missing}", "{bad}"),
    "recover": ("{missing} {tmp}/o.mcap", "{bad} {tmp}/o.mcap"),
    "schemas export": ("{bad}/s", "{bad}/x/s"),
    "router": ("--bus-config {missing}", "--bus-config {bad}"),
    "up": ("--config {missing}", "--config {bad}"),
    "status": ("--config {missing}", "--config {bad}"),
    "alerts": ("--config {missing}", "--config {bad}"),
    "dashboard": ("--recording {missing}", "--config {bad}"),
    "plant simulate": ("--config {missing} --out {tmp}/o.mcap", "--config {bad} --out {tmp}/o"),
    "rtd analyze": ("{missing} --out {tmp}/o", "{bad} --out {tmp}/o"),
    "rtd funnel": ("{missing} --out {tmp}/o", "{bad} --out {tmp}/o"),
    "rtd lots": ("{missing} --out {tmp}/o", "{bad} --out {tmp}/o"),
    "rtd reproduce": ("--out {bad}/o", "--out {bad}/x/o"),
    "dem run": ("{missing}", "{bad}"),
    "calibrate design": ("--levels {missing} --out {tmp}/o", "--levels {bad} --out {tmp}/o"),
    "calibrate fit": ("{missing}", "{bad}"),
    "calibrate solve": ("--targets {missing}", "--targets {bad}"),
    "calibrate campaign": ("{missing} --results {missing}", "{bad} --results {bad}"),
    "feeder simulate": ("{missing} --out {tmp}/o", "{bad} --out {tmp}/o"),
    "feeder fit-ff": ("{missing}", "{bad}"),
    "mixing compute": ("{missing} --out {tmp}/o", "{bad} --out {tmp}/o"),
    "mixing blender": ("{missing} --runs 1 --out {tmp}/o", "{bad} --runs 1 --out {tmp}/o"),
    "compartment build": ("{missing} --out {tmp}/o", "{bad} --out {tmp}/o"),
    "compartment simulate": ("{missing}", "{bad}"),
    "compartment synthetic": ("{nodir}/o", "{bad}/o"),
    "close-loop": (
        "{missing} --config {missing} --report {tmp}/r.json",
        "{missing} --config {bad} --report {tmp}/r.json",
    ),
    "bridge opcua": ("--config {missing} --line {missing}", "--config {bad} --line {bad}"),
    "plant-opcua": ("{missing}", "{bad}"),
    "import": (
        "{missing} --config {missing} --out {tmp}/o.mcap",
        "{tmp} --config {bad} --out {tmp}/o.mcap",
    ),
    "trace": ("{missing} --lot api-L0001", "{missing} --config {bad} --at 10"),
    "batch report": ("{missing} --out {tmp}/o", "{missing} --config {bad} --out {tmp}/o"),
    "audit verify": ("{missing} --key {missing}", "{missing} --config {bad}"),
    "audit export": ("{missing} --out {tmp}/t.csv", "{missing} --out {nodir}/t.csv"),
}


def run(argv: list[str], capsys) -> tuple[int, str]:
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse
        rc = exc.code
    return rc, capsys.readouterr().err


def check_one_line(rc: int, err: str) -> str:
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    return lines[0]


#: sub-commands that read no input file (a bad argument is their only bad input)
NO_INPUT = {"dem warmup"}


def test_every_sub_command_has_its_cases():
    assert set(CASES) | NO_INPUT == leaf_commands()


@pytest.mark.parametrize("command", sorted(NO_INPUT))
def test_a_bad_argument_to_a_command_without_input_is_a_one_line_error(command, capsys):
    line = check_one_line(*run([*command.split(), "--no-such-option"], capsys))
    assert "--no-such-option" in line


@pytest.mark.parametrize("command", sorted(CASES))
def test_missing_file_bad_config_and_bad_argument_are_one_line_errors(command, tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    fill = {
        "missing": str(tmp_path / "absent.file"),
        "bad": str(bad),
        "tmp": str(tmp_path),
        "nodir": str(tmp_path / "no" / "such"),
    }
    before = sorted(p.name for p in tmp_path.iterdir())
    for case in CASES[command]:
        argv = [*command.split(), *case.format(**fill).split()]
        check_one_line(*run(argv, capsys))
    first = CASES[command][0].format(**fill).split()
    line = check_one_line(*run([*command.split(), *first, "--no-such-option"], capsys))
    assert "--no-such-option" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing created


def test_an_effect_with_unknown_keys_is_refused(tmp_path, capsys):
    out = tmp_path / "o.mcap"
    argv = ["plant", "simulate", "--out", str(out), "--duration", "10"]
    line = check_one_line(*run([*argv, "--effect", '{"name":"extra_delay","delay_s":10}'], capsys))
    assert "--effect keys must be among" in line and "delay_s" in line
    line = check_one_line(*run([*argv, "--effect", '{"name":"nosuch"}'], capsys))
    assert "nosuch" in line
    assert not out.exists()


def test_an_output_in_a_missing_folder_is_refused_before_any_work(tmp_path, capsys):
    """`compartment build` used to compute before finding its output folder missing."""
    fields = tmp_path / "fields.npz"
    fields.write_bytes(b"")
    out = tmp_path / "no" / "model.json"
    line = check_one_line(*run(["compartment", "build", str(fields), "--out", str(out)], capsys))
    assert "the output's folder does not exist" in line and not out.parent.exists()


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["--address", "0.0.0.0"], "--address is not a loopback address"),
        (["--port", "0"], "--port must be in 1..65535, got 0"),
        (["--speed", "nan"], "--speed must be a finite number > 0, got nan"),
        (["--max-points", "3"], "--max-points must be >= 10, got 3"),
    ],
)
def test_dashboard_refuses_a_public_address_and_bad_numbers(argv, named, capsys):
    """The page has no login: a non-loopback address needs --allow-remote."""
    line = check_one_line(*run(["dashboard", *argv], capsys))
    assert named in line


def test_dashboard_refuses_a_recording_of_another_line(capsys):
    """The bundled recording ran the line at 5 % API; the default configuration is the 10 % line:
    its limits would frame the wrong target."""
    rec = Path(__file__).resolve().parents[2] / "recordings" / "line1_30min.mcap"
    line = check_one_line(*run(["dashboard", "--recording", str(rec)], capsys))
    assert "does not match the line configuration" in line
    assert "feeders.api.setpoint_kg_h" in line
