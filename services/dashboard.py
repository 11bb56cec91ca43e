"""``twin dashboard``: the live twin (or a recording) in the browser, a Bokeh server on loopback.

Why Bokeh server: it is a maintained library for live plots whose server ships its own
BokehJS with the Python package (no CDN: the page works on a plant network without internet),
keeps each browser's document in sync over one websocket, and streams only the changed data
sources; the plots are Bokeh models built in Python, no hand-written plotting JavaScript.

Data path (the page never waits on the bus):

    zenoh callback / recording thread --put--> queue --every period_ms--> DashboardState
        --view, PlotFeed (twin_core.online.dashboard_state)--> ColumnDataSources --> browser

The feed's thread only puts ``(key, message)`` on a queue (an OOS alert or divert command also
asks each page for a refresh at once, through Bokeh's thread-safe ``add_next_tick_callback``).
A periodic callback of each document (``period_ms``, 200 ms by default) drains the queue into
the one :class:`~twin_core.online.dashboard_state.DashboardState` and, when it changed, updates
the panels (the alerts first) and streams the new samples to each plot, replacing a plot's data
by its decimated window only once it holds ``max_points``
(:class:`~twin_core.online.dashboard_state.PlotFeed`), so a 200x replay costs the browser a
bounded amount of work per period and never lags more than a period plus the drawing.
"""

from __future__ import annotations

import html
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import DivertCommand, OosAlert
from services.bus import AlertFeed, Counters, TypedSubscriber
from services.recording import Recording, replay
from twin_core.online.dashboard_state import DashboardState, DashboardView, PlotFeed, Window

log = logging.getLogger(__name__)

#: how often each page takes the queued messages in, ms
DEFAULT_PERIOD_MS = 200
#: points per plotted series at most
DEFAULT_MAX_POINTS = 600
#: plant time shown in the plots, s (the last hour)
DEFAULT_WINDOW_S = 3600.0
#: how often the slow panels (header, estimates, findings, service health) are redrawn at most,
#: s: a changed panel makes the browser lay the page out again
SLOW_PANELS_S = 1.0
#: how often the plots get new data at most, s: a browser starved of CPU draws each update of
#: thousands of points slowly, and updates it has not drawn yet delay the alerts behind them
PLOT_PERIOD_S = 0.5

ALERT_COLOR = "#d62728"
DIVERT_COLOR = "#ff7f0e"
REFILL_COLOR = "#2ca02c"


@dataclass
class RejectedMessage:
    """A recorded message that did not validate (counted on the page as ``RejectedMessage``)."""

    t: float
    detail: str


class DashboardHub:
    """The one state behind every page: a queue the feeds put on, drained on the server's
    thread (:meth:`drain`), and the state's view cached per version."""

    def __init__(self, spec: LineSpec, max_points: int = DEFAULT_MAX_POINTS) -> None:
        self.spec = spec
        self.max_points = max_points
        self.state = DashboardState()
        self._queue: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._view: tuple[int, DashboardView] | None = None
        self.source = "bus"
        self._source_changed = False
        self._wake: dict[str, Callable[[], None]] = {}
        self._wake_lock = threading.Lock()
        self.finished = threading.Event()
        #: the bus feed's counters (received, rejected_*), when the page follows a bus
        self.bus_counters: Callable[[], dict[str, int]] = dict

    def put(self, key: str, msg: Any) -> None:
        """Hand one validated message over (any thread; never blocks). An alert or divert
        command asks every page for a refresh at once instead of at its next period."""
        self._queue.put((key, msg))
        if isinstance(msg, OosAlert | DivertCommand):
            with self._wake_lock:
                wakes = list(self._wake.values())
            for wake in wakes:
                wake()

    def on_urgent(self, page_id: str, wake: Callable[[], None] | None) -> None:
        """Register (or with None remove) a page's thread-safe request for a refresh."""
        with self._wake_lock:
            if wake is None:
                self._wake.pop(page_id, None)
            else:
                self._wake[page_id] = wake

    def set_source(self, text: str) -> None:
        """Say where the data comes from (any thread): shown in each page's header at its next
        refresh, e.g. that the twin was lost."""
        self.source = text
        self._source_changed = True

    def drain(self) -> int:
        """Move every queued message into the state (the server's thread); how many."""
        if self._source_changed:
            self._source_changed = False
            self.state.version += 1  # redraw the header
        n = 0
        while True:
            try:
                key, msg = self._queue.get_nowait()
            except queue.Empty:
                return n
            self.state.add(key, msg)
            n += 1

    def view(self) -> DashboardView:
        """The view of the current state but its series (computed once per state version; each
        page follows the series itself, :class:`PlotFeed`)."""
        if self._view is None or self._view[0] != self.state.version:
            self._view = (self.state.version, self.state.view(None))
        return self._view[1]


