"""The dashboard's state: ring buffers, min-max decimation, divert windows, refills, counters.

Validated against: the definition of min-max decimation (Jugel et al. 2014, M4 with two points
per bucket: every bucket's extremes kept, so the decimated series has the global extremes and
the same envelope per bucket) computed here by brute force, and hand-built message sequences
whose windows are known.
"""

from __future__ import annotations

import numpy as np
import pytest

from schemas.messages import (
    DivertCommand,
    Event,
    FeederFlow,
    MeasuredConcentration,
    OosAlert,
    PredictedConcentration,
    ServiceHealth,
)
from twin_core.online.dashboard_state import DashboardState, PlotFeed, Ring, decimate_min_max

KEY_API = "twin/line1/feeder/api/flow"
KEY_NIR = "twin/line1/pat/nir1/concentration"


def flow(t: float, seq: int, kg_h: float = 0.6, refilling: bool = False) -> FeederFlow:
    return FeederFlow(
        t=t,
        seq=seq,
        component="api",
        mass_flow_kg_h=kg_h,
        screw_speed_rpm=10.0,
        hopper_mass_kg=5.0,
        feed_factor_g_rev=1.0,
        refilling=refilling,
    )


def nir(t: float, seq: int, value: float, quality: str = "good") -> MeasuredConcentration:
    return MeasuredConcentration(
        t=t, seq=seq, sensor="nir1", component="api", concentration_pct_w_w=value, quality=quality
    )


def divert(cid: str, t: float, seq: int, start: float, end: float, action: str = "divert"):
    return DivertCommand(
        t=t, seq=seq, command_id=cid, action=action, t_start_s=start, t_end_s=end, reason="oos"
    )


