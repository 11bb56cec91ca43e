"""Mixing analysis pipeline and CLI on synthetic mixing runs.

Reference: in a run whose swapped (randomised) fraction grows as 1 - exp(-k t), every index
must report a smaller T95 when k is larger (the seed's finding that T95 falls as blade speed
rises, Table 4.2), and the Lacey progress, which for a random swap of fraction f equals
1 - (1 - f)^2 (variance of a binary mixture, Lacey 1954), must give gamma = 2 k.
"""

import json

import numpy as np
import pandas as pd
import pytest

from twin_core.dem.frames import Frame, FrameWriter
from twin_core.mixing import GridSpec, MixingConfig
from twin_core.mixing.analysis import analyze, t95_by_speed
from twin_core.mixing.plots import analysis_figure, plot_analysis, plot_t95_by_speed

R = 1e-3


def bed_frame(t, ids, types, radii, pos):
    """A particle frame at rest."""
    return Frame(t, ids, types, radii, pos, np.zeros_like(pos))


def bed():
    a = 2 * np.sqrt(2) * R
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
    n = [6, 14, 10]
    cells = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    pos = (cells[:, None, :] * a + basis[None]).reshape(-1, 3) + R / 2
    return pos, np.array(n) * a


def run(k, seed=0, t_end=12.0, dt=0.2, onset=0.0):
    """A bed whose randomised fraction grows as 1 - exp(-k (t - onset)) after ``onset``."""
    pos0, size = bed()
    n = len(pos0)
    types = (pos0[:, 1] >= size[1] / 2).astype(int)
    rng = np.random.default_rng(seed)
    order = rng.permutation(n)
    frames = []
    for t in np.arange(0, t_end + 1e-9, dt):
        sel = np.sort(order[: int((1 - np.exp(-k * max(t - onset, 0.0))) * n)])
        pos = pos0.copy()
        pos[sel] = pos0[rng.permutation(sel)]
        frames.append(bed_frame(float(t), np.arange(n), types, np.full(n, R), pos))
    grid = GridSpec((0, 0, 0), tuple(size), (1, 8, 8))
    return frames, MixingConfig(grid=grid, box=(size[0], np.inf, np.inf), ah_axis=1, sm_pairs=5000)


@pytest.fixture(scope="module")
def analyses():
    out = {}
    for rpm, k in [(100, 0.6), (50, 0.25)]:
        frames, cfg = run(k)
        out[rpm] = analyze(frames, cfg, "all")
    return out


def test_faster_mixing_gives_smaller_t95_for_every_index(analyses):
    table = t95_by_speed(analyses)
    assert list(table.columns) == ["100 rpm", "50 rpm"]
    fitted = table.dropna()
    assert len(fitted) >= 13, table
    assert np.all(fitted["100 rpm"] < fitted["50 rpm"]), table


def test_lacey_progress_rate_matches_swap_rate(analyses):
    fit = analyses[100].fits["LI"]
    assert fit.gamma == pytest.approx(2 * 0.6, rel=0.15)
    assert fit.r2 > 0.9


def test_onset_fit_beside_eq29_when_mixing_starts_late():
    """Mixing starts at 3 s: the delayed-onset fit finds the onset and the Lacey rate 2 k
    (Lacey variance of a partially randomised bed); its T95 comes earlier than that of Eq. (29)
    fitted from t = 0, which reads the idle start as slow mixing."""
    frames, cfg = run(0.6, t_end=14.0, onset=3.0)
    table = analyze(frames, cfg, "LI,ESI,DM").t95_table()
    assert {"t0_s", "T95_onset_s", "R2_onset"} <= set(table.columns)
    li = table.loc["LI"]
    assert li["t0_s"] == pytest.approx(3.0, abs=0.4)
    assert li["T95_onset_s"] == pytest.approx(3.0 + np.log(20) / 1.2, abs=0.6)
    assert np.all(table["T95_onset_s"] < table["T95_s"]) and np.all(table["R2_onset"] > 0.95)


def test_progress_axis_says_what_one_means(analyses):
    """The default curves are normalised to their own plateau, not to a random mixture."""
    import matplotlib.pyplot as plt

    fig = analysis_figure(analyses[100])
    assert fig.get_supylabel() == "mixing progress (0 initial, 1 own plateau)"
    plt.close(fig)


def test_figures_written(analyses, tmp_path):
    assert plot_analysis(analyses[100], tmp_path / "a.png").stat().st_size > 10_000
    table = t95_by_speed(analyses)
    assert plot_t95_by_speed(table, tmp_path / "b.png").stat().st_size > 5_000


def write_frames(directory, frames, meta):
    with FrameWriter(directory, chunk_frames=8, meta=meta) as w:
        for f in frames:
            w.append(f)
    return directory


