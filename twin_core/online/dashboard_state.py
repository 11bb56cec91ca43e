"""What the operator's dashboard shows, kept from the twin's typed messages (pure computation).

:class:`DashboardState` takes the messages of one line (``add(key, msg)``: feeder flows, NIR
measurements, predictions, events, OOS alerts, divert commands, RTD estimates, close-loop
findings, service health) and keeps them in bounded ring buffers, so a twin that runs for days
holds a fixed amount of memory. :func:`decimate_min_max` thins a series to a maximum number of
points for a plot while keeping every excursion visible (the extremes of each bucket),
:class:`PlotFeed` tells a plot what to append or replace at each refresh, and
:meth:`DashboardState.diverter` tells whether the gate diverts now and which divert windows are
still to come. Nothing here draws or talks to a bus: the dashboard service turns a
:class:`DashboardView` into pixels.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: samples a time series keeps (about 5.5 h at the line's 1 Hz)
DEFAULT_CAPACITY = 20_000
#: alerts, divert commands, RTD estimates and findings kept
DEFAULT_EVENTS_KEPT = 200


def decimate_min_max(t: np.ndarray, y: np.ndarray, max_points: int) -> tuple[np.ndarray, ...]:
    """At most ``max_points`` samples of the series ``(t, y)`` (``t`` increasing), keeping the
    shape a plot of all samples shows.

    The samples are split into ``b = (max_points - 2) // 2`` buckets of ``ceil(n / b)``
    consecutive samples (the last one shorter); of each bucket the minimum and the maximum of ``y`` are kept, in time order (min-max
    decimation, the two-point case of the M4 aggregation of Jugel et al., *M4: A
    Visualization-Oriented Time Series Data Aggregation*, PVLDB 7(10), 2014: a line drawn
    through the kept points covers the same pixel rows per column as one through all of them),
    and so are the first and the newest sample (the plot's ends). A series with at most
    ``max_points`` samples is returned as it is; a sample that is NaN is dropped first.
    """
    if max_points < 4:
        raise ValueError(f"max_points must be >= 4, got {max_points}")
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    keep = ~np.isnan(y)
    t, y = t[keep], y[keep]
    if t.size <= max_points:
        return t, y
    n_buckets = (max_points - 2) // 2
    size = -(-t.size // n_buckets)  # samples per bucket (the last one padded with its edge)
    buckets = np.pad(y, (0, n_buckets * size - t.size), mode="edge").reshape(n_buckets, size)
    first = np.arange(n_buckets) * size
    picked = np.concatenate(
        ([0, t.size - 1], first + buckets.argmin(axis=1), first + buckets.argmax(axis=1))
    )
    idx = np.unique(np.minimum(picked, t.size - 1))
    return t[idx], y[idx]


class Ring:
    """A bounded time series: the last ``capacity`` samples of ``(t, value...)`` in a
    preallocated array, as numpy columns on request."""

    def __init__(self, n_values: int = 1, capacity: int = DEFAULT_CAPACITY) -> None:
        self._data = np.full((capacity, 1 + n_values), np.nan)
        self._next = 0
        self._count = 0
        self.n_values = n_values

    def append(self, t: float, *values: float | None) -> None:
        if len(values) != self.n_values:
            raise ValueError(f"values must have {self.n_values} entries, got {len(values)}")
        self._data[self._next] = (t, *(np.nan if v is None else v for v in values))
        self._next = (self._next + 1) % len(self._data)
        self._count = min(self._count + 1, len(self._data))

    def __len__(self) -> int:
        return self._count

    def columns(self) -> np.ndarray:
        """``(1 + n_values, n)``: times, then each value column, oldest first."""
        if self._count < len(self._data):
            return self._data[: self._count].T.copy()
        return np.roll(self._data, -self._next, axis=0).T


@dataclass(frozen=True)
class Window:
    """A plant-time window ``[t_start_s, t_end_s]`` with the id and text it came with."""

    t_start_s: float
    t_end_s: float
    ident: str
    text: str = ""


@dataclass(frozen=True)
class DiverterState:
    """The gate at plant time ``t_s``: diverting or not, the windows still to come (start after
    ``t_s``) and the one it is in, if any."""

    t_s: float
    diverting: bool
    current: Window | None
    upcoming: list[Window]


@dataclass
class DashboardView:
    """One decimated picture of the state, ready to draw (plain lists and dicts)."""

    now_s: float
    series: dict[str, dict[str, list[float]]]
    alerts: list[dict[str, Any]]
    divert_windows: list[Window]
    refill_windows: dict[str, list[Window]]
    diverter: DiverterState
    blender_model: str | None
    #: the newest ``BlenderModelInUse`` (kind, name, reason, applies from, operating point)
    model_in_use: dict[str, Any] | None
    rtd_estimates: list[dict[str, Any]]
    findings: list[dict[str, Any]]
    health: dict[str, dict[str, Any]]
    counters: dict[str, int]


def _message_kind(msg: Any) -> str:
    return type(msg).__name__


@dataclass
class DashboardState:
    """The twin of one line as its dashboard shows it, fed message by message.

    ``add(key, msg)`` dispatches on the message's type (``schemas.messages`` /
    ``schemas.closeloop`` models, by class name so this module needs no bus); a type the
    dashboard does not show is only counted. :attr:`version` grows with every message kept,
    so a drawer redraws only when something changed.
    """

    capacity: int = DEFAULT_CAPACITY
    events_kept: int = DEFAULT_EVENTS_KEPT
    version: int = 0
    now_s: float = 0.0
    counters: Counter = field(default_factory=Counter)
    _series: dict[str, Ring] = field(default_factory=dict)
    _alerts: dict[str, Any] = field(default_factory=dict)
    _diverts: dict[str, Any] = field(default_factory=dict)
    _refills: dict[str, deque] = field(default_factory=dict)
    _open_refill: dict[str, float] = field(default_factory=dict)
    _rtd: deque = field(default_factory=deque)
    _findings: deque = field(default_factory=deque)
    _health: dict[str, Any] = field(default_factory=dict)
    _blender_model: str | None = None
    _model_in_use: Any = None

    # ----------------------------------------------------------------------------- input

    def add(self, key: str, msg: Any) -> None:
        """Keep one message (``key``: its key expression, ``msg``: its validated model)."""
        kind = _message_kind(msg)
        self.counters[kind] += 1
        handler = getattr(self, f"_on_{kind}", None)
        if handler is None:
            return
        if kind != "ServiceHealth":
            self.now_s = max(self.now_s, float(msg.t))
        handler(key, msg)
        self.version += 1

    def add_all(self, items: Iterable[tuple[str, Any]]) -> None:
        for key, msg in items:
            self.add(key, msg)

    def _ring(self, name: str, n_values: int = 1) -> Ring:
        ring = self._series.get(name)
        if ring is None:
            ring = self._series[name] = Ring(n_values, self.capacity)
        return ring

    def _on_FeederFlow(self, key: str, msg: Any) -> None:  # noqa: N802 - dispatch by class name
        self._ring(f"flow:{key.split('/')[-2]}").append(msg.t, msg.mass_flow_kg_h)
        self._refill_state(key.split("/")[-2], msg.t, msg.refilling)

    def _on_MeasuredConcentration(self, key: str, msg: Any) -> None:  # noqa: N802
        value = msg.concentration_pct_w_w if msg.quality != "bad" else None
        self._ring(f"measured:{msg.sensor}").append(msg.t, value)

    def _on_PredictedConcentration(self, key: str, msg: Any) -> None:  # noqa: N802
        self._ring(f"predicted:{msg.component}", 3).append(
            msg.t, msg.concentration_pct_w_w, msg.lower_pct_w_w, msg.upper_pct_w_w
        )
        self._blender_model = msg.model

    def _on_BlenderModelInUse(self, key: str, msg: Any) -> None:  # noqa: N802
        self._model_in_use = msg

    def _on_Event(self, key: str, msg: Any) -> None:  # noqa: N802
        if msg.kind == "refill_start":
            self._refill_state(msg.source, msg.t, True)
        elif msg.kind == "refill_stop":
            self._refill_state(msg.source, msg.t, False)

    def _refill_state(self, feeder: str, t: float, refilling: bool) -> None:
        """Open a refill window at its first sign (flag or event), close it at its first end."""
        start = self._open_refill.get(feeder)
        if refilling and start is None:
            self._open_refill[feeder] = t
        elif not refilling and start is not None:
            del self._open_refill[feeder]
            windows = self._refills.setdefault(feeder, deque(maxlen=self.events_kept))
            windows.append(Window(start, t, f"{feeder}-refill-{start:g}", "refill"))

    def _on_OosAlert(self, key: str, msg: Any) -> None:  # noqa: N802
        self._alerts[msg.alert_id] = msg
        _trim(self._alerts, self.events_kept)

    def _on_DivertCommand(self, key: str, msg: Any) -> None:  # noqa: N802
        self._diverts[msg.command_id] = msg
        _trim(self._diverts, self.events_kept)

    def _on_RtdEstimate(self, key: str, msg: Any) -> None:  # noqa: N802
        _bounded_append(self._rtd, msg, self.events_kept)

    def _on_ModelFinding(self, key: str, msg: Any) -> None:  # noqa: N802
        _bounded_append(self._findings, msg, self.events_kept)

    def _on_ServiceHealth(self, key: str, msg: Any) -> None:  # noqa: N802
        self._health[msg.service] = msg

    # ----------------------------------------------------------------------------- output

    def series(self, name: str) -> np.ndarray:
        """The kept samples of a series (``flow:<feeder>``, ``measured:<sensor>``,
        ``predicted:<component>``, with lower and upper bound): rows t, value(s)."""
        ring = self._series.get(name)
        return ring.columns() if ring is not None else np.empty((2, 0))

    def series_names(self) -> list[str]:
        return sorted(self._series)

    def divert_windows(self) -> list[Window]:
        """The gate's divert windows in force: each ``divert`` command's window unless an
        ``accept`` command for the same window came later (by ``(t, seq)``), by start time. A
        later command of the same alert (``alert_id``: the final window after the early,
        provisional one) replaces it from its decision time ``t`` on: the earlier window ends
        there (what passed before was diverted under it)."""
        accepted = {
            (c.t_start_s, c.t_end_s): (c.t, c.seq)
            for c in self._diverts.values()
            if c.action == "accept"
        }
        replaced: dict[str, float] = {}
        by_alert: dict[str, list[Any]] = {}
        for c in self._diverts.values():
            if getattr(c, "alert_id", None):
                by_alert.setdefault(c.alert_id, []).append(c)
        for cmds in by_alert.values():
            cmds.sort(key=lambda c: (c.t, c.seq))
            for earlier, later in zip(cmds, cmds[1:], strict=False):
                replaced[earlier.command_id] = float(later.t)
        windows = []
        for c in self._diverts.values():
            end = min(c.t_end_s, replaced.get(c.command_id, math.inf))
            if (
                c.action == "divert"
                and end >= c.t_start_s
                and accepted.get((c.t_start_s, c.t_end_s), (-1, -1)) < (c.t, c.seq)
            ):
                windows.append(Window(c.t_start_s, end, c.command_id, c.reason))
        return sorted(windows, key=lambda w: (w.t_start_s, w.ident))

    def diverter(self, t_s: float | None = None) -> DiverterState:
        """The gate at plant time ``t_s`` (default: the newest plant time seen)."""
        now = self.now_s if t_s is None else t_s
        windows = self.divert_windows()
        current = next((w for w in windows if w.t_start_s <= now <= w.t_end_s), None)
        upcoming = [w for w in windows if w.t_start_s > now]
        return DiverterState(now, current is not None, current, upcoming)

    def refill_windows(self) -> dict[str, list[Window]]:
        """Each feeder's refill windows; one still open ends at the newest plant time."""
        out = {f: list(ws) for f, ws in self._refills.items()}
        for feeder, start in self._open_refill.items():
            out.setdefault(feeder, []).append(
                Window(start, max(start, self.now_s), f"{feeder}-refill-{start:g}", "refilling")
            )
        return out

    def view(self, max_points: int | None) -> DashboardView:
        """The state as plain data, each series decimated to at most ``max_points`` points
        (:func:`decimate_columns`; ``None``: no series, for a drawer that follows them with
        :class:`PlotFeed`)."""
        names = self.series_names() if max_points is not None else []
        return DashboardView(
            now_s=self.now_s,
            series={name: decimate_columns(self.series(name), max_points) for name in names},
            alerts=[_alert_row(a) for a in self._alerts.values()],
            divert_windows=self.divert_windows(),
            refill_windows=self.refill_windows(),
            diverter=self.diverter(),
            blender_model=self._blender_model,
            model_in_use=None
            if self._model_in_use is None
            else _fields(self._model_in_use, MODEL_FIELDS),
            rtd_estimates=[_rtd_row(e) for e in self._rtd],
            findings=[_finding_row(f) for f in self._findings],
            health={name: _health_row(h) for name, h in sorted(self._health.items())},
            counters=dict(self.counters),
        )