def test_decimation_keeps_each_buckets_extremes():
    """Brute force: for each of the 49 buckets, its min and max are among the kept points, and
    so are the first and the newest sample."""
    rng = np.random.default_rng(4)
    t = np.arange(10_000.0)
    y = rng.normal(size=t.size)
    y[7_321] = 9.0  # a one-sample excursion a stride-decimation would miss
    td, yd = decimate_min_max(t, y, 100)
    assert td.size <= 100 and np.all(np.diff(td) > 0)
    size = -(-t.size // 49)
    for lo in range(0, t.size, size):
        hi = min(lo + size, t.size)
        inside = (td >= t[lo]) & (td <= t[hi - 1])
        assert yd[inside].max() == y[lo:hi].max() and yd[inside].min() == y[lo:hi].min()
    assert 9.0 in yd and td[0] == 0.0 and td[-1] == 9_999.0


def test_decimation_short_series_unchanged_and_nan_dropped():
    t = np.array([0.0, 1.0, 2.0])
    td, yd = decimate_min_max(t, np.array([1.0, np.nan, 3.0]), 10)
    assert td.tolist() == [0.0, 2.0] and yd.tolist() == [1.0, 3.0]
    with pytest.raises(ValueError, match="max_points must be >= 4, got 3"):
        decimate_min_max(t, t, 3)


def test_ring_is_bounded():
    r = Ring(capacity=5)
    for i in range(12):
        r.append(float(i), float(i * i))
    cols = r.columns()
    assert cols[0].tolist() == [7.0, 8.0, 9.0, 10.0, 11.0] and cols[1][-1] == 121.0
    with pytest.raises(ValueError, match="values must have 1 entries, got 2"):
        r.append(0.0, 1.0, 2.0)


def test_series_decimated_in_view_and_bad_nir_left_out():
    s = DashboardState(capacity=3000)
    for i in range(5000):
        s.add(KEY_API, flow(float(i), i))
        s.add(KEY_NIR, nir(float(i), i, 5.0, quality="bad" if i == 4999 else "good"))
    v = s.view(max_points=200)
    assert len(s.series("flow:api")[0]) == 3000  # the ring keeps the last 3000
    assert len(v.series["flow:api"]["t"]) <= 200
    assert v.series["measured:nir1"]["t"][-1] == 4998.0  # the 'bad' sample is not plotted
    assert v.counters == {"FeederFlow": 5000, "MeasuredConcentration": 5000}
    assert v.now_s == 4999.0


def test_prediction_band_follows_kept_points():
    s = DashboardState()
    for i in range(10):
        p = PredictedConcentration(
            t=float(i),
            seq=i,
            model="rtd",
            component="api",
            concentration_pct_w_w=5.0 + i,
            lower_pct_w_w=None if i == 3 else 4.5 + i,
            upper_pct_w_w=None if i == 3 else 5.5 + i,
        )
        s.add("twin/line1/blender/outlet/predicted", p)
    d = s.view(max_points=100).series["predicted:api"]
    assert d["y"][3] == 8.0 and d["lower"][3] == 8.0 and d["upper"][3] == 8.0  # no band
    assert d["lower"][4] == 8.5 and d["upper"][4] == 9.5
    assert s.view(100).blender_model == "rtd"


def test_diverter_state_and_upcoming_windows():
    s = DashboardState()
    s.add("twin/line1/divert/command", divert("c1", 100.0, 0, 150.0, 200.0))
    s.add("twin/line1/divert/command", divert("c2", 110.0, 1, 400.0, 450.0))
    s.add("twin/line1/divert/command", divert("c3", 120.0, 2, 600.0, 650.0))
    s.add("twin/line1/divert/command", divert("c4", 130.0, 3, 600.0, 650.0, action="accept"))
    before = s.diverter(140.0)
    assert not before.diverting and [w.ident for w in before.upcoming] == ["c1", "c2"]
    inside = s.diverter(160.0)
    assert inside.diverting and inside.current.ident == "c1"
    assert [w.ident for w in inside.upcoming] == ["c2"]
    # a divert for the same window after the accept is in force again
    s.add("twin/line1/divert/command", divert("c5", 140.0, 4, 600.0, 650.0))
    assert [w.ident for w in s.diverter(300.0).upcoming] == ["c2", "c5"]


def test_a_final_divert_window_replaces_the_provisional_one_of_its_alert():
    """The diverter's early command of a flagged disturbance holds a provisional window (up to
    3600 s from its start) until the alert's final command replaces it: after the final one,
    the gate is diverting inside the final window only, not for the next hour."""
    s = DashboardState()
    opened = divert("a.open", 305.0, 0, 312.0, 3912.0).model_copy(update={"alert_id": "a"})
    final = divert("a.final", 332.0, 1, 312.0, 369.0).model_copy(update={"alert_id": "a"})
    s.add("twin/line1/divert/command", opened)
    assert s.diverter(1800.0).diverting  # only the provisional window is known yet
    s.add("twin/line1/divert/command", final)
    assert s.diverter(350.0).diverting and s.diverter(350.0).current.ident == "a.final"
    assert not s.diverter(1800.0).diverting
    assert max(w.t_end_s for w in s.divert_windows()) == 369.0


def test_refill_windows_from_flags_and_events():
    s = DashboardState()
    s.add(KEY_API, flow(10.0, 0))
    s.add(KEY_API, flow(11.0, 1, refilling=True))
    s.add(KEY_API, flow(12.0, 2, refilling=True))
    s.add(KEY_API, flow(13.0, 3))
    ev = Event(t=20.0, seq=0, kind="refill_start", source="excipient")
    s.add("twin/line1/feeder/excipient/event", ev)
    s.add(KEY_API, flow(25.0, 4))
    w = s.refill_windows()
    assert [(x.t_start_s, x.t_end_s) for x in w["api"]] == [(11.0, 13.0)]
    assert [(x.t_start_s, x.t_end_s) for x in w["excipient"]] == [(20.0, 25.0)]  # still open


def test_alerts_kept_once_per_id_and_bounded():
    s = DashboardState(events_kept=3)
    for i in range(5):
        a = OosAlert(
            t=100.0 + i,
            seq=i,
            alert_id=f"a{i}",
            component="api",
            t_start_s=10.0 * i,
            t_end_s=10.0 * i + 5,
            peak_deviation_pct_w_w=1.0,
            limit_pct_w_w=0.5,
            cause="refill api",
        )
        s.add("twin/line1/oos/alert", a)
        s.add("twin/line1/oos/alert", a)  # history and live: shown once
    assert [a["alert_id"] for a in s.view(10).alerts] == ["a2", "a3", "a4"]


def test_health_is_latest_per_service_and_does_not_move_plant_time():
    s = DashboardState()
    h = ServiceHealth(
        t=500.0, seq=0, service="oos", state="running", pid=1, uptime_s=3.0,
        wall_time_unix_s=1.0e9, counters={"published": 2},
    )  # fmt: skip
    s.add("twin/line1/service/oos/health", h)
    assert s.now_s == 0.0
    assert s.view(10).health["oos"]["counters"] == {"published": 2}


def test_plot_feed_streams_then_replaces_with_the_decimated_window():
    """A plot of max 100 points: new samples are appended until it would hold more, then it is
    replaced by the last window_s of the series decimated to 50; what it shows always ends at
    the newest sample and never holds more than 100."""
    s = DashboardState()
    feed = PlotFeed(max_points=100, window_s=500.0)
    shown: list[float] = []
    kinds = []
    for i in range(1000):
        s.add(KEY_NIR, nir(float(i), i, 5.0 + np.sin(i / 7.0)))
        if i % 40 == 39:  # a refresh every 40 samples (200 ms at 200x)
            kind, data = feed.update(s.series("measured:nir1"))
            shown = shown + data["t"] if kind == "stream" else data["t"]
            kinds.append(kind)
            assert len(shown) <= 100 and shown[-1] == float(i)
            assert feed.n_shown == len(shown)
    assert feed.update(s.series("measured:nir1")) is None  # nothing new
    assert kinds[:2] == ["stream", "stream"] and "replace" in kinds
    assert kinds.count("replace") <= len(kinds) // 2
    assert shown[0] >= 999.0 - 500.0 - 40.0  # the window, plus what streamed since
