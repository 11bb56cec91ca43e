"""``twin close-loop`` end to end: plant run -> MCAP recording -> report JSON and figures."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from schemas import keys
from schemas.closeloop import CloseLoopReport
from schemas.line import LineConfig, LineSpec
from schemas.messages import FeederFlow, MeasuredConcentration
from twin_core.closeloop.scenarios import effect_spec, standard_scenario
from twin_core.plant import simulate_line

recording = pytest.importorskip("services.recording")
CONFIG = Path(__file__).resolve().parents[2] / "services" / "configs" / "line1.yaml"


def write_line_config(cfg: LineConfig, path: Path) -> None:
    """The line configuration file of a run: line1.yaml's settings with the run's declared line;
    no planned tracers (the recording's tracer events are the source)."""
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(cfg.line_dict(), tracers=[])
    LineSpec.model_validate(data).to_file(path)


def write_mcap(run, path, line="line1"):
    """Record a LineRun as the plant would publish it (reported flows, NIR, events)."""
    with recording.McapRecorder(path) as rec:
        for i, t in enumerate(run.t_s):
            for name, f in run.feeders.items():
                msg = FeederFlow(
                    t=float(t),
                    seq=i,
                    component=f.component,
                    mass_flow_kg_h=float(f.flow_kg_h[i]),
                    screw_speed_rpm=float(f.screw_speed_rpm[i]),
                    hopper_mass_kg=max(float(f.hopper_mass_kg[i]), 0.0),
                    feed_factor_g_rev=float(f.feed_factor_g_rev[i]),
                    refilling=bool(f.refilling[i]),
                )
                rec.write_message(keys.feeder_flow(line, name), msg)
            y = run.measured_pct_w_w[i]
            if math.isfinite(y):
                msg = MeasuredConcentration(
                    t=float(t),
                    seq=i,
                    sensor="nir1",
                    component=run.sensor_component,
                    concentration_pct_w_w=float(y),
                )
                rec.write_message(keys.measured_concentration(line, "nir1"), msg)
        for e in run.events:  # the simulator's events are the wire messages
            rec.write_message(keys.event(line, "plant", e.source), e)


def test_cli_close_loop_writes_report_and_figures(tmp_path):
    """A hidden sensor offset of 0.6 % w/w in a recorded run: the CLI finds it (within 0.05),
    the held-out RMSE drops, the report validates and the figures exist."""
    from services.cli.main import main

    cfg, dist = standard_scenario(900.0)
    run = simulate_line(
        cfg, 900.0, seed=4, effects=[effect_spec("sensor_offset", 1)], disturbances=dist
    )
    mcap = tmp_path / "run.mcap"
    write_mcap(run, mcap)
    conf = tmp_path / "line.yaml"
    write_line_config(cfg, conf)
    out = tmp_path / "report.json"
    figs = tmp_path / "figs"
    rc = main(
        [
            "close-loop",
            str(mcap),
            "--config",
            str(conf),
            "--report",
            str(out),
            "--figures",
            str(figs),
        ]
    )
    assert rc == 0
    rep = CloseLoopReport.model_validate(json.loads(out.read_text()))
    assert rep.status == "explained"
    assert rep.effects[0].name == "sensor_offset"
    assert rep.effects[0].params[0].value == pytest.approx(-0.6, abs=0.05)
    assert rep.errors.after.heldout.rmse < 0.6 * rep.errors.before.heldout.rmse
    assert len(rep.figures) == 3
    for p in rep.figures:
        assert (figs / p.split("/")[-1]).stat().st_size > 10_000
    assert np.isfinite(rep.errors.before.train.mae)


def test_cli_close_loop_estimates_the_noise_on_request(tmp_path):
    """``--noise estimate``: the report says which noise was used (the simulator's seed noise:
    white 0.10 % w/w, found within 15 %) and, with no effect in the run, claims none."""
    from services.cli.main import main

    cfg, dist = standard_scenario(1500.0)
    run = simulate_line(cfg, 1500.0, seed=11, disturbances=dist)
    mcap = tmp_path / "run.mcap"
    write_mcap(run, mcap)
    conf = tmp_path / "line.yaml"
    write_line_config(cfg, conf)
    out = tmp_path / "report.json"
    args = ["close-loop", str(mcap), "--config", str(conf), "--report", str(out)]
    assert main([*args, "--noise", "estimate", "--max-effects", "1"]) == 0
    rep = CloseLoopReport.model_validate(json.loads(out.read_text()))
    assert rep.noise["source"] == "estimated"
    assert rep.noise["white_sd"] == pytest.approx(0.10, rel=0.15)
    assert rep.status == "consistent" and rep.effects == []
    assert main(args) == 0
    assert json.loads(out.read_text())["noise"]["source"] == "declared"


def test_cli_close_loop_rejects_a_file_that_is_not_a_line_config(tmp_path, capsys):
    """One format: a YAML that is not a ``LineSpec`` (here a bare declared line without the
    specification, with a feeder's id misspelt) stops the command with exit code 2 and one line
    naming the fields, before the recording is read."""
    from services.cli.main import main

    cfg, _ = standard_scenario(900.0)
    data = cfg.line_dict()
    data["feeders"][0]["name"] = data["feeders"][0].pop("id")
    conf = tmp_path / "line.json"
    conf.write_text(json.dumps(data))
    args = ["close-loop", str(tmp_path / "absent.mcap"), "--config", str(conf)]
    rc = main([*args, "--report", str(tmp_path / "r.json")])
    assert rc == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("error: ") and "is not a valid line config" in line
    assert "feeders.0.id: Field required" in line and "spec: Field required" in line