# ------------------------------------------------------------------------------------ feeds


class BusFeed:
    """Every message of the line on the bus to the hub: one typed subscriber on the line's keys
    (invalid ones counted and dropped, as a service does) and, for alerts and divert commands,
    the diverter's history as well (a page opened late shows the alerts raised before).
    :meth:`attach` moves it to another session (the twin restarted, ``services.bus.TwinLink``):
    a fresh time order per key (the new run's plant time starts over) and the alerts the page
    missed from the new run's history, each alert once."""

    def __init__(self, session: Any, hub: DashboardHub) -> None:
        self._hub = hub
        self.counters = Counters()
        self._sub: TypedSubscriber | None = None
        self._alerts = AlertFeed(None, hub.spec.name, hub.put, divert=True)
        hub.bus_counters = self.counters.snapshot
        if session is not None:
            self.attach(session)

    def attach(self, session: Any) -> None:
        """Follow the line on ``session``."""
        self.undeclare()
        self._sub = TypedSubscriber(
            session,
            keys.everything(self._hub.spec.name),
            self._on_message,
            allow_unknown=False,
            name="dashboard",
            counters=self.counters,
        )
        self._alerts.attach(session)

    def _on_message(self, key: str, msg: Any) -> None:
        if not isinstance(msg, OosAlert | DivertCommand):  # these come through the AlertFeed
            self._hub.put(key, msg)

    def undeclare(self) -> None:
        sub, self._sub = self._sub, None
        if sub is not None:
            try:
                sub.undeclare()
            except Exception as exc:  # noqa: BLE001 - a session already closed
                log.debug("undeclare: %s", exc)
        self._alerts.undeclare()


def recorded_decisions(rec: Recording, spec: LineSpec) -> Callable[[str, Any], list] | None:
    """What the twin would have decided on ``rec`` (``twin_core.online.recorded``), as a
    function of each recorded message giving the messages to show with it (predictions, OOS
    alerts, divert commands; ``("", None)`` at the end gives the last ones); None when the
    recording holds the twin's own decisions (a recording of a running twin: they are shown as
    recorded). Predictions are computed only when the recording holds none."""
    from schemas.messages import PredictedConcentration
    from services.oos import to_message
    from twin_core.online.recorded import RecordedDecisions

    line = spec.name
    recorded = {m.key for m in rec.messages}
    if keys.oos_alert(line) in recorded or keys.divert_command(line) in recorded:
        return None
    predicted_key = keys.predicted_concentration(line, "outlet")
    with_predictions = predicted_key not in recorded
    twin = RecordedDecisions(spec)
    seqs = {"alert": 0, "divert": 0, "predicted": 0}

    def derived(key: str, msg: Any) -> list[tuple[str, Any]]:
        preds, outs = twin.push(key, msg) if msg is not None else ([], twin.finish())
        shown: list[tuple[str, Any]] = []
        for t, conc in preds if with_predictions else []:
            for component, c in conc.items():
                shown.append(
                    (
                        predicted_key,
                        PredictedConcentration(
                            t=t,
                            seq=seqs["predicted"],
                            model=twin.blender.kernel.model_name,
                            component=component,
                            concentration_pct_w_w=c,
                        ),
                    )
                )
                seqs["predicted"] += 1
        for o in outs:
            out_key = keys.oos_alert(line) if o.kind == "alert" else keys.divert_command(line)
            shown.append((out_key, to_message(o, seqs[o.kind])))
            seqs[o.kind] += 1
        return shown

    return derived


