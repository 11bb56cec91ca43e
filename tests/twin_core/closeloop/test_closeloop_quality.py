"""Data quality before the fit (twin_core.closeloop.quality) and the ``data_quality`` status.

Validated against injected faults of known kind and interval on runs of the plant simulator
(``twin_core.plant.simulate_line``, the standard scenario with the seed's NIR noise: white +
1/f + proportional + isolated outliers). Each detection threshold is set so that the seed's own
noise trips it with probability < ``false_alarm`` = 1e-3 per series and kind over a record
(quality module docstring), so a clean record of this test is flagged with probability < 2 %
(18 series x kind checks); the runs use fixed seeds. ``benchmarks/closeloop_quality.py``
measures the rates on 2-hour windows.
"""

from __future__ import annotations

import numpy as np
import pytest

from twin_core.closeloop import RunData, close_loop
from twin_core.closeloop.data import StreamStamps
from twin_core.closeloop.quality import (
    QualityOptions,
    burst_threshold,
    check_data_quality,
    stamp_flags,
)
from twin_core.closeloop.scenarios import standard_scenario
from twin_core.plant import LineModel, simulate_line

DURATION = 1500.0


def _clean(seed: int, noise_scale: float = 1.0) -> tuple[LineModel, RunData]:
    cfg, dist = standard_scenario(DURATION)
    if noise_scale != 1.0:
        n = cfg.sensor.noise
        cfg.sensor.noise = n.model_copy(
            update={
                "white_sd": n.white_sd * noise_scale,
                "pink_sd": n.pink_sd * noise_scale,
                "proportional_rel": n.proportional_rel * noise_scale,
            }
        )
    run = simulate_line(cfg, DURATION, seed=seed, disturbances=dist)
    return LineModel(cfg), RunData.from_line_run(run)


@pytest.fixture(scope="module")
def clean():
    return _clean(7)


def _kinds(q, series):
    return [f.kind for f in q.flags if f.series == series]


@pytest.mark.parametrize("seed,scale", [(1, 1.0), (2, 2.0), (3, 1.0), (4, 2.0)])
def test_clean_records_give_no_flags(seed, scale):
    """The seed's noise at 1x and 2x, refills, flow dips and tracer pulses: nothing flagged."""
    model, data = _clean(seed, scale)
    q = check_data_quality(data, model)
    assert q.flags == [] and not q.exclude.any()


def test_a_stuck_probe_of_30_s_is_found_and_left_out(clean):
    model, data = clean
    y = data.measured.copy()
    a = 700
    y[a : a + 30] = y[a]
    bad = RunData(data.t_s, y, data.inputs, data.events)
    q = check_data_quality(bad, model)
    assert _kinds(q, "nir") == ["stuck"]
    f = q.flags[0]
    assert f.t_start_s == data.t_s[a] and f.t_end_s == data.t_s[a + 29] and f.n_samples == 30
    assert q.exclude[a : a + 30].all() and q.exclude.sum() == 30


def test_a_stuck_feeder_flow_is_found_and_its_reach_left_out(clean):
    """A feeder flow frozen for 30 s: flagged on that feeder, and the outlet samples it reaches
    (until the blender's t(F = 0.995) after its end) are left out."""
    model, data = clean
    flows = {k: v.copy() for k, v in data.inputs.flows_kg_h.items()}
    a = 600
    flows["api"][a : a + 30] = flows["api"][a]
    inp = data.inputs
    bad_inp = type(inp)(inp.t_s, flows, inp.components, inp.refilling, inp.tracers)
    q = check_data_quality(RunData(data.t_s, data.measured, bad_inp, data.events), model)
    assert _kinds(q, "api:flow") == ["stuck"]
    assert q.exclude[a : a + 30].all() and not q.exclude[:a].any()
    assert q.exclude.sum() > 30


def test_clipping_and_spike_burst_and_gap_are_told_apart(clean):
    model, data = clean
    y = data.measured.copy()
    top = float(np.nanmax(y)) + 1.0
    y[300:306] = top
    y[900:908:2] += 6.0
    y[1200:1206] = np.nan
    q = check_data_quality(RunData(data.t_s, y, data.inputs, data.events), model)
    assert sorted(_kinds(q, "nir")) == ["clipping", "gap", "spike_burst"]
    by = {f.kind: f for f in q.flags}
    assert by["clipping"].n_samples == 6 and by["gap"].n_samples == 6
    burst = by["spike_burst"]
    assert burst.t_start_s == data.t_s[900] and burst.t_end_s == data.t_s[906]
    assert 4 <= burst.n_samples <= 7  # the 4 spikes (a sample between them may join them)


