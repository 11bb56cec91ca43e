"""The dashboard's page without a browser: a recording replayed into the hub fills the Bokeh
document's sources and panels (counts checked against the recording itself), and the served page
references only its own origin."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

from bokeh.document import Document

from schemas.closeloop import ModelFinding
from schemas.line import LineSpec
from schemas.messages import BlenderModelInUse, RtdEstimate
from services.bus import free_port
from services.dashboard import DashboardHub, Page, health_html, make_server, start_recording_feed
from services.recording import read_recording, write_messages
from twin_core.online.blender import declared_kernel
from twin_core.plant.messages import simulate_messages

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "services" / "configs" / "line1_5pct.yaml"
RECORDING = ROOT / "recordings" / "line1_30min.mcap"


def test_recording_fills_the_page():
    """The bundled recording (1,801 NIR samples, one excipient refill, three tracer pulses) at
    1e5x: every message reaches the state, with the twin's predictions and decisions computed
    from it (three alerts, six divert commands, as `twin demo`'s live twin gives); the NIR plot
    holds at most max_points decimated samples ending at the last one, the refill shows as one
    window."""
    rec = read_recording(RECORDING)
    hub = DashboardHub(LineSpec.from_file(CONFIG), max_points=500)
    start_recording_feed(rec, hub, 1e5, lambda: False)
    assert hub.finished.wait(60)
    doc = Document()
    page = Page(doc, hub, period_ms=200, window_s=3600.0)
    c = hub.state.counters
    derived = c["PredictedConcentration"] + c["OosAlert"] + c["DivertCommand"]
    assert sum(c.values()) - derived == len(rec.messages)
    assert (c["OosAlert"], c["DivertCommand"]) == (3, 6)
    nir = page.sources["measured:nir1"].data
    assert 2 <= len(nir["t"]) <= 500 and nir["t"][-1] == 1800.0
    assert page.sources["refill_windows"].data["x0"] != []
    assert "newest NIR sample 1800 s" in page.divs["status"].text
    assert "divert windows computed by the twin" in page.divs["status"].text
    assert page.divs["alerts"].text.count("data-alert-id") == 3
    assert "accepting" in page.divs["diverter"].text  # at 1800 s, past every window


def test_recording_mode_shows_what_the_twin_would_decide(tmp_path):
    """A plant recording (no twin ran on it) with an API feeder disturbance whose NIR readings
    leave the specification: the page shows the alert the twin's diverter gives on it, the gate
    diverting inside its window and the readings beyond the limit inside that window, not
    "OOS alerts: none" and "accepting" beside them."""
    spec = LineSpec.from_file(CONFIG)
    dist = {"feeder": "api", "t_s": 200.0, "delta_kg_h": 0.6, "duration_s": 30.0}
    _, msgs = simulate_messages(spec, 600.0, 0, [dist])
    write_messages(tmp_path / "d.mcap", msgs)
    hub = DashboardHub(spec)
    start_recording_feed(read_recording(tmp_path / "d.mcap"), hub, 1e5, lambda: False)
    assert hub.finished.wait(60)
    page = Page(Document(), hub, period_ms=200, window_s=3600.0)
    upper = spec.limits("api").upper_pct_w_w
    nir = page.sources["measured:nir1"].data
    beyond = [t for t, y in zip(nir["t"], nir["y"], strict=True) if y > upper]
    assert beyond, "the disturbance must take the NIR beyond the upper limit"
    assert "line1.api.feed-000000200000" in page.divs["alerts"].text
    windows = hub.state.divert_windows()  # the early (.open) and the final window
    assert len(windows) == 2
    lo, hi = min(w.t_start_s for w in windows), max(w.t_end_s for w in windows)
    assert all(lo <= t <= hi for t in beyond)
    assert hub.state.diverter(beyond[0]).diverting


def test_page_is_served_from_its_own_origin_only():
    """No CDN: the page's scripts come from the server itself (relative paths)."""
    hub = DashboardHub(LineSpec.from_file(CONFIG))
    port = free_port()
    server = make_server(hub, port=port)
    server.start()
    thread = threading.Thread(target=server.io_loop.start, daemon=True)
    thread.start()
    try:
        html = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=20).read().decode()
    finally:
        server.io_loop.add_callback(server.io_loop.stop)
        thread.join(10)
        server.stop()
    assert "/static/js/bokeh.min.js" in html
    assert "http://" not in html and "https://" not in html and "//cdn" not in html


def finding(status: str, t_end: float) -> ModelFinding:
    err = {"rmse": 0.2, "mae": 0.1, "n": 100}
    pair = {"train": err, "heldout": err}
    return ModelFinding(
        t=t_end, seq=0, finding_id=f"line1.closeloop-{int(t_end * 1000)}", status=status,
        t_start_s=t_end - 600.0, t_end_s=t_end, errors={"before": pair, "after": pair},
    )  # fmt: skip


def test_estimate_curve_and_findings_panel():
    """An RTD estimate with the declared model's own parameters draws the declared E(t) (seed
    Table 6.2's axial dispersion model, evaluated by twin_core.rtd.models); findings show with
    their status, newest first."""
    spec = LineSpec.from_file(CONFIG)
    hub = DashboardHub(spec)
    page = Page(Document(), hub, period_ms=200, window_s=3600.0, slow_panels_s=0.0)
    b = spec.blender
    hub.put(
        "twin/line1/rtd/estimate",
        RtdEstimate(t=400.0, seq=0, model=b.model, params=b.params, mean_residence_time_s=28.3),
    )
    hub.put("twin/line1/closeloop/finding", finding("consistent", 900.0))
    hub.put("twin/line1/closeloop/finding", finding("unexplained", 1200.0))
    page.refresh()
    assert "axial_dispersion_open" in page.divs["blender"].text  # the model of the predictions
    hub.put(
        "twin/line1/blender/outlet/model_in_use",
        BlenderModelInUse(
            t=600.0, seq=0, kind="compartment", name="zones-120rpm", reason="blade_speed",
            applies_from_s=600.0, blade_speed_rpm=120.0, mean_residence_time_s=31.5,
        ),
    )  # fmt: skip
    page.refresh()
    assert "compartment zones-120rpm from 600 s (blade_speed; blade rpm 120; MRT 31.5 s)" in (
        page.divs["blender"].text
    )
    assert page.sources["rtd_estimate"].data["e"] == declared_kernel(spec).tolist()
    text = page.divs["findings"].text
    assert text.index("line1.closeloop-1200000") < text.index("line1.closeloop-900000")
    assert "status-unexplained" in text and "status-consistent" in text
    assert "axial_dispersion_open" in page.divs["blender"].text  # the estimates table


def test_cli_serves_a_recording_and_stops_cleanly_on_sigterm():
    """``twin dashboard --recording``: the page is served on loopback, SIGTERM stops it with
    exit status 0."""
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "dashboard", "--config", str(CONFIG)]
        + ["--recording", str(RECORDING), "--speed", "1000", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        first = proc.stdout.readline()
        assert f"http://127.0.0.1:{port}/" in first and "line1_30min.mcap at 1000x" in first
        html = ""
        for _ in range(100):
            try:
                html = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5).read()
                break
            except OSError:
                time.sleep(0.1)
        assert b"powder-twin line1" in html
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_health_panel_shows_the_dashboards_own_rejections():
    view = DashboardHub(LineSpec.from_file(CONFIG)).view()
    text = health_html(view, 0.0, {"received": 5, "rejected_json": 2})
    assert "Dashboard on the bus</b>: received=5, rejected_json=2" in text
    assert "Dashboard on the bus" not in health_html(view, 0.0, {})