def start_recording_feed(
    rec: Recording, hub: DashboardHub, speed: float, should_stop: Callable[[], bool]
) -> threading.Thread:
    """Replay ``rec`` into the hub at ``speed`` times real time on a thread
    (``services.recording.replay``: the same schedule as ``twin replay``), with what the twin
    would have decided on it (:func:`recorded_decisions`) as the replay reaches it, and say so
    in the page's header; the hub's :attr:`~DashboardHub.finished` is set at its end."""
    derived = recorded_decisions(rec, hub.spec)

    def publish(key: str, payload: bytes) -> None:
        model = keys.model_for_key(key)
        if model is None:
            return
        try:
            msg = model.model_validate_json(payload)
        except ValueError as exc:  # a recorded message that does not validate: counted, skipped
            hub.put(key, RejectedMessage(t=0.0, detail=str(exc)))
            return
        hub.put(key, msg)
        for k, m in derived(key, msg) if derived is not None else []:
            hub.put(k, m)

    def run() -> None:
        try:
            replay(rec, publish, speed=speed, should_stop=should_stop)
            for k, m in derived("", None) if derived is not None and not should_stop() else []:
                hub.put(k, m)
        finally:
            hub.finished.set()

    decisions = (
        "the twin's decisions as recorded"
        if derived is None
        else "alerts and divert windows computed by the twin's diverter from the recording "
        "(declared model, no adoption)"
    )
    hub.source = f"recording {rec.path.name if rec.path else ''} at {speed:g}x; {decisions}"
    thread = threading.Thread(target=run, name="dashboard-recording", daemon=True)
    thread.start()
    return thread


# ------------------------------------------------------------------------------------ page


def _table(header: list[str], rows: list[list[str]], attrs: list[str] | None = None) -> str:
    """An HTML table (cells already escaped); ``attrs``: extra attributes of each row."""
    head = "".join(f"<th>{h}</th>" for h in header)
    body = "".join(
        f"<tr {attrs[i] if attrs else ''}>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>"
        for i, r in enumerate(rows)
    )
    return f"<table class='twin'><tr>{head}</tr>{body}</table>"


def _esc(value: Any) -> str:
    return html.escape(str(value))


def alerts_html(view: DashboardView) -> str:
    """The OOS alerts, newest first; each row carries ``data-alert-id``."""
    rows = sorted(view.alerts, key=lambda a: a["t_start_s"], reverse=True)
    if not rows:
        return "<b>OOS alerts</b><p>none</p>"
    cells = [
        [
            _esc(a["alert_id"]),
            f"{a['t_start_s']:.0f}-{a['t_end_s']:.0f}",
            f"{a['peak_deviation_pct_w_w']:+.2f} (limit {a['limit_pct_w_w']:.2f})",
            _esc(a["cause"]),
        ]
        for a in rows
    ]
    attrs = [f"class='alert' data-alert-id='{_esc(a['alert_id'])}'" for a in rows]
    return "<b>OOS alerts</b>" + _table(
        ["alert", "window, s", "peak deviation, % w/w", "cause"], cells, attrs
    )


def _window_text(w: Window) -> str:
    return f"{w.t_start_s:.0f}-{w.t_end_s:.0f} s"


