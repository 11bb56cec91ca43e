"""``twin demo``'s report in the words of the plant: tracer pulses named as such, each
close-loop status explained in one line, and the two blender models' errors with the reason
they differ, computed from the run (``services.twin_demo``)."""

from __future__ import annotations

import numpy as np
import pytest

from services.twin_demo import STATUS_MEANING, blender_comparison, report_markdown


def _e(t: np.ndarray, mode: float, width: float) -> np.ndarray:
    """A gamma-like E(t) with its peak at ``mode``."""
    k = (mode / width) ** 2
    e = np.where(t > 0, (t / mode) ** k * np.exp(-k * (t / mode - 1.0)), 0.0)
    return e / e.sum()


def _runs(seed: int = 0):
    """NIR = the reference model's outlet (its E(t) wide, peak at 26 s) + noise sd 0.18; the
    'live' model's E(t) has the same mean and a narrower, later peak; two tracer pulses."""
    dt, t_k = 1.0, np.arange(300.0)
    e_ref, e_live = _e(t_k, 26.0, 10.0), _e(t_k, 30.0, 6.0)
    e_live = np.interp(t_k + (e_live * t_k).sum() - (e_ref * t_k).sum(), t_k, e_live)
    e_live /= e_live.sum()
    t = np.arange(0.0, 1800.0, dt)
    inlet = np.full(t.size, 5.0)
    for p in (300.0, 900.0):
        inlet[t == p] += 500.0
    ref = np.convolve(inlet, e_ref)[: t.size]
    live = np.convolve(inlet, e_live)[: t.size]
    rng = np.random.default_rng(seed)
    meas = ref + rng.normal(0.0, 0.18, t.size)
    as_dict = lambda a: dict(zip(t.tolist(), a.tolist()))  # noqa: E731
    return as_dict(meas), as_dict(live), as_dict(ref), [300.0, 900.0], e_live, e_ref, dt


def test_blender_comparison_finds_where_and_why_the_errors_differ():
    """The live model's extra error lies in the pulses' passage; its E(t) has the reference's
    mean residence time but a narrower, later peak; the pulses' peaks say so."""
    c = blender_comparison(*_runs())
    assert c["pulses"] == 2
    assert c["excess_share_in_pulses"] > 0.9
    assert c["rmse_outside"]["live"] == pytest.approx(c["rmse_outside"]["reference"], abs=0.02)
    assert c["rmse_in_pulses"]["live"] > 2 * c["rmse_in_pulses"]["reference"]
    e = c["e_t"]
    assert e["live"]["mean_s"] == pytest.approx(e["reference"]["mean_s"], abs=0.5)
    assert e["live"]["sd_s"] < e["reference"]["sd_s"]
    assert e["live"]["mode_s"] > e["reference"]["mode_s"]
    assert all(m < lv for m, lv in zip(c["peak_delay_s"]["measured"], c["peak_delay_s"]["live"]))
    text = c["text"]
    assert "tracer pulses' passage" in text and "mean residence time" in text
    assert "narrower" in text and "later peak" in text


def _report(findings: list[dict], alerts: list[dict], comparison: dict | None) -> dict:
    return {
        "recording": "x.mcap",
        "recording_status": "complete",
        "messages_replayed": 10,
        "plant_span_s": 1800.0,
        "timings_s": {"replay_wall_s": 1.0, "startup_s": 1.0, "total_s": 3.0},
        "speedup_achieved": 10.0,
        "predictions": 1800,
        "blender_model": "compartment",
        "prediction_error_pct_w_w": {"n": 1800, "bias": -0.05, "rmse": 0.347},
        "reference_prediction_error_pct_w_w": {"n": 1800, "bias": -0.05, "rmse": 0.184},
        "blender_comparison": comparison,
        "alerts": alerts,
        "divert_commands": [],
        "rtd_estimates": [],
        "rtd_skipped": [],
        "duplicates_seen": 0,
        "model_findings": findings,
        "service_health": {},
    }


def _finding(status: str, t0: float) -> dict:
    err = {"heldout": {"rmse": 0.2}}
    return {
        "t_start_s": t0,
        "t_end_s": t0 + 1200,
        "status": status,
        "effects": [],
        "errors": {"before": err, "after": err},
    }


def test_the_report_names_tracer_pulses_explains_statuses_and_the_models_errors():
    alert = {
        "alert_id": "line1.api.feed-000000300000",
        "t_start_s": 317.0,
        "t_end_s": 373.0,
        "peak_deviation_pct_w_w": 8.1,
        "cause": "tracer pulse of api (10 g injected at 300.0 s; inlet peak 147.967 % w/w over 2 "
        "samples) is outside the funnel's feasible region: predicted outlet deviation +8.1 % w/w",
    }
    findings = [_finding("unexplained", 0.0), _finding("partly_explained", 300.0)]
    md = report_markdown(_report(findings, [alert], blender_comparison(*_runs())))
    assert "OOS alerts: 1 (1 tracer pulse)" in md
    # each status of the findings explained in one line, every status's meaning known
    assert set(STATUS_MEANING) == {
        "consistent",
        "explained",
        "partly_explained",
        "unexplained",
        "data_quality",
    }
    for status in ("unexplained", "partly_explained"):
        [line] = [x for x in md.splitlines() if x.startswith(f"- `{status}`")]
        assert STATUS_MEANING[status] in line
    # the two blender models' errors side by side, with the reason they differ
    line = next(x for x in md.splitlines() if "Table 6.2" in x and "RMSE 0.184" in x)
    why = md[md.index(line) :]
    assert "tracer pulses' passage" in why and "mean residence time" in why
