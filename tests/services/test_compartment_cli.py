"""`twin compartment build / simulate / synthetic` end to end on a small synthetic field."""

import json

import numpy as np
import pytest

from schemas.blender_model import BlenderModel
from services.cli.main import main


def test_cli_build_and_simulate(tmp_path, capsys):
    fields = tmp_path / "f.npz"
    assert main(["compartment", "synthetic", str(fields), "--shape", "5", "7", "7"]) == 0
    capsys.readouterr()
    model = tmp_path / "m.json"
    figs = tmp_path / "figs"
    rc = main(
        [
            "compartment",
            "build",
            str(fields),
            "--out",
            str(model),
            "--figures",
            str(figs),
            "--sections",
            "4",
            "--rpm",
            "100",
            "--rpm-run",
            "50",
            str(fields),
            "--surrogate",
            "2000",
        ]
    )
    assert rc == 0
    report = json.loads(capsys.readouterr().out)
    assert report["raw_imbalance_max_rel"] < 1e-10
    assert report["seed_imbalance_max_rel"] > 0.1
    assert report["rtd_validation"]["against"] == "random-walk surrogate"
    bm = BlenderModel.load(model)
    assert bm.n_sections == 4 and bm.k_b_per_s is not None and bm.k_b_per_s > 0
    assert bm.rpm_flow_scale == [(50.0, pytest.approx(1.0))]  # same fields at "50 rpm"
    for name in ("zone_maps", "compartment_maps", "network_graph", "rtd_comparison", "rsd"):
        assert (figs / f"{name}.png").stat().st_size > 1000
    # DEM transit times given as an npz with 'transit_s'
    tt = tmp_path / "transit.npz"
    np.savez(tt, transit_s=np.random.default_rng(0).gamma(4.0, bm.mean_residence_time_s / 16, 50))
    assert (
        main(
            [
                "compartment",
                "build",
                str(fields),
                "--out",
                str(model),
                "--transit-times",
                str(tt),
                "--rsd-source",
                "compartments",
            ]
        )
        == 0
    )
    assert json.loads(capsys.readouterr().out)["rtd_validation"]["against"] == "DEM transit times"
    tw = tmp_path / "transit_w.npz"  # the recording window stored with the transit times
    np.savez(tw, transit_s=np.load(tt)["transit_s"], window_s=20.0)
    assert (
        main(
            [
                "compartment",
                "build",
                str(fields),
                "--out",
                str(model),
                "--transit-times",
                str(tw),
                "--rsd-source",
                "compartments",
            ]
        )
        == 0
    )
    rv = json.loads(capsys.readouterr().out)["rtd_validation"]
    assert rv["against"].startswith("DEM transit times (window 20")
    assert rv["model_mean"] < bm.mean_residence_time_s / 4  # censoring shortens the law

    csv = tmp_path / "s.csv"
    rc = main(
        [
            "compartment",
            "simulate",
            str(model),
            "--duration",
            "200",
            "--dt",
            "0.1",
            "--pulse-at",
            "10",
            "--scale-at",
            "100",
            "--scale-to",
            "0.5",
            "--out",
            str(csv),
            "--figures",
            str(figs),
        ]
    )
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["points"] == 2000
    data = np.loadtxt(csv, delimiter=",", skiprows=1)
    assert data.shape == (2000, 3)
    assert data[:, 2].max() > 3.0 + 1e-3  # the pulse reaches the outlet
    assert (figs / "simulation.png").exists()


def test_cli_bad_input(tmp_path, capsys):
    assert (
        main(
            ["compartment", "build", str(tmp_path / "none.npz"), "--out", str(tmp_path / "m.json")]
        )
        == 2
    )
    assert "does not exist" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    np.savez(bad, x_edges=np.arange(3.0))
    assert main(["compartment", "build", str(bad), "--out", str(tmp_path / "m.json")]) == 2
    assert "missing key" in capsys.readouterr().err


def test_cli_simulate_bad_input(tmp_path, capsys):
    assert main(["compartment", "simulate", str(tmp_path / "none.json")]) == 2
    assert "does not exist" in capsys.readouterr().err
    fields, model = tmp_path / "f.npz", tmp_path / "m.json"
    assert main(["compartment", "synthetic", str(fields), "--shape", "4", "5", "5"]) == 0
    assert (
        main(
            [
                "compartment",
                "build",
                str(fields),
                "--out",
                str(model),
                "--surrogate",
                "0",
                "--rsd-source",
                "compartments",
            ]
        )
        == 0
    )
    assert main(["compartment", "simulate", str(model), "--step-at", "5"]) == 2
    assert "step_at needs step_to" in capsys.readouterr().err
    assert main(["compartment", "simulate", str(model), "--dt", "0"]) == 2
    assert main(["compartment", "simulate", str(model), "--scale-at", "1", "--rpm-to", "50"]) == 2
    assert "needs rpm_basis" in capsys.readouterr().err
    assert main(["compartment"]) == 2