def diverter_html(view: DashboardView) -> str:
    """The gate now and its upcoming divert windows."""
    d = view.diverter
    state = (
        f"<span class='diverting'>DIVERTING ({_window_text(d.current)})</span>"
        if d.current is not None
        else "<span class='accepting'>accepting</span>"
    )
    upcoming = ", ".join(_window_text(w) for w in d.upcoming[:8]) or "none"
    return f"<b>Diverter</b>: {state}<br>upcoming divert windows: {upcoming}"


def blender_html(view: DashboardView) -> str:
    """The blender's model and the RTD estimates, newest first."""
    rows = [
        [
            f"{e['t']:.0f}",
            _esc(e["model"]),
            f"{e['mean_residence_time_s']:.1f}",
            _esc(", ".join(f"{k}={v:.4g}" for k, v in e["params"].items())),
            "" if e["applies_from_s"] is None else f"{e['applies_from_s']:.0f}",
        ]
        for e in reversed(view.rtd_estimates[-10:])
    ]
    table = (
        _table(["t, s", "model", "MRT, s", "parameters", "applies from, s"], rows)
        if rows
        else "<p>no RTD estimate yet</p>"
    )
    model = _esc(view.blender_model or "no prediction yet")
    m = view.model_in_use
    if m is not None:
        point = ", ".join(
            f"{label} {m[k]:g}"
            for k, label in (("blade_speed_rpm", "blade rpm"), ("throughput_kg_h", "kg/h"))
            if m[k] is not None
        )
        model = (
            f"{_esc(m['kind'])} {_esc(m['name'])} from {m['applies_from_s']:.0f} s "
            f"({_esc(m['reason'])}{'; ' + point if point else ''}; MRT "
            f"{m['mean_residence_time_s']:.1f} s)"
        )
    return f"<b>Blender model</b>: {model}<br><b>RTD estimates</b>{table}"


def findings_html(view: DashboardView) -> str:
    """The close-loop findings, newest first, with their status."""
    rows = [
        [
            _esc(f["finding_id"]),
            f"<span class='status-{_esc(f['status'])}'>{_esc(f['status'])}</span>",
            f"{f['t_start_s']:.0f}-{f['t_end_s']:.0f}",
            _esc(", ".join(f["effects"]) or "-"),
            "yes" if f["product_at_risk"] else "no",
        ]
        for f in reversed(view.findings[-10:])
    ]
    if not rows:
        return "<b>Close-loop findings</b><p>none yet</p>"
    return "<b>Close-loop findings</b>" + _table(
        ["finding", "status", "window, s", "effects", "product at risk"], rows
    )


def health_html(view: DashboardView, now_unix: float, own: dict[str, int] | None = None) -> str:
    """Each service's health (state, plant time, age of the report, counters), the messages the
    page has seen by type and the dashboard's own bus counters ``own`` (received, rejected)."""
    rows = [
        [
            _esc(name),
            _esc(h["state"]),
            f"{h['t']:.0f}",
            f"{max(0.0, now_unix - h['wall_time_unix_s']):.0f}",
            _esc(", ".join(f"{k}={v}" for k, v in sorted(h["counters"].items()))),
        ]
        for name, h in view.health.items()
    ]
    table = (
        _table(["service", "state", "plant t, s", "report age, s", "counters"], rows)
        if rows
        else "<p>no service reports (a recording, or no twin running)</p>"
    )
    counts = ", ".join(f"{k}={v}" for k, v in sorted(view.counters.items()))
    text = f"<b>Services</b>{table}<b>Messages seen</b>: {_esc(counts) or 'none'}"
    if own:
        bus = ", ".join(f"{k}={v}" for k, v in sorted(own.items()))
        text += f"<br><b>Dashboard on the bus</b>: {_esc(bus)}"
    return text


