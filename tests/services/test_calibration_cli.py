"""`twin calibrate ...` and `twin feeder simulate` end to end (small runs, files written)."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from services.cli import calibrate
from services.cli.main import COMMAND_MODULES


def main(argv: list[str]) -> int:
    """The `twin` entry point restricted to this command group (skips importing the others)."""
    import argparse

    parser = argparse.ArgumentParser(prog="twin")
    calibrate.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


def test_registered_groups():
    import argparse

    assert "calibrate" in COMMAND_MODULES
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    calibrate.register(sub)
    assert {"calibrate", "feeder"} <= set(sub.choices)


def test_design_fit_solve(tmp_path, capsys):
    assert main(["calibrate", "design", "--out", str(tmp_path / "d")]) == 0
    phys = pd.read_csv(tmp_path / "d" / "design_physical.csv")
    assert len(phys) == 21 and (tmp_path / "d" / "correlation_map.png").stat().st_size > 0
    assert (
        main(["calibrate", "fit", "seed:bulk", "--no-figures", "--out", str(tmp_path / "f")]) == 0
    )
    summary = pd.read_csv(tmp_path / "f" / "summary.csv").set_index("response")
    assert summary.loc["shear_angle_deg", "sse"] == pytest.approx(188.135, abs=1e-3)
    assert set(pd.read_csv(tmp_path / "f" / "effect_summary.csv")["response"]) == set(summary.index)
    args = [
        "calibrate",
        "fit",
        "seed:feed_factor",
        "--criterion",
        "p",
        "--responses",
        "FF_max",
        "--predict",
        "seed:verification",
    ]
    assert main(args + ["--out", str(tmp_path / "ff")]) == 0
    pred = pd.read_csv(tmp_path / "ff" / "predictions.csv")
    assert list(pred["run"]) == ["V1", "V2"]
    assert (pred["FF_max:lower"] < pred["FF_max:predicted"]).all()
    assert (tmp_path / "ff" / "parity.png").exists()
    assert (tmp_path / "ff" / "profiler_FF_max.png").exists()
    rc = main(
        [
            "calibrate",
            "solve",
            "--targets",
            "shear_angle_deg=25,max_flowrate_kg_s=0.17",
            "--unknowns",
            "PP_SF,PW_SF",
            "--fixed",
            "PP_RF=0.04",
            "--starts",
            "8",
            "--method",
            "multistart",
            "--contour",
            "PP_SF,PW_SF",
            "--out",
            str(tmp_path / "s"),
        ]
    )
    assert rc == 0
    sol = pd.read_csv(tmp_path / "s" / "solutions.csv")
    assert sol["recommended"].sum() == 1 and sol["exact"].all()
    assert (tmp_path / "s" / "contours.png").exists() and (tmp_path / "s" / "profiles.png").exists()
    out = capsys.readouterr().out
    assert "recommended" in out


def test_fit_bad_table_is_a_clear_error(tmp_path):
    bad = pd.DataFrame({"PP_SF": [0.1, 0.6, 0.35], "y": [1.0, 2.0, 3.0]})
    bad.to_csv(tmp_path / "bad.csv", index=False)
    with pytest.raises(SystemExit, match="lacks factor"):
        main(["calibrate", "fit", str(tmp_path / "bad.csv")])
    with pytest.raises(SystemExit, match="too few runs"):
        main(
            [
                "calibrate",
                "fit",
                str(tmp_path / "bad.csv"),
                "--factors",
                "PP_SF",
                "--terms",
                "PP_SF,PP_SF*PP_SF",
            ]
        )


def test_campaign_cli_with_surrogate(tmp_path):
    assert main(["calibrate", "design", "--factors", "3", "--out", str(tmp_path / "d")]) == 0
    d = pd.read_csv(tmp_path / "d" / "design_physical.csv")
    d.columns = ["run", "PP_SF", "PP_RF", "PW_SF"]
    d = d.assign(
        PP_SF=0.35 + 0.25 * d.PP_SF, PP_RF=0.05 + 0.04 * d.PP_RF, PW_SF=0.35 + 0.25 * d.PW_SF
    )
    d = d.assign(PP_COR=0.4, PW_RF=0.04, PW_COR=0.1, SM=5e6, PR=0.35)
    d.to_csv(tmp_path / "design.csv", index=False)
    rc = main(
        [
            "calibrate",
            "campaign",
            str(tmp_path / "design.csv"),
            "--results",
            str(tmp_path / "r.csv"),
            "--workers",
            "1",
        ]
    )
    assert rc == 0
    assert len(pd.read_csv(tmp_path / "r.csv")) == len(d)


def test_feeder_simulate(tmp_path):
    cfg = tmp_path / "f.yaml"
    cfg.write_text("setpoint_kg_h: 10.0\ninitial_mass_kg: 2.0\n")
    assert (
        main(
            [
                "feeder",
                "simulate",
                str(cfg),
                "--duration",
                "200",
                "--set",
                "flow_noise_rel=0",
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 0
    )
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert len(summary["refills"]) == 1
    assert (tmp_path / "o" / "feeder.png").exists()
    tr = pd.read_csv(tmp_path / "o" / "trace.csv")
    assert {"t_s", "mass_flow_kg_h", "screw_speed_rpm", "hopper_mass_kg", "refilling"} <= set(
        tr.columns
    )
    with pytest.raises(SystemExit, match="unstable"):
        main(["feeder", "simulate", "--set", "kp=5", "--out", str(tmp_path / "x")])


def test_feeder_fit_ff(tmp_path, capsys):
    """Eq. (2) fit from a feeder trace: the configured FF_max/FF_min/beta come back."""
    assert (
        main(
            [
                "feeder",
                "simulate",
                "--duration",
                "600",
                "--set",
                "flow_noise_rel=0,refill_enabled=false",
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 0
    )
    assert (
        main(["feeder", "fit-ff", str(tmp_path / "o" / "trace.csv"), "--out", str(tmp_path / "f")])
        == 0
    )
    fit = json.loads((tmp_path / "f" / "fit.json").read_text())
    assert fit["r2"] > 0.999
    assert fit["beta"] == pytest.approx(0.8, rel=0.05)
    with pytest.raises(SystemExit, match="lacks column"):
        main(["feeder", "fit-ff", str(tmp_path / "o" / "trace.csv"), "--ff-col", "nope"])
