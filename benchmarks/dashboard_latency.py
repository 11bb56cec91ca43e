"""``twin dashboard`` in headless Chromium: NIR message -> pixels latency, page load time, and the
CPU the dashboard process spends following a replay.

Method: this process hosts a zenoh router on loopback and publishes the bundled recording
(``recordings/line1_30min.mcap``, 5 keys, 5,408 messages over 1,800 s of plant time) with the
replay schedule of ``twin replay`` (``services.recording.replay``), noting the wall time each
NIR sample left. ``twin dashboard`` (a separate process) follows the bus; Chromium (the
``tests/e2e/browser.py`` driver) loads the page and a watcher run on every animation frame
notes the frame at which each sample first is the newest point of the NIR plot's data in
BokehJS (the frame that draws it). Latency = that time minus the sample's publish time (same
machine clock); at 200x a plot update (at most every 0.5 s) brings about 100 samples and the
newest is measured, so the latencies are those of the samples drawn last. Page load: from
``driver.get`` to the first drawn panels (BokehJS loaded, document built), cold (first load of
the browser) and warm (second). CPU: user + system time of the dashboard process
(``/proc/<pid>/stat``) over the replay's wall time.

Alerts: at plant times 300, 900 and 1,500 s (the recording's tracer pulses) this process also
publishes an ``OosAlert`` the moment the NIR sample of that time leaves; latency = the time its
row first shows in the DOM (the page's watcher) minus that publish time. This is the figure
behind the dashboard's "an alert on the screen within 1 s"; the browser test
(``tests/e2e/test_dashboard_browser.py``) checks that alerts reach the page, with a margin for
a loaded machine.

Run: ``python benchmarks/dashboard_latency.py [SPEED ...]`` (default ``1 200``; at 1x the
first 60 s of plant time).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml
from machine import describe

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "e2e"))

from browser import (  # noqa: E402
    browser_missing,
    load_dashboard,
    open_browser,
    seen,
    start_dashboard,
)

from schemas.line import LineSpec  # noqa: E402
from schemas.messages import OosAlert  # noqa: E402
from services.bus import free_port, open_session  # noqa: E402
from services.recording import Recording, read_recording, replay  # noqa: E402

CONFIG = ROOT / "services" / "configs" / "line1_5pct.yaml"
RECORDING = ROOT / "recordings" / "line1_30min.mcap"
NIR_KEY = "twin/line1/pat/nir1/concentration"
ALERT_KEY = "twin/line1/oos/alert"
#: plant times (s) at which an alert is published with the NIR sample
ALERT_AT_S = (300.0, 900.0, 1500.0)
OUT = ROOT / "out" / "bench"


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid``, s (``/proc/<pid>/stat`` fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def first_seconds(rec: Recording, plant_s: float) -> Recording:
    """The recording's messages of its first ``plant_s`` seconds."""
    t0 = rec.messages[0].t
    msgs = [m for m in rec.messages if m.t - t0 <= plant_s]
    return Recording(rec.path, msgs, rec.channels, rec.truncated, rec.error)


def run_speed(session, rec: Recording, speed: float, driver, pid: int) -> dict[str, float]:
    """Publish ``rec`` at ``speed``; the latencies of the NIR samples drawn and the CPU used."""
    published: dict[str, float] = {}
    alerted: dict[str, float] = {}

    def publish(key: str, payload: bytes) -> None:
        session.put(key, payload)
        if key == NIR_KEY:
            t = _plant_t(payload)
            published.setdefault(f"{t:g}", time.time())
            if t in ALERT_AT_S:
                alert = _alert(t, len(alerted))
                session.put(ALERT_KEY, alert.to_json_bytes())
                alerted[alert.alert_id] = time.time()

    frames0 = seen(driver)["frames"]
    cpu0, wall0 = cpu_seconds(pid), time.time()
    replay(rec, publish, speed=speed)
    time.sleep(1.5)  # the last refreshes reach the page
    cpu = cpu_seconds(pid) - cpu0
    wall = time.time() - wall0
    page = seen(driver)
    shown: dict[str, float] = {}
    for t, at in page["plotted"]:  # the NIR plot's newest sample, frame by frame
        shown.setdefault(f"{t:g}", at)
    lat = np.array([shown[t] - published[t] for t in shown if t in published])
    alert_lat = [page["alerts"][a] - at for a, at in alerted.items() if a in page["alerts"]]
    return {
        "alerts_published": len(alerted),
        "alerts_shown": len(alert_lat),
        "alert_max_ms": float(max(alert_lat, default=float("nan")) * 1e3),
        "speed": speed,
        "nir_published": len(published),
        "nir_drawn": int(lat.size),
        "p50_ms": float(np.percentile(lat, 50) * 1e3),
        "p90_ms": float(np.percentile(lat, 90) * 1e3),
        "max_ms": float(lat.max() * 1e3),
        "cpu_fraction": cpu / wall,
        "frames_per_s": (page["frames"] - frames0) / wall,
        "wall_s": wall,
    }


