"""``twin dashboard`` in a real browser (headless Chromium) while the live twin runs a replay.

The supervised twin (feeder, blender, oos) gets the bundled recording at 100x; ``twin dashboard``
follows its bus as a separate process; Chromium loads the page while the replay runs. Checked:

- the plots update while the replay runs (the newest NIR sample of BokehJS's data source
  advances at least three times before the replay ends);
- every OOS alert shows in the page while the twin runs: the test's own subscriber notes the
  wall time the alert reached it on loopback (its publish time within a millisecond), the
  page's watcher the wall time its row first appeared in the DOM (same machine clock), and the
  difference is bounded with a margin for a loaded machine (``ALERT_REACHES_PAGE_S``). The
  dashboard's speed (an alert on the screen within 1 s) is a benchmark's figure, measured on a
  quiet machine by ``benchmarks/dashboard_latency.py``, not a timed test: with the rest of the
  suite running in parallel on two cores the page has taken 2.5 s;
- the page and what the browser fetched reference no URL off the dashboard's origin (a plant
  network has no internet).

Screenshots and the measured latencies go to ``out/test_artifacts/``. Reference for the alerts: one per tracer pulse of the
bundled recording (its three API pulses, 300/900/1500 s, leave the 5 % +- 15 % specification,
as ``tests/e2e/test_demo.py`` finds through ``twin demo``).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest
import yaml
import zenoh
from browser import (
    browser_missing,
    external_urls,
    load_dashboard,
    open_browser,
    seen,
    sources,
    start_dashboard,
)
from twin_view import plant_replay, wait_until

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import OosAlert
from services.bus import free_port, open_session
from services.recording import read_recording
from services.supervisor import Supervisor

pytestmark = pytest.mark.e2e

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "services" / "configs" / "line1_5pct.yaml"
RECORDING = ROOT / "recordings" / "line1_30min.mcap"
ARTIFACTS = ROOT / "out" / "test_artifacts"
#: the replay's speed: 100x keeps the test near half a minute of replay while leaving the shared
#: machine's CPU to the page (the dashboard's keeping up with 200x is measured by
#: benchmarks/dashboard_latency.py)
SPEED = 100.0
#: an alert reaches the page while the twin runs (functional bound, with room for the parallel
#: suite's load; the 1 s speed figure is benchmarks/dashboard_latency.py's)
ALERT_REACHES_PAGE_S = 10.0
NIR = "measured:nir1"


class AlertClock:
    """The wall time (unix s) each OOS alert reached a subscriber of the test (loopback)."""

    def __init__(self, session: zenoh.Session, line: str) -> None:
        self.at: dict[str, float] = {}
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(
            keys.oos_alert(line), zenoh.handlers.Callback(self._on, lambda: None)
        )

    def _on(self, sample: zenoh.Sample) -> None:
        now = time.time()
        alert = OosAlert.model_validate_json(sample.payload.to_bytes())
        with self._lock:
            self.at.setdefault(alert.alert_id, now)

    def undeclare(self) -> None:
        self._sub.undeclare()


def line_spec(tmp: Path) -> tuple[LineSpec, Path]:
    """The bundled recording's line on a free loopback port, state in ``tmp``; and its file."""
    data = LineSpec.from_file(CONFIG).model_dump(mode="json")
    data.update(
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{free_port()}"], "connect": []},
        services=["feeder", "blender", "oos"],
        state_dir=str(tmp / "state"),
        record_path=None,
    )
    spec = LineSpec.model_validate(data)
    path = tmp / "line.yaml"
    path.write_text(yaml.safe_dump(spec.model_dump(mode="json")))
    return spec, path


@pytest.fixture
def browser(tmp_path):
    why = browser_missing()
    if why:
        pytest.skip(why)
    driver = open_browser(tmp_path / "chromium-profile")
    yield driver
    driver.quit()


def test_dashboard_follows_the_twin_in_chromium(tmp_path, browser):
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    spec, spec_path = line_spec(tmp_path)
    rec = read_recording(RECORDING)
    port = free_port()
    sup = Supervisor(spec, backoff_s=0.2).start()
    proc = clock = session = None
    try:
        assert sup.wait_ready(60), f"services not ready: alive {sup.alive}"
        proc, url = start_dashboard(["--config", str(spec_path), "--port", str(port)])
        load_s = load_dashboard(browser, url)
        session = open_session(sup.client_config("operator"))
        clock = AlertClock(session, spec.name)
        with plant_replay(rec, sup) as rp:
            done = threading.Event()
            replay = threading.Thread(
                target=lambda: (rp.replay(speed=SPEED), done.set()), daemon=True
            )
            replay.start()
            assert wait_until(lambda: sources(browser).get(NIR, (0, None))[0] > 0, 20)
            browser.save_screenshot(str(ARTIFACTS / "dashboard_during_replay.png"))
            assert done.wait(60), "the replay did not finish"
            replay_end = time.time()
            assert wait_until(lambda: len(clock.at) >= 3, 30), clock.at
            in_page = wait_until(
                lambda: set(clock.at) <= set(seen(browser)["alerts"]), ALERT_REACHES_PAGE_S
            )
            assert in_page, (clock.at, seen(browser)["alerts"], sorted(seen(browser)["nir"])[-3:])
        browser.save_screenshot(str(ARTIFACTS / "dashboard_after_replay.png"))
        shown = seen(browser)["alerts"]
        plotted = seen(browser)["plotted"]
        latency = {a: shown[a] - t for a, t in clock.at.items()}
        resources = browser.execute_script(
            "return performance.getEntriesByType('resource').map(e => e.name)"
        )
        offsite = external_urls(browser.page_source, resources, url.rstrip("/"))
    finally:
        if clock is not None:
            clock.undeclare()
        if session is not None:
            session.close()
        if proc is not None:
            proc.terminate()
            proc.wait(10)
        sup.stop()
    (ARTIFACTS / "dashboard_latency.json").write_text(
        json.dumps({"alert_to_page_s": latency, "page_load_s": load_s}, indent=2)
    )
    during = [t for t, at in plotted if at <= replay_end]
    assert len(during) >= 3 and during == sorted(during), f"NIR plot during the replay: {during}"
    assert len(latency) == 3, latency  # one alert per tracer pulse
    assert max(latency.values()) <= ALERT_REACHES_PAGE_S, f"alert -> page latency {latency} s"
    assert offsite == [], f"the page references URLs off {url}: {offsite}"
    assert load_s < 30.0
