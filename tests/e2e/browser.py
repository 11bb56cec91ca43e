"""Headless Chromium on the dashboard (Selenium with Debian's ``chromium`` and
``chromium-driver``; ``make test`` installs them when it can), and what the page shows, read in
the browser.

The browser runs a watcher on every animation frame (:data:`WATCHER_JS`): it looks through the
page's DOM, shadow roots included (Bokeh renders each panel in one; the roots are collected
again every second), and notes the wall-clock time
(``Date.now()``, ms) at which each OOS alert row (``data-alert-id``) and each newest-NIR-sample
time (``data-nir-t``) first appeared, and each new newest ``t`` of one plot's data source;
:func:`sources` reads the plots' data sources. A test or a
benchmark compares those times with the times the messages were published on the same machine.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
#: the flags without which headless Chromium tries to reach the internet on start
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    "--window-size=1500,1150",
)

WATCHER_JS = """
window.__twin = {alerts: {}, nir: {}, frames: 0, roots: [], walked: 0, plotted: [],
                 plot: arguments[0]};
function twinPlotted(w, now) {
  const doc = window.Bokeh && Bokeh.documents && Bokeh.documents[0];
  const m = doc && doc.get_model_by_name(w.plot);
  if (!m) return;
  const t = (m.data instanceof Map) ? m.data.get('t') : m.data.t;
  const last = (t && t.length) ? t[t.length - 1] : null;
  if (last !== null && (w.plotted.length === 0 || w.plotted[w.plotted.length - 1][0] !== last))
    w.plotted.push([last, now]);
}
function twinRoots(root, out) {
  out.push(root);
  for (const e of root.querySelectorAll('*')) if (e.shadowRoot) twinRoots(e.shadowRoot, out);
  return out;
}
function twinFrame() {
  const now = Date.now();
  const w = window.__twin;
  if (now - w.walked > 1000) { w.roots = twinRoots(document, []); w.walked = now; }
  for (const root of w.roots) {
    for (const e of root.querySelectorAll('[data-alert-id]')) {
      const a = e.getAttribute('data-alert-id');
      if (!(a in w.alerts)) w.alerts[a] = now;
    }
    for (const e of root.querySelectorAll('[data-nir-t]')) {
      const t = e.getAttribute('data-nir-t');
      if (t !== '' && !(t in w.nir)) w.nir[t] = now;
    }
  }
  twinPlotted(w, now);
  w.frames += 1;
  requestAnimationFrame(twinFrame);
}
requestAnimationFrame(twinFrame);
"""

SOURCES_JS = """
const doc = window.Bokeh && Bokeh.documents && Bokeh.documents[0];
if (!doc) return null;
const out = {};
for (const m of doc.all_models) {
  if (m.name && typeof m.get_length === 'function') {
    const t = (m.data instanceof Map) ? m.data.get('t') : m.data.t;
    const n = m.get_length() || 0;
    out[m.name] = [n, (t && n) ? t[n - 1] : null];
  }
}
return out;
"""


def browser_missing() -> str | None:
    """Why no headless browser can run here (None: it can)."""
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    if missing:
        return (
            f"{', '.join(missing)} not installed (make test installs Debian's chromium and "
            f"chromium-driver with apt-get when run as root)"
        )
    return None


def open_browser(profile_dir: Path) -> Any:
    """A headless Chromium driven by the system's chromedriver (never a downloaded one)."""
    os.environ["SE_OFFLINE"] = "1"
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for flag in CHROMIUM_FLAGS:
        opts.add_argument(flag)
    opts.add_argument(f"--user-data-dir={profile_dir}")
    return webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=opts)


def load_dashboard(
    driver: Any, url: str, timeout_s: float = 30.0, plot: str = "measured:nir1"
) -> float:
    """Open the page, wait until BokehJS has built the document and the panels are drawn, start
    the watcher (following the newest ``t`` of the data source ``plot``); the load time, s
    (navigation start to the first drawn status panel)."""
    t0 = time.time()
    driver.get(url)
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if driver.execute_script(SOURCES_JS) and driver.execute_script(_HAS_STATUS_JS):
            break
        time.sleep(0.05)
    else:
        raise TimeoutError(f"the dashboard at {url} did not render in {timeout_s} s")
    loaded = time.time() - t0
    driver.execute_script(WATCHER_JS, plot)
    return loaded


_HAS_STATUS_JS = """
function has(root) {
  if (root.querySelector('.nir-t')) return true;
  for (const e of root.querySelectorAll('*')) if (e.shadowRoot && has(e.shadowRoot)) return true;
  return false;
}
return has(document);
"""


def seen(driver: Any) -> dict[str, Any]:
    """When (unix s) each alert id and each newest-NIR time first showed in the page, how many
    frames the page has drawn since the watcher started, and each newest ``t`` of the followed
    plot with when it came (``plotted``)."""
    raw = driver.execute_script(
        "const w = window.__twin;"
        "return {alerts: w.alerts, nir: w.nir, frames: w.frames, plotted: w.plotted};"
    )
    return {
        "alerts": {k: v / 1000.0 for k, v in raw["alerts"].items()},
        "nir": {k: v / 1000.0 for k, v in raw["nir"].items()},
        "frames": raw["frames"],
        "plotted": [(t, at / 1000.0) for t, at in raw["plotted"]],
    }


def sources(driver: Any) -> dict[str, tuple[int, float | None]]:
    """Rows and newest ``t`` of each named data source of the page, as BokehJS holds them."""
    return {k: tuple(v) for k, v in (driver.execute_script(SOURCES_JS) or {}).items()}


def external_urls(html: str, resource_urls: list[str], origin: str) -> list[str]:
    """Every URL the page references (``src``/``href`` attributes, absolute URLs in the text,
    resources the browser fetched) that is not on ``origin`` or relative."""
    found = re.findall(r"""(?:src|href)\s*=\s*["']([^"']+)["']""", html)
    found += re.findall(r"https?://[^\s\"'<>)]+", html)
    found += resource_urls
    return sorted({u for u in found if re.match(r"^[a-z]+://", u) and not u.startswith(origin)})


def start_dashboard(args: list[str], env: dict | None = None) -> tuple[subprocess.Popen, str]:
    """``twin dashboard ARGS`` as a child process; returns it and its URL once it serves."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "dashboard", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    lines = []
    for line in proc.stdout:
        lines.append(line)
        m = re.search(r"(http://\S+/)$", line.strip())
        if line.startswith("twin dashboard:") and m:
            # keep reading its output, or a full pipe would stall the server
            threading.Thread(target=proc.stdout.read, daemon=True).start()
            return proc, m.group(1)
    raise RuntimeError(f"twin dashboard exited {proc.wait()}: {''.join(lines)[-2000:]}")