def _alert(t: float, seq: int) -> OosAlert:
    """A synthetic OOS alert of plant time ``t`` (the page shows every alert it receives)."""
    return OosAlert(
        t=t,
        seq=seq,
        alert_id=f"bench-{t:.0f}",
        component="api",
        t_start_s=t,
        t_end_s=t + 10.0,
        peak_deviation_pct_w_w=2.0,
        limit_pct_w_w=0.75,
        cause="benchmark",
    )


def _plant_t(payload: bytes) -> float:
    import json

    return float(json.loads(payload)["t"])


def main(speeds: list[float]) -> None:
    why = browser_missing()
    if why:
        sys.exit(f"error: no headless browser, {why}")
    print(describe(), "| load", " ".join(f"{x:.2f}" for x in os.getloadavg()))
    tmp = Path(tempfile.mkdtemp(prefix="dashboard-bench-"))
    port = free_port()
    data = LineSpec.from_file(CONFIG).model_dump(mode="json")
    data["bus"] = {"mode": "router", "listen": [f"tcp/127.0.0.1:{port}"], "connect": []}
    data["state_dir"] = str(tmp / "state")
    spec = LineSpec.model_validate(data)
    spec_path = tmp / "line.yaml"
    spec_path.write_text(yaml.safe_dump(spec.model_dump(mode="json")))
    rec = read_recording(RECORDING)
    session = open_session(spec.bus)
    proc, url = start_dashboard(["--config", str(spec_path), "--port", str(free_port())])
    driver = open_browser(tmp / "profile")
    try:
        cold = load_dashboard(driver, url)
        warm = load_dashboard(driver, url)
        print(f"page load to first drawn panels: cold {cold:.2f} s, warm {warm:.2f} s")
        for i, speed in enumerate(speeds):
            if i:  # a fresh dashboard per speed: plant time starts again
                driver.quit()
                proc.terminate()
                proc.wait(10)
                proc, url = start_dashboard(
                    ["--config", str(spec_path), "--port", str(free_port())]
                )
                driver = open_browser(tmp / f"profile{i}")
                load_dashboard(driver, url)
            part = rec if speed >= 10 else first_seconds(rec, 60.0)
            r = run_speed(session, part, speed, driver, proc.pid)
            print(
                f"{speed:g}x: NIR message -> pixels p50 {r['p50_ms']:.0f} ms, "
                f"p90 {r['p90_ms']:.0f} ms, max {r['max_ms']:.0f} ms "
                f"({r['nir_drawn']} of {r['nir_published']} samples drawn); dashboard CPU "
                f"{100 * r['cpu_fraction']:.0f} % of one core over {r['wall_s']:.1f} s; page "
                f"drew {r['frames_per_s']:.0f} frames/s; alert message -> row in the page max "
                f"{r['alert_max_ms']:.0f} ms ({r['alerts_shown']} of {r['alerts_published']})"
            )
            OUT.mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(str(OUT / f"dashboard_{speed:g}x.png"))
    finally:
        driver.quit()
        proc.terminate()
        proc.wait(10)
        session.close()


if __name__ == "__main__":
    main([float(a) for a in sys.argv[1:]] or [1.0, 200.0])
