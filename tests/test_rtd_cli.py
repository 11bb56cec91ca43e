"""`twin rtd` command line: analyze, funnel, lots, reproduce."""

import json

import numpy as np
import pandas as pd
import pytest

from services.cli.main import main
from twin_core.rtd.synthetic import generate_campaign


@pytest.fixture(scope="module")
def run_csv(tmp_path_factory):
    run = generate_campaign(3)[0]
    p = tmp_path_factory.mktemp("rtd") / "run.csv"
    pd.DataFrame({"time [s]": run.t, "concentration [% w/w]": run.c}).to_csv(p, index=False)
    return p, run


def test_analyze_writes_report_and_figure(run_csv, tmp_path, capsys):
    """analyze with outliers + auto denoise + PAT truncation + AD fit: the JSON report holds
    the fit, whose CI covers the run's true Pe-independent delay within 2 s (seed workflow)."""
    path, run = run_csv
    out = tmp_path / "a"
    rc = main(
        [
            "rtd",
            "analyze",
            str(path),
            "--outliers",
            "--denoise",
            "auto",
            "--truncate",
            "pat:3",
            "--fit",
            "ad_open",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["outliers"]["count"] >= len(run.outlier_indices) - 1
    assert rep["fits"][0]["model"] == "ad_open"
    assert abs(rep["fits"][0]["params"]["tau_d"] - run.params["tau_d"]) < 2.0
    assert rep["noise"]["sigma_total"] > 0
    assert (out / "profile.png").stat().st_size > 1000


def test_funnel_and_lots(run_csv, tmp_path, capsys):
    """funnel writes JSON/CSV/PNG; lots prints boundaries and the diversion window."""
    path, _ = run_csv
    out = tmp_path / "f"
    assert (
        main(
            ["rtd", "funnel", str(path), "--limit", "5", "--denoise", "wavelet", "--out", str(out)]
        )
        == 0
    )
    f = json.loads((out / "funnel.json").read_text())
    assert 0 < f["funnels"]["run"]["feasible_fraction"] < 1
    assert (out / "funnel.png").exists() and (out / "funnel.csv").exists()
    out2 = tmp_path / "f2"
    assert main(["rtd", "funnel", str(path), "--compare", str(path), "--out", str(out2)]) == 0
    c = json.loads((out2 / "funnel.json").read_text())["comparison"]
    assert c["cells_changed"] == 0 and (out2 / "funnel_difference.png").exists()
    capsys.readouterr()
    assert main(["rtd", "lots", str(path), "--disturbance", "100", "130"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["t_lo_s"] < res["t_hi_s"]
    assert res["diversion_window_s"][0] == pytest.approx(100 + res["t_lo_s"])


def test_cli_errors(tmp_path, capsys):
    """Bad files and options return exit code 2 with a message naming the problem."""
    bad = tmp_path / "bad.csv"
    bad.write_text("time [s],concentration [% w/w]\n" + "\n".join(f"{i},{1}" for i in range(5)))
    assert main(["rtd", "lots", str(bad)]) == 2
    assert "at least 10 points" in capsys.readouterr().err
    good = tmp_path / "good.csv"
    good.write_text(
        "time [s],concentration [% w/w]\n" + "\n".join(f"{i},{np.exp(-i / 5)}" for i in range(30))
    )
    assert (
        main(["rtd", "analyze", str(good), "--truncate", "bogus", "--out", str(tmp_path / "x")])
        == 2
    )
    assert "kind:value" in capsys.readouterr().err
    assert (
        main(["rtd", "funnel", str(good), "--durations", "1:2", "--out", str(tmp_path / "y")]) == 2
    )


def test_reproduce(tmp_path):
    """reproduce writes the Table 6.1/6.2 and Fig. 6.16/6.17 CSV + PNG; the untruncated AD fits
    of the 10 g runs land near the Table 6.2 parameters the campaign was drawn from."""
    out = tmp_path / "r"
    assert main(["rtd", "reproduce", "--out", str(out), "--seed", "1", "--repeats", "2"]) == 0
    for name in (
        "table_6_1.csv",
        "table_6_2.csv",
        "fig_6_16.png",
        "fig_6_17.csv",
        "fig_6_17.png",
        "lots.csv",
    ):
        assert (out / name).exists(), name
    t2 = pd.read_csv(out / "table_6_2.csv")
    row = t2[t2.level == "0"].iloc[0]
    assert row.tau_d_mean == pytest.approx(11.92, abs=1.5)
    assert row.pe_mean == pytest.approx(7.67, abs=1.0)
    t1 = pd.read_csv(out / "table_6_1.csv")
    assert {"SA", "WT", "SV", "FFT", "Original"} <= set(t1.method)