def test_cli_compute_on_frames_directory(tmp_path, capsys):
    from services.cli.main import main

    frames, cfg = run(0.6, t_end=6.0, dt=0.3)
    meta = {
        "domain_lo": list(cfg.grid.lo),
        "domain_hi": list(cfg.grid.hi),
        "periodic": [True, False, False],
    }
    write_frames(tmp_path / "frames", frames, meta)
    out = tmp_path / "out"
    rc = main(["mixing", "compute", str(tmp_path / "frames"), "--indices", "LI,RSD,CN,SI",
               "--out", str(out)])  # fmt: skip
    assert rc == 0
    for name in ("indices.csv", "progress.csv", "t95.csv", "mixing_indices.png", "summary.json"):
        assert (out / name).exists()
    text = (out / "t95.csv").read_text()
    assert "LI" in text and "SI" in text and "T95_onset_s" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["domain_source"] == "meta" and summary["dropped_particles"] == 0


def test_cli_compute_drops_lost_particles_and_derives_the_domain(tmp_path, capsys):
    """Particles that left the domain are dropped and counted; frames without a domain are
    sampled over the particle extents, and the output says so."""
    from services.cli.main import main

    frames, _ = run(0.6, t_end=6.0, dt=0.3)
    lost = np.isin(frames[0].ids, [3, 17])
    moving = []
    for k, f in enumerate(frames):
        keep = ~lost if k >= 5 else np.ones(len(f.ids), bool)
        vel = np.zeros_like(f.positions)
        vel[:, 0] = 0.01 * f.positions[:, 2]  # a shear flow, for the velocity field
        moving.append(Frame(f.t, f.ids[keep], f.types[keep], f.radii[keep], f.positions[keep],
                            vel[keep]))  # fmt: skip
    write_frames(tmp_path / "frames", moving, {})
    out = tmp_path / "out"
    rc = main(["mixing", "compute", str(tmp_path / "frames"), "--indices", "LI,ESI,SSI",
               "--bins", "cartesian:1x4x4", "--weight", "volume", "--mapping", "fractional",
               "--min-fill", "0.3", "--homogeneity", "radius,speed", "--out", str(out)])  # fmt: skip
    assert rc == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dropped_particles"] == 2
    assert summary["domain_source"] == "particle extents"
    assert summary["weight"] == "volume" and summary["mapping"] == "fractional"
    printed = capsys.readouterr().out
    assert "2 particles left the domain" in printed and "particle extents" in printed
    mean = pd.read_csv(out / "velocity_mean.csv")
    assert mean["vx_m_s"].to_numpy() == pytest.approx(0.01 * mean["z_m"].to_numpy(), rel=0.2)
    for name in ("velocity.png", "homogeneity.png", "homogeneity.csv", "velocity_frames.csv"):
        assert (out / name).exists()


def test_cli_compute_cylindrical_bins_and_bad_input(tmp_path, capsys):
    from services.cli.main import main

    frames, cfg = run(0.6, t_end=6.0, dt=0.3)
    write_frames(tmp_path / "frames", frames, {"domain_lo": list(cfg.grid.lo),
                                                "domain_hi": list(cfg.grid.hi)})  # fmt: skip
    out = tmp_path / "out"
    rc = main(["mixing", "compute", str(tmp_path / "frames"), "--indices", "LI,DM",
               "--bins", "cylindrical:4x2x3,axis=x", "--out", str(out)])  # fmt: skip
    assert rc == 0
    assert json.loads((out / "summary.json").read_text())["grid"].startswith("cylindrical:4x2x3")
    capsys.readouterr()
    bad = {"--bins": ("spherical:2x2x2", "twin mixing compute: bins must be"),
           "--slice": ("z=0.1", "--slice must look like")}  # fmt: skip
    for flag, (value, message) in bad.items():
        rc = main(["mixing", "compute", str(tmp_path / "frames"), flag, value, "--out", str(out)])
        [line] = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and line.startswith("error: ") and message in line, (rc, line)


def test_uncoloured_run_split_at_the_first_frame():
    """A run whose frames carry no colour: --split y makes the near half (by volume) of the
    first frame's bed the tracer in every frame, so LI starts at its segregated bound."""
    from twin_core.mixing.runs import RunOptions, analyze_run

    frames, cfg = run(0.6, t_end=3.0, dt=0.3)
    plain = [Frame(f.t, f.ids, np.ones(len(f.ids), int), f.radii, f.positions, f.velocities)
             for f in frames]  # fmt: skip
    meta = {"domain_lo": list(cfg.grid.lo), "domain_hi": list(cfg.grid.hi)}
    result = analyze_run(plain, meta, RunOptions(indices="LI", split="y", weight="volume"))
    li = result.analysis.indices["LI"].to_numpy()
    assert abs(li[0]) < 0.05 and li[-1] > 0.5
