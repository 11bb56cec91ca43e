"""The dashboard's page without a browser: a recording replayed into the hub fills the Bokeh
document's sources and panels (counts checked against the recording itself), and the served page
references only its own origin."""

from __future__ import annotations

import threading
import urllib.request
from pathlib import Path

from bokeh.document import Document

from schemas.line import LineSpec
from services.bus import free_port
from services.dashboard import DashboardHub, Page, make_server, start_recording_feed
from services.recording import read_recording

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "services" / "configs" / "line1_5pct.yaml"
RECORDING = ROOT / "recordings" / "line1_30min.mcap"


def test_recording_fills_the_page():
    """The bundled recording (1,801 NIR samples, one excipient refill) at 1e5x: every message
    reaches the state, the NIR plot holds at most max_points decimated samples ending at the last
    one, the refill shows as one window."""
    rec = read_recording(RECORDING)
    hub = DashboardHub(LineSpec.from_file(CONFIG), max_points=500)
    start_recording_feed(rec, hub, 1e5, lambda: False)
    assert hub.finished.wait(60)
    doc = Document()
    page = Page(doc, hub, period_ms=200, window_s=3600.0)
    assert sum(hub.state.counters.values()) == len(rec.messages)
    nir = page.sources["measured:nir1"].data
    assert 2 <= len(nir["t"]) <= 500 and nir["t"][-1] == 1800.0
    assert page.sources["refill_windows"].data["x0"] != []
    assert "newest NIR sample 1800 s" in page.divs["status"].text
    assert "OOS alerts</b><p>none" in page.divs["alerts"].text
    assert "accepting" in page.divs["diverter"].text


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