def test_isolated_outliers_are_noise_not_a_burst():
    """The seed's isolated spikes (outlier_prob 0.003) never make a burst: the burst size is
    the smallest count the background rate makes improbable (binomial tail < 1e-3 / n)."""
    k = burst_threshold(10, 0.003, 7200, 1e-3)
    assert k == 4
    from scipy import stats

    assert stats.binom.sf(k - 1, 10, 0.003) < 1e-3 / 7200 <= stats.binom.sf(k - 2, 10, 0.003)


def test_stamps_duplicates_time_jumps_and_dropouts():
    """A repeated stamp, a clock jump (sequence numbers advance by one) and a dropout (they
    skip) are told apart; stamps going backwards are a time jump."""
    t = np.arange(0.0, 100.0)
    seq = np.arange(100)
    t_dup = np.insert(t, 10, t[10])
    s_dup = np.insert(seq, 10, seq[10])
    assert [f.kind for f in stamp_flags("nir", StreamStamps(t_dup, s_dup), 1.0)] == [
        "duplicate_stamp"
    ]
    t_jump = np.where(t >= 50, t + 20.0, t)
    assert [f.kind for f in stamp_flags("nir", StreamStamps(t_jump, seq), 1.0)] == ["time_jump"]
    keep = (t < 50) | (t >= 60)
    drop = stamp_flags("nir", StreamStamps(t[keep], seq[keep]), 1.0)
    assert [(f.kind, f.n_samples) for f in drop] == [("gap", 10)]
    back = np.where(t >= 50, t - 5.0, t)
    assert "time_jump" in [f.kind for f in stamp_flags("nir", StreamStamps(back, seq), 1.0)]


def test_options_are_checked():
    with pytest.raises(ValueError, match="min_stuck_samples"):
        QualityOptions(min_stuck_samples=1)


def test_a_record_whose_only_fault_is_flagged_gets_data_quality_status(clean):
    """A stuck probe (60 s at a reading 1 % w/w off) on a record without an undeclared effect:
    left out, no effect claimed, status ``data_quality`` (without the check the stuck stretch
    is residual beyond the noise)."""
    model, data = clean
    y = data.measured.copy()
    y[500:560] = y[500] + 1.0
    res = close_loop(RunData(data.t_s, y, data.inputs, data.events), model)
    rep = res.to_dict()
    assert res.status == "data_quality" and rep["effects"] == []
    assert [f["kind"] for f in rep["data_quality"]] == ["stuck"]
    assert rep["decision"]["samples_left_out"] == 60


def test_a_clock_jump_leaves_the_rest_out_and_the_part_before_is_still_checked(clean):
    """A PLC clock reset half-way through the NIR stamps (sequence numbers advance by one while
    the stamps jump 20 s): everything after it is misaligned and left out, so the held-out
    window of the usual split would be empty; the windows are laid over the usable part and
    the record gets ``data_quality``, no effect claimed (before: a ValueError, no report)."""
    model, data = clean
    jump = data.t_s.size // 2
    t_stamps = np.where(np.arange(data.t_s.size) >= jump, data.t_s + 20.0, data.t_s)
    stamps = {"nir": StreamStamps(t_stamps, np.arange(data.t_s.size))}
    res = close_loop(
        RunData(data.t_s, data.measured, data.inputs, data.events, "jump", stamps), model
    )
    rep = res.to_dict()
    assert [f["kind"] for f in rep["data_quality"]] == ["time_jump"]
    assert res.status == "data_quality" and rep["effects"] == []
    assert rep["decision"]["samples_left_out"] >= data.t_s.size - jump