def columns_dict(cols: np.ndarray) -> dict[str, list[float]]:
    """Series columns (rows t, y[, lower, upper]) as a plot's data: samples with a NaN value
    left out; a missing bound is the value itself (no band there)."""
    cols = cols[:, ~np.isnan(cols[1])]
    out = {"t": cols[0].tolist(), "y": cols[1].tolist()}
    if cols.shape[0] == 4:
        out["lower"] = np.where(np.isnan(cols[2]), cols[1], cols[2]).tolist()
        out["upper"] = np.where(np.isnan(cols[3]), cols[1], cols[3]).tolist()
    return out


def decimate_columns(cols: np.ndarray, max_points: int) -> dict[str, list[float]]:
    """:func:`decimate_min_max` of series columns, the bounds (if any) at the kept times."""
    cols = cols[:, ~np.isnan(cols[1])]
    t, _ = decimate_min_max(cols[0], cols[1], max_points)
    return columns_dict(cols[:, np.isin(cols[0], t)])


class PlotFeed:
    """What one plot of one series needs at each refresh to show the series' newest
    ``window_s`` of plant time with at most ``max_points`` points, sending little.

    New samples are streamed (appended) while the plot holds fewer than ``max_points``; then it
    is replaced by the window decimated to ``max_points // 2`` (:func:`decimate_columns`), so a
    replacement comes once per ``max_points // 2`` new samples and a refresh otherwise carries
    only what is new.
    """

    def __init__(self, max_points: int, window_s: float) -> None:
        self.max_points = max_points
        self.window_s = window_s
        self.n_shown = 0
        self.last_t = -np.inf

    def update(self, cols: np.ndarray) -> tuple[str, dict[str, list[float]]] | None:
        """``("stream", new samples)``, ``("replace", all to show)`` or None (nothing new) for
        the series' columns ``cols`` (rows t, value(s); :meth:`DashboardState.series`)."""
        new = cols[:, cols[0] > self.last_t]
        if new.shape[1] == 0:
            return None
        self.last_t = float(new[0, -1])
        if self.n_shown + new.shape[1] <= self.max_points:
            data = columns_dict(new)
            self.n_shown += len(data["t"])
            return "stream", data
        shown = cols[:, cols[0] >= self.last_t - self.window_s]
        data = decimate_columns(shown, self.max_points // 2)
        self.n_shown = len(data["t"])
        return "replace", data


def _trim(items: dict[str, Any], kept: int) -> None:
    while len(items) > kept:
        del items[next(iter(items))]


def _bounded_append(items: deque, item: Any, kept: int) -> None:
    items.append(item)
    while len(items) > kept:
        items.popleft()


#: the fields of each kind of event the view carries
ALERT_FIELDS = (
    "alert_id", "t", "component", "t_start_s", "t_end_s", "peak_deviation_pct_w_w",
    "limit_pct_w_w", "cause",
)  # fmt: skip
RTD_FIELDS = (
    "t", "model", "mean_residence_time_s", "params", "pulse_t_s", "rmse", "applies_from_s",
)  # fmt: skip
FINDING_FIELDS = (
    "finding_id", "t", "status", "t_start_s", "t_end_s", "product_at_risk", "remaining",
)  # fmt: skip

MODEL_FIELDS = (
    "kind", "name", "reason", "applies_from_s", "blade_speed_rpm", "throughput_kg_h",
    "mean_residence_time_s", "rule",
)  # fmt: skip


def _fields(msg: Any, names: tuple[str, ...]) -> dict[str, Any]:
    return {name: getattr(msg, name) for name in names}


def _alert_row(a: Any) -> dict[str, Any]:
    return _fields(a, ALERT_FIELDS)


def _rtd_row(e: Any) -> dict[str, Any]:
    return {**_fields(e, RTD_FIELDS), "params": dict(e.params)}


def _finding_row(f: Any) -> dict[str, Any]:
    return {**_fields(f, FINDING_FIELDS), "effects": [e.label for e in f.effects]}


def _health_row(h: Any) -> dict[str, Any]:
    return {
        "state": h.state,
        "t": h.t,
        "uptime_s": h.uptime_s,
        "wall_time_unix_s": h.wall_time_unix_s,
        "counters": dict(h.counters),
        "last_error": h.last_error,
    }
