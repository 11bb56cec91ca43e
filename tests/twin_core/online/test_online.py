"""Tests of twin_core.online: streaming convolution, OOS tracking, funnel flag, tracer detection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twin_core.online import (
    FunnelFlagger,
    HysteresisTracker,
    InletAligner,
    StreamingConvolver,
    TracerPulseDetector,
)
from twin_core.online.inlet import composition_pct
from twin_core.quality.funnel import funnel_gain


def ad_open(t: np.ndarray, tau_d: float, tau: float, pe: float) -> np.ndarray:
    """Axial dispersion E(t) with delay (seed Eq. (7) of 6.2 in the standard form, docs/seed.md)."""
    s = np.asarray(t, float) - tau_d
    out = np.zeros_like(s)
    m = s > 0
    out[m] = np.sqrt(pe / (4 * np.pi * s[m] * tau)) * np.exp(
        -pe * (tau - s[m]) ** 2 / (4 * tau * s[m])
    )
    return out


DT = 0.5
T_E = np.arange(0, 150, DT)
E_SEED = ad_open(T_E, 11.92, 16.37, 7.67)  # Table 6.2 of the seed


# ---------------------------------------------------------------- streaming convolution
def test_streaming_matches_numpy_convolve_sample_by_sample_and_blocks():
    """Reference: numpy.convolve (batch) of the same inlet and kernel, Eq. (1) of the module."""
    rng = np.random.default_rng(1)
    u = rng.normal(10, 1, 3000)
    ref = DT * np.convolve(u, E_SEED)[: u.size]
    sc = StreamingConvolver(E_SEED, DT)
    y1 = np.array([sc.push(x) for x in u])
    np.testing.assert_allclose(y1, ref, rtol=1e-12, atol=1e-12)
    sc2 = StreamingConvolver(E_SEED, DT)
    parts, i = [], 0
    while i < u.size:
        n = int(rng.integers(1, 400))
        parts.append(sc2.push_many(u[i : i + n]))
        i += n
    np.testing.assert_allclose(np.concatenate(parts), ref, rtol=1e-12, atol=1e-12)
    assert sc.n_ == sc2.n_ == u.size


def test_streaming_amend_corrects_a_past_input():
    """Reference: numpy.convolve of the corrected inlet. Amending the input ``lag`` samples back
    gives the outputs of the corrected stream from then on; in both halves of the ring buffer
    (across wraps)."""
    rng = np.random.default_rng(4)
    u = rng.normal(10, 1, 1500)
    sc = StreamingConvolver(E_SEED, DT)
    fixed = u.copy()
    out = []
    for i, x in enumerate(u):
        out.append(sc.push(x))
        if i % 97 == 50:
            lag = int(rng.integers(0, min(i + 1, E_SEED.size)))
            fixed[i - lag] += 3.0
            sc.amend(lag, 3.0)
    ref = DT * np.convolve(fixed, E_SEED)[: u.size]
    after = np.arange(u.size) > 50 + 97 * ((u.size - 51) // 97)  # after the last amendment
    np.testing.assert_allclose(np.array(out)[after], ref[after], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sc.history(), fixed[-E_SEED.size :], rtol=0, atol=0)
    with pytest.raises(ValueError, match="lag must be in"):
        sc.amend(E_SEED.size, 1.0)


def test_streaming_steady_initial_and_normalisation():
    """A steady inlet predicts itself with a unit-gain kernel (mass conservation of an RTD)."""
    u0 = 10.0
    rng = np.random.default_rng(2)
    u = u0 + rng.normal(0, 0.5, 500)
    sc = StreamingConvolver(E_SEED, DT, initial=u0)
    y = sc.push_many(u)
    x = np.concatenate([np.full(E_SEED.size - 1, u0), u])
    np.testing.assert_allclose(y, DT * np.convolve(x, E_SEED, mode="valid"), rtol=1e-12)
    sn = StreamingConvolver(E_SEED, DT, initial=u0, normalize=True)
    assert sn.gain_ == 1.0
    assert sn.push(u0) == pytest.approx(u0, rel=1e-12)


def test_streaming_cstr_step_response_analytic():
    """Analytic: a CSTR, E = exp(-t/tau)/tau, answers a unit step with 1 - exp(-t/tau)."""
    tau, dt = 20.0, 0.05
    t = np.arange(0, 150, dt)
    e = np.exp(-t / tau) / tau
    sc = StreamingConvolver(e, dt)
    y = sc.push_many(np.ones(t.size))
    np.testing.assert_allclose(y, 1 - np.exp(-t / tau), atol=2 * dt / tau)


def test_streaming_kernel_swap_and_state_roundtrip():
    """After set_kernel the output is the new kernel applied to the true past inputs (numpy)."""
    rng = np.random.default_rng(3)
    u = rng.normal(5, 1, 1200)
    e2 = ad_open(T_E, 8.0, 20.0, 12.0)
    sc = StreamingConvolver(E_SEED, DT)
    sc.push_many(u[:700])
    sc.set_kernel(e2)
    y = np.array([sc.push(x) for x in u[700:]])
    ref = DT * np.convolve(u, e2)[: u.size]
    np.testing.assert_allclose(y, ref[700:], rtol=1e-12)
    # save / restore mid-stream reproduces the uninterrupted stream
    a = StreamingConvolver(E_SEED, DT, initial=5.0)
    a.push_many(u[:333])
    b = StreamingConvolver.from_state(a.to_state())
    np.testing.assert_allclose(b.push_many(u[333:]), a.push_many(u[333:]), rtol=1e-14)


def test_streaming_rejects_bad_input():
    with pytest.raises(ValueError, match="dt"):
        StreamingConvolver(E_SEED, 0.0)
    with pytest.raises(ValueError, match="e must"):
        StreamingConvolver(np.array([]), 1.0)
    sc = StreamingConvolver(E_SEED, DT)
    with pytest.raises(ValueError, match="u must be finite"):
        sc.push(float("nan"))


# ---------------------------------------------------------------- hysteresis tracker
def batch_episodes(t, v, lo, hi, hyst, n_on, n_off):
    """Offline reference: scan the whole series with the same rules, return (start, end) pairs."""
    out_mask = (v < lo) | (v > hi)
    in_mask = (v >= lo + hyst) & (v <= hi - hyst)
    eps, i, n = [], 0, len(v)
    while i < n:
        if out_mask[i : i + n_on].size == n_on and out_mask[i : i + n_on].all():
            start, last, j, run = i, i + n_on - 1, i + n_on, 0
            while j < n:
                if out_mask[j]:
                    last, run = j, 0
                elif in_mask[j]:
                    run += 1
                    if run >= n_off:
                        break
                else:
                    run = 0
                j += 1
            eps.append((t[start], t[last]))
            i = j + 1
        else:
            i += 1
    return eps


def test_tracker_matches_offline_scan_and_has_stable_unique_ids():
    """Reference: an independent offline scan; every episode found once, none missed."""
    rng = np.random.default_rng(4)
    t = np.arange(20000) * DT
    v = 10 + np.cumsum(rng.normal(0, 0.05, t.size)) * 0.2 + rng.normal(0, 0.2, t.size)
    v = 10 + (v - 10) % 1.6 - 0.8  # keep it wandering around the limits
    args = (9.5, 10.5, 0.05, 3, 4)
    ref = batch_episodes(t, v, *args)
    tr = HysteresisTracker(*args, prefix="x")
    opened, closed, t_close = [], [], []
    for ti, vi in zip(t, v):
        for ev in tr.push(ti, vi):
            (opened if ev.kind == "open" else closed).append(ev.episode)
            if ev.kind == "close":
                t_close.append(ev.t)
    closed += [ev.episode for ev in tr.flush()]
    assert len(ref) > 20
    assert [(e.t_start, e.t_end) for e in closed] == ref
    assert [e.id for e in opened] == [e.id for e in closed]
    assert len({e.id for e in closed}) == len(closed)
    # restart from a saved state mid-stream: same ids, same windows
    tr2 = HysteresisTracker(*args, prefix="x")
    half = t.size // 2
    for ti, vi in zip(t[:half], v[:half]):
        tr2.push(ti, vi)
    tr3 = HysteresisTracker.from_state(tr2.to_state())
    got = []
    for ti, vi in zip(t[half:], v[half:]):
        got += [ev.episode.id for ev in tr3.push(ti, vi) if ev.kind == "close"]
    got += [ev.episode.id for ev in tr3.flush()]
    expected = [e.id for e, tc in zip(closed, t_close + [t[-1]]) if tc >= t[half]]
    assert len(expected) > 5 and got == expected


def test_tracker_debounce_and_deadband():
    """A single-sample spike is ignored with n_on=2; chatter inside the deadband stays one episode."""
    tr = HysteresisTracker(9.0, 11.0, hysteresis=0.2, n_on=2, n_off=2, prefix="p")
    seq = [10, 12, 10, 10, 12, 12, 10.9, 11.1, 10.9, 10.0, 10.0, 10.0]
    evs = [ev for i, x in enumerate(seq) for ev in tr.push(float(i), x)]
    assert [(e.kind, e.episode.t_start, e.episode.t_end) for e in evs] == [
        ("open", 4.0, 5.0),
        ("close", 4.0, 7.0),
    ]
    assert evs[0].episode.id == "p-000000004000"
    assert evs[0].episode.peak_value == 12


def test_tracker_rejects_bad_arguments():
    with pytest.raises(ValueError, match="upper must be > lower"):
        HysteresisTracker(2.0, 1.0)
    with pytest.raises(ValueError, match="n_on"):
        HysteresisTracker(1.0, 2.0, n_on=0)
    tr = HysteresisTracker(1.0, 2.0)
    tr.push(1.0, 1.5)
    with pytest.raises(ValueError, match="t must increase"):
        tr.push(1.0, 1.5)


# ---------------------------------------------------------------- funnel
def quantile_window(e, dt, lower=0.005, upper=0.995):
    f = np.cumsum(e) * dt / (np.sum(e) * dt)
    t_lo = np.searchsorted(f, lower) * dt
    t_hi = np.searchsorted(f, upper) * dt
    return lambda a, b: (a + t_lo, b + t_hi)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_funnel_flag_iff_outlet_exceeds_and_before_it(sign):
    """Funnel plot (seed ch. 6, Engisch & Muzzio 2016): a rectangular feeder deviation (d, h)
    puts the outlet out of spec iff it lies outside the feasible region; checked against the
    batch convolution of each pulse with E(t), and the flag comes before the outlet exceedance."""
    target, lim = 10.0, 0.5  # +/- 5 % relative
    g = funnel_gain(E_SEED, DT)
    win = quantile_window(E_SEED, DT)
    n_flag = n_case = 0
    for m in (2, 6, 10, 16, 24, 40, 80, 200):
        for h in (0.02, 0.05, 0.08, 0.12, 0.2, 0.4, 0.8):
            n_case += 1
            u = np.full(900, target)
            s0 = 100
            u[s0 : s0 + m] = target * (1 + sign * h)
            y = target + DT * np.convolve(u - target, E_SEED)[: u.size]
            exceeds = bool(np.any(np.abs(y - target) > lim))
            ff = FunnelFlagger(target, target - lim, target + lim, g, DT, win, detect=0.1)
            evs = [ev for i, x in enumerate(u) for ev in ff.push(i * DT, x)]
            flags = [ev for ev in evs if ev.kind == "flag"]
            assert bool(flags) == exceeds, (m, h)
            if exceeds:
                n_flag += 1
                first_out = np.argmax(np.abs(y - target) > lim) * DT
                assert flags[0].t < first_out
                closes = [ev for ev in evs if ev.kind == "close"]
                assert len(flags) == 1 and len(closes) == 1
                c = closes[0]
                assert c.t_in_start == s0 * DT and c.t_in_end == (s0 + m - 1) * DT
                assert (c.t_out_start, c.t_out_end) == win(s0 * DT, (s0 + m - 1) * DT)
                # the whole outlet excursion lies inside the traced window
                out_idx = np.nonzero(np.abs(y - target) > lim)[0] * DT
                assert c.t_out_start <= out_idx[0] and out_idx[-1] <= c.t_out_end
    assert 0 < n_flag < n_case


# ---------------------------------------------------------------- tracer
def test_tracer_pulse_detected_with_seed_noise():
    """Seed ch. 6: axial-dispersion pulse (Table 6.2) with baseline noise mu=-0.05, sigma=0.13;
    the segment holds the peak and reaches past the 99.5 % quantile of F (72.2 s)."""
    rng = np.random.default_rng(5)
    t = np.arange(0, 3600, DT)
    t_pulse = 1800.0
    c = 4.0 / E_SEED.max() * ad_open(t - t_pulse, 11.92, 16.37, 7.67) - 0.05
    c += rng.normal(0, 0.13, t.size)
    det = TracerPulseDetector(DT)
    segs = [s for ti, ci in zip(t, c) if (s := det.push(ti, ci)) is not None]
    assert len(segs) == 1
    s = segs[0]
    assert t_pulse < s.t0 < t_pulse + 11.92 + 5
    assert abs(s.peak_t - (t_pulse + 11.92 + 16.37 * (math.sqrt(1 + 9 / 7.67**2) - 3 / 7.67))) < 4
    assert s.t[-1] > t_pulse + 72.2
    assert s.sigma == pytest.approx(0.13, rel=0.25)
    # announced injection: the segment starts at the injection
    det2 = TracerPulseDetector(DT)
    segs2 = []
    for ti, ci in zip(t, c):
        if ti == t_pulse:
            det2.announce(t_pulse)
        if (s2 := det2.push(ti, ci)) is not None:
            segs2.append(s2)
    assert len(segs2) == 1 and segs2[0].announced and segs2[0].t[0] == t_pulse


@pytest.mark.parametrize("late", [1, 3, 10])
def test_tracer_announced_a_few_samples_late_gives_the_in_time_segment(late):
    """An announcement that reaches the detector ``late`` samples after the injection (another
    route than the NIR samples) gives the segment, baseline and noise of an in-time one: the
    baseline is the one before the injection."""
    rng = np.random.default_rng(7)
    t = np.arange(0, 900, DT)
    t_pulse = 600.0
    c = 4.0 / E_SEED.max() * ad_open(t - t_pulse, 11.92, 16.37, 7.67) - 0.05
    c += rng.normal(0, 0.13, t.size)

    def segment(delay: int):
        det = TracerPulseDetector(DT)
        i_pulse = int(np.argmax(t >= t_pulse))
        for i, (ti, ci) in enumerate(zip(t, c)):
            if i == i_pulse + delay:
                det.announce(t_pulse)
            if (s := det.push(ti, ci)) is not None:
                return s
        return None

    ref, got = segment(0), segment(late)
    assert ref.announced and got.announced and ref.t[0] == t_pulse
    assert (got.baseline, got.sigma) == (ref.baseline, ref.sigma)
    np.testing.assert_array_equal(got.t, ref.t)
    np.testing.assert_array_equal(got.c, ref.c)


def test_tracer_no_false_pulse_on_noise():
    rng = np.random.default_rng(6)
    det = TracerPulseDetector(DT)
    t = np.arange(0, 7200, DT)
    c = rng.normal(-0.05, 0.13, t.size)
    assert all(det.push(ti, ci) is None for ti, ci in zip(t, c))
    assert det.flush() is None


# ---------------------------------------------------------------- inlet
def test_inlet_aligner_orders_and_holds():
    al = InletAligner(["api", "exc"], dt=1.0, max_lag=3)
    assert al.push("api", 0.0, 1.0) == []
    assert al.push("exc", 0.0, 9.0) == [(0.0, {"api": 1.0, "exc": 9.0})]
    assert al.push("exc", 1.0, 9.0) == []  # api's tick 1 never arrives
    out = []
    for k in range(2, 6):
        out += al.push("exc", float(k), 9.0)
        out += al.push("api", float(k), 2.0)
    assert [t for t, _ in out] == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert out[0][1] == {"api": 1.0, "exc": 9.0} and al.held_ == 1
    assert composition_pct({"api": 1.0, "exc": 9.0}, {"api": "api", "exc": "exc"}) == {
        "api": 10.0,
        "exc": 90.0,
    }


def test_watermark_merge_is_independent_of_arrival_order():
    """Streams delivered one after the other (history after a restart) or interleaved give
    the same release order."""
    from twin_core.online import WatermarkMerger

    rng = np.random.default_rng(7)
    streams = {s: np.sort(rng.uniform(0, 100, 50)) for s in ("a", "b", "c")}
    m1 = WatermarkMerger(["a", "b", "c"])
    got1 = []
    for s in ("a", "b", "c"):  # stream by stream
        for t in streams[s]:
            got1 += m1.push(s, t, (s, t))
    got1 += m1.release_all()
    m2 = WatermarkMerger(["a", "b", "c"])
    allv = sorted((t, s) for s, ts in streams.items() for t in ts)
    got2 = []
    for t, s in allv:  # interleaved in time
        got2 += m2.push(s, t, (s, t))
    got2 += m2.release_all()
    assert [x[2] for x in got1] == [x[2] for x in got2] == [(s, t) for t, s in allv]