def test_a_dense_spike_burst_is_found_by_the_longer_scan_windows(clean):
    """A burst in which 40 % of 60 s carry spikes of 1.5-4.5 % w/w: its own spikes inflate the
    Hampel scale, so only some are outliers and no 10-sample window holds the count a burst
    needs; the 30- and 100-sample windows of the scan still see the cluster (before: not
    flagged, the record ``unexplained``)."""
    model, data = clean
    y = data.measured.copy()
    rng = np.random.default_rng(5)
    hit = 700 + np.flatnonzero(rng.random(60) < 0.4)
    y[hit] += rng.choice([-1.0, 1.0], hit.size) * 3.0 * rng.uniform(0.5, 1.5, hit.size)
    rd = RunData(data.t_s, y, data.inputs, data.events)
    q = check_data_quality(rd, model)
    bursts = [f for f in q.flags if f.kind == "spike_burst"]
    assert len(bursts) == 1 and 690 <= bursts[0].t_start_s and bursts[0].t_end_s <= 770
    res = close_loop(rd, model)
    assert res.status == "data_quality" and res.to_dict()["effects"] == []


def test_clipping_at_the_range_leaves_out_the_censored_stretch(clean):
    """A probe whose range ends inside the noise band of the reading (clipped at the 90th
    percentile of the record: the tracer peaks and the high set points): the readings that escape the clip there are the low tail of their distribution,
    so only leaving out the whole stretch near the clip level (running median within 3 noise
    SD) keeps a level out of the residual; the flags are few merged stretches, not one per
    clipped sample, and the status is ``data_quality`` with no effect."""
    model, data = clean
    y = data.measured.copy()
    level = float(np.percentile(y, 90))
    y = np.minimum(y, level)
    rd = RunData(data.t_s, y, data.inputs, data.events)
    q = check_data_quality(rd, model)
    clips = [f for f in q.flags if f.kind == "clipping"]
    n_clipped = int(np.sum(y == level))
    assert clips and len(clips) <= n_clipped / 10
    assert sum(f.n_samples for f in clips) == n_clipped
    res = close_loop(rd, model)
    assert res.status == "data_quality" and res.to_dict()["effects"] == []


def test_a_feeder_dropout_does_not_cut_the_record_and_is_a_gap_not_stuck():
    """One feeder's messages lost for 240 s (``twin_core.plant.faults``, applied on the bus
    messages): the record still runs to its end (before: every tick after the gap waited for
    the missing feeder and 25 % of the record was lost without a word), the dropout is one
    ``gap`` flag, and the held-over value is not called ``stuck``."""
    from twin_core.closeloop.record import LineRecord
    from twin_core.plant.faults import DataFault, apply_faults
    from twin_core.plant.messages import run_messages

    cfg, dist = standard_scenario(DURATION)
    run = simulate_line(cfg, DURATION, seed=3, disturbances=dist)
    msgs, _ = apply_faults(
        run_messages(run, cfg), [DataFault("gap", "excipient", t_s=900.0, duration_s=240.0)], cfg
    )
    sensor = cfg.sensor
    rec = LineRecord.from_messages(msgs, cfg.components, sensor.sample_period_s, sensor.component)
    data = rec.run_data("dropout")
    assert data.t_s[-1] >= DURATION - 2.0
    q = check_data_quality(data, LineModel(cfg))
    assert [(f.kind, f.series) for f in q.flags] == [("gap", "excipient:flow")]
    assert q.flags[0].n_samples == 240


def test_a_stuck_screw_speed_is_flagged_but_its_hold_after_a_refill_is_not():
    """The API screw speed frozen for 180 s (``twin_core.plant.faults`` on the bus messages of
    the open-world scenario, where the feeders refill with the load cell frozen): flagged
    ``stuck`` on ``api:screw_speed``; the excipient's speed, held from each refill until its
    feeder is back in gravimetric mode (10-20 s after the refill flag drops), is not (before
    the refill rule: two false ``stuck`` flags per record)."""
    from twin_core.closeloop.record import LineRecord
    from twin_core.plant.openworld_cases import FAULT_CASES, Case, Setting, run_case

    cr = run_case(Case("fault", "api_screw_stuck", faults=FAULT_CASES["api_screw_stuck"]),
                  Setting(False, 1.0), 400000)  # fmt: skip
    cfg = cr.run.config
    s = cfg.sensor
    data = LineRecord.from_messages(
        cr.messages, cfg.components, s.sample_period_s, s.component
    ).run_data("screw")
    q = check_data_quality(data, LineModel(cfg))
    assert [(f.kind, f.series, f.n_samples) for f in q.flags] == [("stuck", "api:screw_speed", 180)]
