"""`twin dem run` end to end on a tiny silo: results, STL, frames, figures, resume; `twin dem
warmup`."""

from __future__ import annotations

import json
import logging

import numba
import pytest
import yaml

from services.cli.main import main
from twin_core.dem.frames import FrameReader
from twin_core.dem.stl import read_stl
from twin_core.dem.warmup import compile_kernels, kernel_cache_counts

pytestmark = pytest.mark.slow


def test_cli_runs_scene_and_resumes(tmp_path):
    """The CLI writes the outputs it documents, and --resume on a finished run does no extra
    simulated time (same end time and frame count); --pair-chunks re-chunks a resumed run and is
    a one-line error without --resume or below 1."""
    cfg = {
        "scene": "silo",
        "name": "tiny",
        "radius": 0.002,
        "silo_radius": 0.02,
        "silo_height": 0.08,
        "orifice_diameter": 0.016,
        "n_particles": 200,
        "settle_s": 0.1,
        "discharge_s": 0.1,
        "material": {"shear_modulus": 1.0e6},
        "output": {"checkpoint_interval_s": 0.1, "vtk": True},
    }
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "out"
    n = numba.get_num_threads()
    try:
        assert (
            main(["dem", "run", str(path), "--out", str(out), "--threads", "1", "--no-progress"])
            == 0
        )
        summary = json.loads((out / "summary.json").read_text())
        assert summary["silo"]["scene"] == "silo"
        for f in ("results.json", "flow_rate.png", "snapshot_end.png", "geometry_wall.stl"):
            assert (out / f).exists(), f
        v, t = read_stl(out / "geometry_bottom.stl")
        assert len(t) > 0
        n_frames = len(FrameReader(out / "frames"))
        assert (out / "vtk" / "particles.pvd").exists()
        assert main(["dem", "run", str(path), "--out", str(out), "--resume", "--no-progress"]) == 0
        assert len(FrameReader(out / "frames")) == n_frames
        resume = ["dem", "run", str(path), "--out", str(out), "--resume", "--no-progress"]
        assert main([*resume, "--pair-chunks", "1"]) == 0
        assert main([*resume, "--pair-chunks", "0"]) == 2
        assert main([*resume, "--pair-chunks", "two"]) == 2
        assert main(["dem", "run", str(path), "--out", str(out), "--pair-chunks", "2"]) == 2
        bad = tmp_path / "bad.yaml"
        bad.write_text(yaml.safe_dump({"scene": "silo", "radius": -1}))
        assert main(["dem", "run", str(bad), "--out", str(out)]) == 2
    finally:
        numba.set_num_threads(n)


def test_cli_warmup_names_each_kernel_phase_before_compiling(capsys, caplog):
    """`twin dem warmup` logs what it compiles before each phase (a cold cache otherwise stalls
    the first step silently) and prints the seconds per phase; once done, running the phases
    again compiles nothing."""
    caplog.set_level(logging.INFO)
    assert main(["dem", "warmup"]) == 0
    phases = list(json.loads(capsys.readouterr().out)["phases_s"])
    assert len(phases) == 5
    starts = [r.getMessage() for r in caplog.records if r.getMessage().endswith(" ...")]
    assert [m.split(": ", 1)[1].removesuffix(" ...") for m in starts] == phases
    compiled = kernel_cache_counts()[1]
    compile_kernels()
    assert kernel_cache_counts()[1] == compiled