def status_html(hub: DashboardHub, view: DashboardView) -> str:
    """The header: line, source, plant time, newest NIR sample time (``data-nir-t``)."""
    nir = hub.state.series(f"measured:{hub.spec.sensor.id}")[0]
    nir_t = float(nir[-1]) if nir.size else None
    nir_text = "-" if nir_t is None else f"{nir_t:.0f} s"
    return (
        f"<span class='title'>powder-twin {_esc(hub.spec.name)}</span> &middot; "
        f"{_esc(hub.source)} &middot; plant time {view.now_s:.0f} s &middot; "
        f"<span class='nir-t' data-nir-t='{'' if nir_t is None else f'{nir_t:g}'}'>"
        f"newest NIR sample {nir_text}</span>"
    )


STYLE = """
<style>
table.twin { border-collapse: collapse; font-size: 12px; margin: 2px 0 6px 0; }
table.twin td, table.twin th { border: 1px solid #ccc; padding: 1px 6px; text-align: left; }
tr.alert td { background: #fde0e0; }
.diverting { color: #b00; font-weight: bold; }
.accepting { color: #070; }
.title { font-weight: bold; font-size: 16px; }
.status-unexplained, .status-partly_explained { color: #b00; }
.status-consistent, .status-explained { color: #070; }
</style>
"""


