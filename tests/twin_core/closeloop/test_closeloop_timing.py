"""Timing faults of the plant's messages (``twin_core.plant.faults.TIMING_KINDS``) through the
record (``twin_core.closeloop.record.LineRecord``) and the data-quality check
(``twin_core.closeloop.quality``).

The faults are injected into the bus messages of the open-world scenario by the plant side (a
refill flag a sample off its held load-cell value, a source's clock seconds off, stamp jitter,
irregular sampling, missing and re-sent ticks); the readings themselves are right, so an
effect-free record must stay free of data-quality flags (its status ``consistent``), with every
repair named per source, and a clock offset estimated with its interval instead of being left
to the identification as a delay.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from twin_core.closeloop.quality import check_data_quality
from twin_core.closeloop.record import LineRecord
from twin_core.plant import LineModel
from twin_core.plant.faults import DataFault, apply_faults
from twin_core.plant.openworld_cases import Case, Setting, run_case

#: an hour of the open-world scenario: the API feeder refills at ~1750 s, API set-point steps
DURATION = 3600.0


@pytest.fixture(scope="module")
def base():
    cr = run_case(Case("none", "none"), Setting(True, 1.0), 100001, DURATION)
    return cr.run.config, cr.messages


def _record(cfg, msgs):
    s = cfg.sensor
    return LineRecord.from_messages(msgs, cfg.components, s.sample_period_s, s.component)


def _check(cfg, msgs):
    data = _record(cfg, msgs).run_data("timing")
    return data, check_data_quality(data, LineModel(cfg))


def _whole(kind, stream, field="flow", size=0.0, fraction=0.3, seed=0):
    return DataFault(
        kind, stream, field, duration_s=math.inf, size=size, fraction=fraction, seed=seed
    )


def test_the_aligned_record_is_clean(base):
    cfg, msgs = base
    data, q = _check(cfg, msgs)
    assert q.flags == [] and not q.exclude.any()
    assert data.inputs.refilling["api"].any()


@pytest.mark.parametrize("feeder", ["api", "excipient"])
@pytest.mark.parametrize("k", [-3, -1, 1, 2, 3])
def test_a_refill_flag_off_its_held_value_by_1_to_3_samples_is_the_refill(base, feeder, k):
    """The feeder reports its load-cell flow held over each refill (``refill_hold``) and the
    refill flag is ``k`` samples off the held value: the hold touches the refill within the
    plausible skew, so it is the refill's, not a stuck sensor; nothing is left out (before:
    ``stuck`` on the excipient flow at its refill, with the blender's reach after it left
    out), and a note says what was seen and where."""
    cfg, msgs = base
    faults = [DataFault("refill_hold", feeder), _whole("shift", feeder, "refilling", size=k)]
    bad, _ = apply_faults(msgs, faults, cfg)
    data, q = _check(cfg, bad)
    assert q.flags == [], [f.to_dict() for f in q.flags]
    assert not q.exclude.any()
    notes = [n for n in q.notes if n.kind == "refill_hold" and n.series == f"{feeder}:flow"]
    if feeder == "excipient":  # the API's refills last 2 s: too short a hold to be stuck
        assert notes and all("refill" in n.detail and "sample" in n.detail for n in notes)


def test_a_stuck_flow_beyond_the_skew_of_a_refill_is_still_stuck(base):
    """The API flow frozen from the refill's end for 60 s more: stuck, and the flag says
    where and what it saw."""
    cfg, msgs = base
    data0, _ = _check(cfg, msgs)
    r = data0.inputs.refilling["api"]
    end = float(data0.t_s[np.flatnonzero(r)[-1]])
    bad, _ = apply_faults(msgs, [DataFault("stuck", "api", t_s=end - 20.0, duration_s=80.0)], cfg)
    _, q = _check(cfg, bad)
    stuck = [f for f in q.flags if f.kind == "stuck" and f.series == "api:flow"]
    assert len(stuck) == 1 and stuck[0].t_end_s >= end + 55.0
    assert "identical" in stuck[0].detail and "api:flow" in stuck[0].to_dict()["series"]


@pytest.mark.parametrize("stream,offset", [("nir", 3.4), ("nir", -4.0), ("api", 2.0)])
def test_a_clock_offset_is_estimated_with_its_interval_and_corrected(base, stream, offset):
    """A source's clock off by seconds, its messages arriving when they did: the offset is
    estimated from the arrival order against the other sources (interval covering the truth,
    point within half a sample), reported, and the record put on the common clock (the NIR on
    its ticks as without the fault), with no data-quality flag."""
    cfg, msgs = base
    bad, _ = apply_faults(msgs, [_whole("clock_offset", stream, size=offset)], cfg)
    data, q = _check(cfg, bad)
    assert q.flags == []
    series = "nir" if stream == "nir" else f"{stream}:flow"
    est = {c.series: c for c in data.clock_offsets}
    assert set(est) == {series}
    c = est[series]
    assert c.low_s <= offset <= c.high_s and abs(c.offset_s - offset) <= 1.0 + 1e-9
    assert c.high_s - c.low_s <= 1.5
    assert any(n.kind == "clock_offset" and n.series == series for n in q.notes)
    ref = _record(cfg, msgs).run_data("aligned")
    common, ia, ib = np.intersect1d(ref.t_s, data.t_s, return_indices=True)
    assert common.size > 0.99 * ref.t_s.size
    a, b = ref.measured[ia], data.measured[ib]
    ok = np.isfinite(a) & np.isfinite(b)
    if stream == "nir":
        assert np.mean(a[ok] == b[ok]) > 0.99


@pytest.mark.parametrize("stream", ["nir", "api"])
def test_a_clock_that_jumps_is_a_time_jump_not_an_offset(base, stream):
    """A source's clock set back by 600 s half-way (``time_jump``): flagged as before, no
    clock offset put on the whole record (the median over its messages would be ~ -300 s)."""
    cfg, msgs = base
    bad, _ = apply_faults(msgs, [DataFault("time_jump", stream, t_s=1800.0, size=-600.0)], cfg)
    data, q = _check(cfg, bad)
    assert data.clock_offsets == []
    assert "time_jump" in [f.kind for f in q.flags]


@pytest.mark.parametrize("stream", ["nir", "api", "excipient"])
def test_stamp_jitter_of_half_a_sample_is_no_fault(base, stream):
    """Stamps jittered by up to half a sample period: no time jump, gap or stuck flag (before:
    a 'time_jump' wherever two stamps were more than 1.5 periods apart, and every later
    sample left out); the jitter is noted for its source."""
    cfg, msgs = base
    bad, _ = apply_faults(msgs, [_whole("jitter", stream, size=0.5, seed=3)], cfg)
    data, q = _check(cfg, bad)
    assert q.flags == [], [f.to_dict() for f in q.flags]
    assert not q.exclude.any()
    series = "nir" if stream == "nir" else f"{stream}:flow"
    assert [n.kind for n in q.notes if n.series == series] == ["jitter"]


@pytest.mark.parametrize("stream", ["nir", "api"])
def test_irregular_sampling_is_put_on_the_grid_and_noted(base, stream):
    """Sampling intervals of 0.5-1.5 periods: no flag, the readings on the tick grid with
    at most a few ticks without one, and the irregular sampling noted for its source."""
    cfg, msgs = base
    bad, _ = apply_faults(msgs, [_whole("irregular", stream, fraction=0.5, seed=4)], cfg)
    data, q = _check(cfg, bad)
    assert q.flags == [], [f.to_dict() for f in q.flags]
    series = "nir" if stream == "nir" else f"{stream}:flow"
    assert [n.kind for n in q.notes if n.series == series] == ["irregular_sampling"]
    assert np.isfinite(data.measured).mean() > 0.75


@pytest.mark.parametrize("stream", ["nir", "api", "excipient"])
def test_missing_ticks_are_repaired_and_marked_per_source(base, stream):
    """5 % of one source's ticks lost (isolated): no flag, each source's missing ticks counted
    in one note (held for a flow, left empty for the NIR)."""
    cfg, msgs = base
    bad, truth = apply_faults(msgs, [_whole("drop_ticks", stream, fraction=0.05, seed=5)], cfg)
    _, q = _check(cfg, bad)
    assert q.flags == []
    series = "nir" if stream == "nir" else f"{stream}:flow"
    notes = [n for n in q.notes if n.series == series]
    assert [n.kind for n in notes] == ["missing_tick"]
    assert notes[0].n_samples == truth[0]["n_samples"]


@pytest.mark.parametrize("stream", ["nir", "api"])
def test_re_sent_ticks_are_dropped_and_marked_per_source(base, stream):
    """5 % of one source's messages delivered twice (same stamp, sequence number and values):
    the copies dropped and counted in a note, no ``duplicate_stamp`` flag (before: flagged,
    status ``data_quality``)."""
    cfg, msgs = base
    bad, truth = apply_faults(msgs, [_whole("duplicate_ticks", stream, fraction=0.05, seed=6)], cfg)
    _, q = _check(cfg, bad)
    assert q.flags == []
    series = "nir" if stream == "nir" else f"{stream}:flow"
    notes = [n for n in q.notes if n.series == series]
    assert [n.kind for n in notes] == ["duplicate_tick"]
    assert notes[0].n_samples == truth[0]["n_samples"] and notes[0].action == "repaired"