class Page:
    """The Bokeh document of one browser: plots and panels, refreshed from the hub; the plots at
    most every ``plot_period_s``, the slow panels (header, estimates, findings, service health)
    at most every ``slow_panels_s``."""

    def __init__(
        self,
        doc: Any,
        hub: DashboardHub,
        period_ms: int,
        window_s: float,
        slow_panels_s: float = SLOW_PANELS_S,
        plot_period_s: float = PLOT_PERIOD_S,
    ) -> None:
        from bokeh.layouts import column, row
        from bokeh.models import ColumnDataSource, Div

        self.hub = hub
        self.window_s = window_s
        self.version = -1
        spec = hub.spec
        limits = spec.limits(spec.sensor.component)
        self.sources: dict[str, ColumnDataSource] = {}
        self.conc = self._concentration_figure(spec, limits)
        self.flows = self._flow_figure(spec)
        self.rtd = self._rtd_figure(spec)
        self.drawn_estimate: tuple[float, str] | None = None
        self.panels_at = -math.inf
        self.slow_panels_s = slow_panels_s
        self.plots_at = -math.inf
        self.plot_period_s = plot_period_s
        self.feeds = {
            name: PlotFeed(hub.max_points, window_s)
            for name in self.sources
            if name.split(":")[0] in ("measured", "predicted", "flow")
        }
        self.divs = {
            name: Div(name=name, text="", sizing_mode="stretch_width", disable_math=True)
            for name in ("status", "diverter", "alerts", "blender", "findings", "health")
        }
        style = Div(text=STYLE)
        doc.title = f"powder-twin {spec.name}"
        doc.add_root(
            column(
                style,
                self.divs["status"],
                row(self.conc, column(self.divs["diverter"], self.divs["alerts"], width=520)),
                row(self.flows, column(self.divs["blender"], self.rtd, width=520)),
                self.divs["findings"],
                self.divs["health"],
                sizing_mode="stretch_width",
            )
        )
        self.refresh()
        doc.add_periodic_callback(self.refresh, period_ms)
        # add_next_tick_callback is the one thread-safe way into a Bokeh document
        hub.on_urgent(id_of(doc), lambda: doc.add_next_tick_callback(self.refresh_alerts))
        doc.on_session_destroyed(lambda ctx: hub.on_urgent(id_of(doc), None))

    def _source(self, name: str, columns: tuple[str, ...]) -> Any:
        from bokeh.models import ColumnDataSource

        src = ColumnDataSource({c: [] for c in columns}, name=name)
        self.sources[name] = src
        return src

    def _concentration_figure(self, spec: LineSpec, limits: Any) -> Any:
        from bokeh.models import Span

        comp = spec.sensor.component
        fig = _time_figure("concentration", f"outlet {comp}: measured vs predicted, % w/w", 340)
        alerts = self._source("alert_windows", ("x0", "x1"))
        fig.vstrip(x0="x0", x1="x1", source=alerts, color=ALERT_COLOR, alpha=0.15)
        diverts = self._source("divert_windows", ("x0", "x1"))
        fig.vstrip(x0="x0", x1="x1", source=diverts, color=DIVERT_COLOR, alpha=0.25)
        pred = self._source(f"predicted:{comp}", ("t", "y", "lower", "upper"))
        fig.varea(x="t", y1="lower", y2="upper", source=pred, color="#1f77b4", alpha=0.2)
        fig.line("t", "y", source=pred, color="#1f77b4", line_width=2, legend_label="predicted")
        src = self._source(f"measured:{spec.sensor.id}", ("t", "y"))
        fig.scatter("t", "y", source=src, size=3, color="black", legend_label="NIR measured")
        if limits is not None:
            fig.add_layout(
                Span(location=limits.target_pct_w_w, dimension="width", line_dash="dashed")
            )
            for bound in (limits.lower_pct_w_w, limits.upper_pct_w_w):
                fig.add_layout(Span(location=bound, dimension="width", line_color=ALERT_COLOR))
        fig.legend.location = "top_left"
        return fig

    def _flow_figure(self, spec: LineSpec) -> Any:
        from bokeh.palettes import Category10_10

        fig = _time_figure("flows", "feeder mass flows, kg/h (refills shaded)", 300)
        fig.x_range = self.conc.x_range
        refills = self._source("refill_windows", ("x0", "x1"))
        fig.vstrip(x0="x0", x1="x1", source=refills, color=REFILL_COLOR, alpha=0.2)
        for i, feeder in enumerate(spec.feeders):
            src = self._source(f"flow:{feeder.id}", ("t", "y"))
            fig.line("t", "y", source=src, color=Category10_10[i % 10], legend_label=feeder.id)
        fig.legend.location = "top_left"
        return fig

    def _rtd_figure(self, spec: LineSpec) -> Any:
        """E(t) of the blender: the declared model and the newest RTD estimate."""
        from bokeh.plotting import figure

        from twin_core.online.blender import declared_kernel, tick_grid

        fig = figure(
            name="rtd",
            title="blender E(t), 1/s: declared and newest RTD estimate",
            height=220,
            width=500,
            x_axis_label="time since entry, s",
            tools="reset,save",
        )
        t = tick_grid(spec.dt_s, spec.blender.kernel_s)
        declared = self._source("rtd_declared", ("t", "e"))
        declared.data = {"t": t.tolist(), "e": declared_kernel(spec).tolist()}
        fig.line(
            "t", "e", source=declared, color="gray", line_dash="dashed", legend_label="declared"
        )
        newest = self._source("rtd_estimate", ("t", "e"))
        fig.line("t", "e", source=newest, color="#1f77b4", line_width=2, legend_label="estimate")
        fig.legend.location = "top_right"
        return fig

    def _show_newest_estimate(self, view: DashboardView) -> None:
        """Draw the E(t) of the newest RTD estimate, once per new estimate."""
        from twin_core.online.blender import tick_grid
        from twin_core.rtd.models import model_e

        if not view.rtd_estimates:
            return
        e = view.rtd_estimates[-1]
        if (e["t"], e["model"]) == self.drawn_estimate:
            return
        self.drawn_estimate = (e["t"], e["model"])
        t = tick_grid(self.hub.spec.dt_s, self.hub.spec.blender.kernel_s)
        try:
            curve = model_e(e["model"], e["params"], t)
        except (TypeError, ValueError) as exc:  # a model or parameters this twin does not know
            log.warning("cannot draw the RTD estimate %s: %s", e["model"], exc)
            return
        self.sources["rtd_estimate"].data = {"t": t.tolist(), "e": curve.tolist()}

    def refresh_alerts(self) -> None:
        """Take the queued messages in and show the alerts and the diverter only: a small
        change that reaches the browser without waiting for the plots (the periodic
        :meth:`refresh` draws the rest)."""
        self.hub.drain()
        self._show_alerts(self.hub.view())

    def _show_alerts(self, view: DashboardView) -> None:
        self.divs["alerts"].text = alerts_html(view)
        self.divs["diverter"].text = diverter_html(view)
        self.sources["alert_windows"].data = _strips(
            [(a["t_start_s"], a["t_end_s"]) for a in view.alerts]
        )
        self.sources["divert_windows"].data = _strips(
            [(w.t_start_s, w.t_end_s) for w in view.divert_windows]
        )

    def _show_series(self) -> None:
        """Send each plot its new samples, or its decimated window (:class:`PlotFeed`)."""
        for name, feed in self.feeds.items():
            change = feed.update(self.hub.state.series(name))
            if change is not None and change[0] == "stream":
                self.sources[name].stream(change[1])
            elif change is not None:
                self.sources[name].data = change[1]

    def refresh(self) -> None:
        """Take the queued messages in; redraw what changed (the server's thread)."""
        self.hub.drain()
        if self.hub.state.version == self.version:
            return
        self.version = self.hub.state.version
        view = self.hub.view()
        self._show_alerts(view)
        self.sources["refill_windows"].data = _strips(
            [(w.t_start_s, w.t_end_s) for ws in view.refill_windows.values() for w in ws]
        )
        now = time.time()
        if now - self.plots_at >= self.plot_period_s:
            self.plots_at = now
            self._show_series()
        else:  # the plots wait for their period: come back for them
            self.version = -1
        self._show_newest_estimate(view)
        if now - self.panels_at >= self.slow_panels_s:  # estimates, findings, health
            self.panels_at = now
            self.divs["status"].text = status_html(self.hub, view)
            self.divs["blender"].text = blender_html(view)
            self.divs["findings"].text = findings_html(view)
            self.divs["health"].text = health_html(view, now, self.hub.bus_counters())


def id_of(doc: Any) -> str:
    """A key for one page's document."""
    return str(id(doc))


def _time_figure(name: str, title: str, height: int) -> Any:
    """A plot over plant time (pan and wheel-zoom along time only)."""
    from bokeh.plotting import figure

    return figure(
        name=name,
        title=title,
        height=height,
        width=900,
        x_axis_label="plant time, s",
        tools="xpan,xwheel_zoom,reset,save",
    )


def _strips(windows: list[tuple[float, float]]) -> dict[str, list[float]]:
    return {"x0": [w[0] for w in windows], "x1": [w[1] for w in windows]}


# ------------------------------------------------------------------------------------ server


def make_server(
    hub: DashboardHub,
    *,
    address: str = "127.0.0.1",
    port: int = 5006,
    period_ms: int = DEFAULT_PERIOD_MS,
    window_s: float = DEFAULT_WINDOW_S,
) -> Any:
    """A Bokeh server (not started) serving the dashboard at ``/`` on ``address:port``; its
    BokehJS comes from the bokeh package (``resources="server"``), nothing from the internet."""
    from bokeh.application import Application
    from bokeh.application.handlers.function import FunctionHandler
    from bokeh.server.server import Server

    def make_document(doc: Any) -> None:
        Page(doc, hub, period_ms, window_s)

    origins = [f"{address}:{port}"] + ([f"localhost:{port}"] if address == "127.0.0.1" else [])
    return Server(
        {"/": Application(FunctionHandler(make_document))},
        address=address,
        port=port,
        allow_websocket_origin=origins,
        num_procs=1,
    )


def is_loopback(address: str) -> bool:
    """Whether ``address`` is a loopback address (``127.0.0.0/8``, ``::1``, ``localhost``)."""
    import ipaddress

    if address == "localhost":
        return True
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return False
