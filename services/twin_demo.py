"""The whole live twin on a recording: :func:`run_full_twin_demo`.

Services up (supervised processes: feeder, blender, rtd, oos, closeloop, recorder; a zenoh
router on a free loopback port), the recording replayed at ``speed`` x real time by the virtual
plant, alerts printed as they come, then a run report (``report.json`` and ``report.md``:
messages, alerts, divert commands, RTD estimates, the close-loop's model findings, prediction
error, timings, rejected messages) and a figure (``outlet.png``: measured vs predicted outlet concentration, alert windows shaded).

The line configuration is derived from the recording (feeders and set points from the flows,
sensor from the PAT channel, target = the set-point composition, limits 85-115 % of target) on
top of ``services/configs/line1.yaml``.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from schemas import keys
from schemas.bus_config import BusConfig
from schemas.closeloop import ModelFinding
from schemas.line import LineSpec
from schemas.messages import (
    BlenderModelInUse,
    DivertCommand,
    Event,
    FeederFlow,
    MeasuredConcentration,
    OosAlert,
    PredictedConcentration,
    RtdEstimate,
    RtdSkipped,
    ServiceHealth,
)
from services.bus import REJECT_REASONS, HistoryFeed, free_port, open_session
from services.common import format_alert

log = logging.getLogger(__name__)

BASE_CONFIG = Path(__file__).resolve().parent / "configs" / "line1.yaml"


def spec_for_recording(rec: Any, port: int, state_dir: Path, base: Path = BASE_CONFIG) -> LineSpec:
    """Line configuration matching a recording (see the module docstring)."""
    data = LineSpec.from_file(base).model_dump()
    setpoints: dict[str, tuple[str, float]] = {}
    sensor: tuple[str, str] | None = None
    line = None
    for m in rec.messages:
        k = keys.parse_key(m.key)
        line = line or k.line
        if k.signal == "flow" and k.id not in setpoints:
            f = FeederFlow.model_validate_json(m.payload)
            setpoints[k.id] = (f.component, f.setpoint_kg_h or f.mass_flow_kg_h)
        elif k.signal == "concentration" and sensor is None:
            c = MeasuredConcentration.model_validate_json(m.payload)
            sensor = (c.sensor, c.component)
        if sensor is not None and len(setpoints) >= 2 and m.t > 5:
            break
    if not setpoints or sensor is None:
        raise ValueError(
            f"recording must hold feeder flows and a PAT concentration, got feeders "
            f"{sorted(setpoints)} and sensor {sensor}"
        )
    total = sum(q for _, q in setpoints.values())
    target = 100.0 * sum(q for c, q in setpoints.values() if c == sensor[1]) / total
    data.update(
        name=line,
        feeders=[
            {"id": fid, "component": c, "setpoint_kg_h": q} for fid, (c, q) in setpoints.items()
        ],
        sensor={"id": sensor[0], "component": sensor[1], "sample_period_s": 1.0},
        spec=[
            {
                "component": sensor[1],
                "target_pct_w_w": round(target, 6),
                "lower_pct_w_w": round(0.85 * target, 6),
                "upper_pct_w_w": round(1.15 * target, 6),
            }
        ],
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{port}"], "connect": []},
        services=["feeder", "blender", "rtd", "oos", "closeloop", "recorder"],
        feeder_mode="replay",
        express=False,  # high-speed replay: batching beats per-message latency
        state_dir=str(state_dir),
        record_path="twin-demo.mcap",
        # the demo's batches: every 10 min of plant time (ICH Q13: by run time), unless set
        batch=data.get("batch") or {"by": "run_time", "size": 600.0},
    )
    return LineSpec.model_validate(data)


def expected_findings(spec: LineSpec, t_first: float, t_last: float) -> int:
    """Number of close-loop windows of a run from ``t_first`` to ``t_last`` (plant time)."""
    c = spec.closeloop
    if "closeloop" not in spec.services or t_last - t_first < c.min_window_s:
        return 0
    return int((t_last - t_first - c.min_window_s) // c.interval_s) + 1


class _Tap:
    """Test-side view of the bus: everything the report needs."""

    def __init__(self, spec: LineSpec, echo: bool, bus: BusConfig) -> None:
        import zenoh

        self.lock = threading.Lock()
        self.alerts: dict[str, OosAlert] = {}
        self.diverts: dict[str, DivertCommand] = {}
        self.rtd: list[RtdEstimate] = []
        self.rtd_skipped: list[RtdSkipped] = []
        self.findings: dict[str, ModelFinding] = {}
        self.health: dict[str, ServiceHealth] = {}
        self.pred: dict[float, float] = {}
        self.meas: dict[float, float] = {}
        self.models_in_use: dict[tuple[float, str], BlenderModelInUse] = {}
        self.alert_wall: dict[str, float] = {}
        self.duplicates = 0
        self.session = open_session(bus)
        comp = spec.sensor.component
        line = spec.name

        def cb(model, sink):
            """(key, payload) -> validated message to ``sink`` under the lock (HistoryFeed)."""

            def on_payload(key: str, payload: bytes) -> None:
                msg = model.model_validate_json(payload)
                with self.lock:
                    sink(msg)

            return on_payload

        def live(on_payload):
            """The same for a plain (no-history) zenoh subscriber."""
            return zenoh.handlers.Callback(
                lambda sample: on_payload(str(sample.key_expr), sample.payload.to_bytes()),
                lambda: None,
            )

        def on_alert(a: OosAlert) -> None:
            if a.alert_id in self.alerts:
                self.duplicates += 1
                return
            self.alerts[a.alert_id] = a
            self.alert_wall[a.alert_id] = time.perf_counter()
            if echo:
                print(format_alert(a), flush=True)

        def on_divert(d: DivertCommand) -> None:
            if d.command_id in self.diverts:
                self.duplicates += 1
                return
            self.diverts[d.command_id] = d

        def on_pred(p: PredictedConcentration) -> None:
            if p.component == comp:
                self.pred[p.t] = p.concentration_pct_w_w

        def on_meas(m: MeasuredConcentration) -> None:
            self.meas[m.t] = m.concentration_pct_w_w

        self.subs = [
            HistoryFeed(self.session, keys.oos_alert(line), cb(OosAlert, on_alert)),
            HistoryFeed(self.session, keys.divert_command(line), cb(DivertCommand, on_divert)),
            HistoryFeed(self.session, keys.rtd_estimate(line), cb(RtdEstimate, self.rtd.append)),
            HistoryFeed(
                self.session, keys.rtd_skipped(line), cb(RtdSkipped, self.rtd_skipped.append)
            ),
            HistoryFeed(
                self.session,
                keys.model_finding(line),
                cb(ModelFinding, lambda f: self.findings.__setitem__(f.finding_id, f)),
            ),
            HistoryFeed(
                self.session,
                keys.predicted_concentration(line, "outlet"),
                cb(PredictedConcentration, on_pred),
            ),
            HistoryFeed(
                self.session,
                keys.blender_model_in_use(line),
                cb(
                    BlenderModelInUse,
                    lambda m: self.models_in_use.__setitem__((m.applies_from_s, m.reason), m),
                ),
            ),
            self.session.declare_subscriber(
                keys.measured_concentration(line, spec.sensor.id),
                live(cb(MeasuredConcentration, on_meas)),
            ),
            self.session.declare_subscriber(
                keys.services_health(line),
                live(cb(ServiceHealth, lambda h: self.health.__setitem__(h.service, h))),
            ),
        ]

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


def _figure(path: Path, tap: _Tap, spec: LineSpec, reference: dict[float, float]) -> None:
    """``outlet.png``: measured vs predicted by the twin's blender model and by the seed's
    Table 6.2 axial dispersion, alert windows shaded (``twin_core.online.plots``)."""
    from twin_core.online.plots import plot_outlet

    lim = spec.limits(spec.sensor.component)
    fig = plot_outlet(
        tap.meas,
        tap.pred,
        spec.sensor.component,
        spec.name,
        None if lim is None else (lim.target_pct_w_w, lim.lower_pct_w_w, lim.upper_pct_w_w),
        [(a.t_start_s, a.t_end_s) for a in tap.alerts.values()],
        predicted_label=f"predicted ({spec.blender.kind} blender, live)",
        others={REFERENCE_LABEL: reference} if spec.blender.kind != "rtd" else None,
    )
    fig.savefig(path, dpi=120)


#: the reference prediction the demo compares the live blender with
REFERENCE_LABEL = "predicted (Table 6.2 axial dispersion)"


def reference_spec(spec: LineSpec) -> LineSpec:
    """``spec`` with the seed's Table 6.2 axial dispersion blender (``BlenderModelConfig``
    defaults, the same kernel length)."""
    from schemas.line import BlenderModelConfig

    return spec.model_copy(update={"blender": BlenderModelConfig(kernel_s=spec.blender.kernel_s)})


def reference_prediction(rec: Any, spec: LineSpec) -> dict[float, float]:
    """What the twin predicts for the sensor's component with the seed's Table 6.2 axial
    dispersion blender (:func:`reference_spec`) from the recording's feeder flows and tracer
    events (:func:`stream_prediction`)."""
    return stream_prediction(rec, reference_spec(spec))


def tracer_injections(rec: Any) -> list[float]:
    """Plant times of the tracer pulses a recording's events announce."""
    from twin_core.online.inlet import event_record, tracer_pulse

    out = []
    for m in rec.messages:
        if keys.parse_key(m.key).signal == "event":
            p = tracer_pulse(event_record(Event.model_validate_json(m.payload)))
            if p is not None:
                out.append(p.t_s)
    return sorted(out)


def stream_prediction(rec: Any, spec: LineSpec) -> dict[float, float]:
    """The blender of ``spec`` (no adoption: its declared model) predicting the sensor's
    component from a recording's feeder flows and tracer events, in the recording's order
    (``twin_core.online.blender.BlenderPredictor``, the blender service's core)."""
    from twin_core.online.blender import BlenderPredictor
    from twin_core.online.inlet import event_record

    core = BlenderPredictor(spec)
    comp = spec.sensor.component
    out: dict[float, float] = {}
    for m in rec.messages:
        k = keys.parse_key(m.key)
        if k.signal == "event":
            core.add_event(event_record(Event.model_validate_json(m.payload)))
        elif k.signal == "flow" and k.unit == "feeder" and k.id in core.components:
            f = FeederFlow.model_validate_json(m.payload)
            for t, conc in core.push(k.id, f.t, f.mass_flow_kg_h, f.refilling):
                out[t] = conc[comp]
    return out


def _wait_for_the_twin(tap: _Tap, spec: LineSpec, rec: Any, limit_s: float = 120.0) -> None:
    """Until the diverter has seen the last plant time, the blender predicted it and the
    close-loop published every window's finding (or ``limit_s``)."""
    last_t = rec.messages[-1].t if rec.messages else 0.0
    n_windows = expected_findings(spec, rec.messages[0].t if rec.messages else 0.0, last_t)
    t_wait = time.perf_counter()
    while time.perf_counter() - t_wait < limit_s:
        h = tap.health.get("oos")
        if (
            h is not None
            and h.t >= last_t
            and (tap.pred and max(tap.pred) >= last_t - 1)
            and len(tap.findings) >= n_windows
        ):
            return
        time.sleep(0.1)


def _feed_recording(
    rec: Any, sup: Any, spec: LineSpec, speed: float, timings: dict[str, float]
) -> tuple[int, Any]:
    """The virtual plant replays the recording into the running twin (``BusReplay``); returns
    (messages published, the open replay, closed by the caller after the drain)."""
    from services.recording import BusReplay

    rp = BusReplay.as_plant(rec, sup.client_config("plant"), spec).__enter__()
    stats = rp.replay(
        speed=speed if math.isfinite(speed) else 1.0,
        as_fast_as_possible=not math.isfinite(speed),
    )
    timings["replay_wall_s"] = stats.wall_s
    return stats.published, rp


class _OpcuaFeed:
    """The loopback OPC UA plant serving the recording and ``twin bridge opcua`` feeding the
    twin from it (``services.opcua_plant``, ``services.opcua_bridge``); the bridge writes the
    diverter's commands back to the plant's gate node over the plant's default security
    (Basic256Sha256 SignAndEncrypt, per-run certificates and user) and the twin's secured bus."""

    def __init__(self, rec: Any, sup: Any, spec: LineSpec, speed: float) -> None:
        import asyncio

        from services.opcua_bridge import OpcuaBridge
        from services.opcua_plant import LoopbackPlant

        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.plant = LoopbackPlant(
            [(m.key, m.decode()) for m in rec.messages],
            port=free_port(),
            speed=speed if math.isfinite(speed) else 1e6,
        )
        self.run(self.plant.start())
        self.bridge = OpcuaBridge(
            self.plant.bridge_config(), sup.client_config("plant"), spec=spec
        ).__enter__()
        if not self.bridge.connected.wait(30):
            raise RuntimeError(f"the OPC UA bridge did not connect to {self.plant.endpoint}")

    def run(self, coro: Any) -> Any:
        import asyncio

        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(600)

    def feed(self, timings: dict[str, float]) -> int:
        t0 = time.perf_counter()
        self.run(self.plant.play())
        want = len(self.plant.messages)
        deadline = time.monotonic() + 30
        while self.bridge.counters.get("published") < want and time.monotonic() < deadline:
            time.sleep(0.02)
        self.bridge.end_of_stream()
        timings["replay_wall_s"] = time.perf_counter() - t0
        return self.bridge.counters.get("published")

    def __exit__(self, *exc: Any) -> None:
        try:
            self.bridge.close()
            self.run(self.plant.stop())
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(5)


def _run_twin(
    rec: Any,
    spec: LineSpec,
    speed: float,
    echo: bool,
    timings: dict[str, float],
    opcua: bool = False,
) -> tuple[_Tap, int, dict[str, Any], dict[str, int], Path, int]:
    """Services up, the recording fed into them (replayed on the bus, or over OPC UA through
    the bridge), the tap's view; returns (tap, messages fed, the services' health at the end of
    the run, exit codes, run directory, divert commands written to the OPC UA gate)."""
    from services.supervisor import Supervisor

    t0 = time.perf_counter()
    sup = Supervisor(spec, backoff_s=0.5)
    tap = None
    written = 0
    try:
        sup.start()
        if not sup.wait_ready(90):
            raise RuntimeError(f"services not ready after 90 s: alive {sorted(sup.alive)}")
        timings["startup_s"] = time.perf_counter() - t0
        tap = _Tap(spec, echo, sup.client_config("operator"))
        if opcua:
            feed = _OpcuaFeed(rec, sup, spec, speed)
            sent = feed.feed(timings)
        else:
            sent, feed = _feed_recording(rec, sup, spec, speed, timings)
        try:
            t_wait = time.perf_counter()
            _wait_for_the_twin(tap, spec, rec)
            timings["drain_s"] = time.perf_counter() - t_wait
            time.sleep(1.5)  # publishers' heartbeat; end-of-stream decisions
            if opcua:  # the last divert commands on their way to the gate
                deadline = time.monotonic() + 10
                while len(feed.plant.commands) < len(tap.diverts) and time.monotonic() < deadline:
                    time.sleep(0.05)
        finally:
            feed.__exit__(None, None, None)
        if opcua:
            written = len(feed.plant.commands)
        health = {k: v.model_dump(mode="json") for k, v in tap.health.items()}
    finally:
        codes = sup.stop()
        if tap is not None:
            tap.close()
    return tap, sent, health, codes, sup.run_dir, written


def prediction_error(measured: dict[float, float], predicted: dict[float, float]) -> dict:
    """Measured - predicted at the plant times of both: n, bias, RMSE, MAE (% w/w)."""
    common = sorted(set(measured) & set(predicted))
    err = np.array([measured[t] - predicted[t] for t in common]) if common else np.array([])
    return {
        "n": int(err.size),
        "bias": float(err.mean()) if err.size else None,
        "rmse": float(np.sqrt(np.mean(err**2))) if err.size else None,
        "mae": float(np.mean(np.abs(err))) if err.size else None,
    }


#: health counters that say an input or a computation did not give its output, or gave it late
FAILURE_COUNTERS = (
    *REJECT_REASONS,
    "handler_errors",
    "window_errors",
    "fit_failed",
    "pulses_skipped_disturbance",
    "adopted_late",
    "adopted_late_max_ms",
    "adoption_bypassed",
    "degraded_releases",
)


def failures(health: dict[str, dict]) -> list[str]:
    """One line per service whose health counts a failure, a skip or a late adoption
    (:data:`FAILURE_COUNTERS`), with its last error."""
    lines = []
    for name, h in sorted(health.items()):
        c = h.get("counters", {})
        found = [f"{k}={c[k]}" for k in FAILURE_COUNTERS if c.get(k)]
        if found:
            err = f" (last error: {h['last_error']})" if h.get("last_error") else ""
            lines.append(f"- {name}: {', '.join(found)}{err}")
    return lines


def _shape(e: np.ndarray, dt: float) -> dict[str, float]:
    """Mean residence time, standard deviation, mode and t(F = 0.995) of an E(t) on the tick
    grid, s."""
    from twin_core.rtd.profiles import moments

    t = np.arange(e.size) * dt
    m = moments(t, e)
    f = np.cumsum(e) / np.sum(e)
    return {
        "mean_s": float(m.mean),
        "sd_s": float(np.sqrt(m.variance)),
        "mode_s": float(t[int(np.argmax(e))]),
        "t995_s": float(t[min(int(np.searchsorted(f, 0.995)), t.size - 1)]),
    }


def _rmse(err: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(err**2))) if err.size else None


def blender_comparison(
    measured: dict[float, float],
    live: dict[float, float],
    reference: dict[float, float],
    pulses: list[float],
    e_live: np.ndarray,
    e_ref: np.ndarray,
    dt: float,
    live_label: str = "compartment model",
) -> dict[str, Any]:
    """Where and why the live blender's error differs from the Table 6.2 model's, from the run:
    the RMSE of each inside the tracer pulses' passage (from each injection to the later
    t(F = 0.995) of the two E(t)) and outside it, the share of the live model's extra squared
    error that lies inside, the two E(t)'s mean residence time, spread and mode, and each
    pulse's peak delay in the NIR and in each prediction; ``text`` says it in two sentences."""
    shapes = {"live": _shape(e_live, dt), "reference": _shape(e_ref, dt)}
    width = max(s["t995_s"] for s in shapes.values()) + dt
    t = np.array(sorted(set(measured) & set(live) & set(reference)))
    y = np.array([measured[x] for x in t])
    a = np.array([live[x] for x in t])
    b = np.array([reference[x] for x in t])
    inside = np.zeros(t.size, bool)
    for p in pulses:
        inside |= (t >= p) & (t <= p + width)
    extra = (y - a) ** 2 - (y - b) ** 2
    share = float(extra[inside].sum() / extra.sum()) if extra.sum() > 0 else None
    delays: dict[str, list[float]] = {"measured": [], "live": [], "reference": []}
    for p in pulses:
        w = (t >= p) & (t <= p + width)
        if w.any():
            for name, z in (("measured", y), ("live", a), ("reference", b)):
                delays[name].append(float(t[w][int(np.argmax(z[w]))] - p))
    out: dict[str, Any] = {
        "pulses": len(pulses),
        "pulse_window_s": width,
        "samples_in_pulses": int(inside.sum()),
        "samples": int(t.size),
        "rmse_in_pulses": {"live": _rmse((y - a)[inside]), "reference": _rmse((y - b)[inside])},
        "rmse_outside": {"live": _rmse((y - a)[~inside]), "reference": _rmse((y - b)[~inside])},
        "excess_share_in_pulses": share,
        "e_t": shapes,
        "peak_delay_s": delays,
    }
    out["text"] = _comparison_text(out, live_label)
    return out


def _comparison_text(c: dict[str, Any], live_label: str) -> str:
    """Two sentences from :func:`blender_comparison`'s numbers: where the live model's extra
    error lies, and how its E(t) differs from Table 6.2's."""
    sentences = []
    share, ins, outs = c["excess_share_in_pulses"], c["rmse_in_pulses"], c["rmse_outside"]
    if c["pulses"] and share is not None and ins["live"] is not None:
        where = (
            f"{share:.1%} of the {live_label}'s extra squared error lies in the "
            f"{c['pulses']} tracer pulses' passage ({c['pulse_window_s']:.0f} s after each "
            f"injection, {c['samples_in_pulses'] / c['samples']:.0%} of the samples): there its "
            f"RMSE is {ins['live']:.3f} against {ins['reference']:.3f} % w/w"
        )
        if outs["live"] is not None:
            where += f", elsewhere {outs['live']:.3f} against {outs['reference']:.3f}"
        sentences.append(where[0].upper() + where[1:])
    lv, rf = c["e_t"]["live"], c["e_t"]["reference"]
    dm = lv["mean_s"] - rf["mean_s"]
    same = abs(dm) <= 0.05 * rf["mean_s"]
    mrt = (
        "the same mean residence time as Table 6.2's"
        if same
        else f"a {'longer' if dm > 0 else 'shorter'} mean residence time than Table 6.2's"
    )
    spread = "narrower" if lv["sd_s"] < rf["sd_s"] else "wider"
    peak = (
        "a later peak"
        if lv["mode_s"] > rf["mode_s"]
        else "an earlier peak"
        if lv["mode_s"] < rf["mode_s"]
        else "the same peak"
    )
    shape = (
        f"Its E(t) has {mrt} ({lv['mean_s']:.1f} vs {rf['mean_s']:.1f} s) "
        f"{'but' if same else 'and'} is {spread} with {peak} (sd {lv['sd_s']:.1f} vs "
        f"{rf['sd_s']:.1f} s, mode {lv['mode_s']:.0f} vs {rf['mode_s']:.0f} s)"
    )
    d = c["peak_delay_s"]
    if d["measured"]:

        def secs(xs: list[float]) -> str:
            return ", ".join(f"{x:.0f}" for x in xs) + " s"

        shape += (
            f": the NIR saw the pulses peak {secs(d['measured'])} after injection, the "
            f"{live_label} predicted {secs(d['live'])}, Table 6.2 {secs(d['reference'])}"
        )
    sentences.append(shape)
    return ". ".join(sentences) + "."


#: what each close-loop status of a window means (docs/closeloop.md), one line each
STATUS_MEANING = {
    "consistent": "the declared model's residual is the NIR's declared noise: nothing is "
    "missing from the model in this window",
    "explained": "an effect was found and, added to the model, leaves only the noise on the "
    "held-out data: the model lacked that effect",
    "partly_explained": "an effect was found but, added to the model, still leaves more than "
    "the noise on the held-out data (the finding's `remaining` says what): reported, not adopted",
    "unexplained": "the residual is more than the noise, yet no candidate effect passes the "
    "claim test: the twin does not know what the model lacks and claims nothing",
    "data_quality": "data faults (stuck, clipped, spiky, missing or mis-stamped samples) were "
    "flagged and left out, and the rest is the noise: no process effect is claimed",
}


def _error_text(err: dict) -> str:
    return f"bias {err['bias']:+.3f}, RMSE {err['rmse']:.3f} % w/w" if err["n"] else "n/a"


def _model_lines(report: dict[str, Any]) -> list[str]:
    """The reference prediction's error, why it differs from the live one, and the blender
    models the twin used."""
    lines = []
    ref = report.get("reference_prediction_error_pct_w_w")
    if ref is not None and report.get("blender_model") != "rtd":
        lines.append(f"- the same with the seed's Table 6.2 axial dispersion: {_error_text(ref)}")
        comparison = report.get("blender_comparison")
        if comparison:
            lines.append(f"  - why they differ: {comparison['text']}")
    for m in report.get("models_in_use", []):
        lines.append(
            f"- blender model from {m['applies_from_s']:.0f} s ({m['reason']}): {m['name']}, "
            f"mean residence time {m['mean_residence_time_s']:.1f} s"
        )
    return lines


def report_markdown(report: dict[str, Any]) -> str:
    """``report.md``: the run in a few lines, the alerts, RTD estimates and findings."""
    t, err = report["timings_s"], report["prediction_error_pct_w_w"]
    lines = [
        f"# Live twin run on `{Path(report['recording']).name}`",
        "",
        f"- {report['recording_status']}; {report['messages_replayed']} messages, "
        f"{report['plant_span_s']:.0f} s of plant time replayed in "
        f"{t['replay_wall_s']:.2f} s ({report['speedup_achieved']:.0f}x real time)",
        f"- start-up {t['startup_s']:.1f} s, total {t['total_s']:.1f} s",
        f"- predictions: {report['predictions']}; measured - predicted: "
        + _error_text(err)
        + f" ({report.get('blender_model', 'rtd')} blender, live)",
        *_model_lines(report),
        f"- OOS alerts: {len(report['alerts'])}{_tracer_alerts(report['alerts'])}; divert commands: "
        f"{len(report['divert_commands'])}; RTD estimates: {len(report['rtd_estimates'])} "
        f"(pulses without one: {len(report['rtd_skipped'])}); "
        f"duplicates seen: {report['duplicates_seen']}",
        "",
        "| alert | outlet window (s) | peak deviation (% w/w) | cause |",
        "|---|---|---|---|",
    ]
    for a in report["alerts"]:
        lines.append(
            f"| {a['alert_id']} | {a['t_start_s']:.1f} - {a['t_end_s']:.1f} | "
            f"{a['peak_deviation_pct_w_w']:+.3f} | {a['cause']} |"
        )
    for r in report["rtd_estimates"]:
        ps = ", ".join(f"{k}={v:.3g}" for k, v in r["params"].items())
        lines.append(
            f"\nRTD estimate (pulse at {r['pulse_t_s']} s): {r['model']} {ps}, "
            f"mean residence time {r['mean_residence_time_s']:.1f} s"
        )
    for r in report["rtd_skipped"]:
        lines.append(
            f"\nRTD pulse at {r['pulse_t_s']} s without estimate ({r['reason']}): {r['detail']}"
        )
    failed = failures(report["service_health"])
    lines += ["", "Failures, skips and late adoptions:", *(failed or ["- none"])]
    if report["model_findings"]:
        lines += [
            "",
            "| close-loop window (s) | status | effects found | held-out RMSE before -> after |",
            "|---|---|---|---|",
        ]
    for f in report["model_findings"]:
        eff = ", ".join(
            e["label"]
            + " ("
            + ", ".join(f"{p['name']}={p['value']:.3g}" for p in e["params"])
            + ")"
            for e in f["effects"]
        )
        rmse = f["errors"]["before"]["heldout"]["rmse"], f["errors"]["after"]["heldout"]["rmse"]
        lines.append(
            f"| {f['t_start_s']:.0f} - {f['t_end_s']:.0f} | {f['status']} | {eff or '-'} | "
            f"{rmse[0]:.3f} -> {rmse[1]:.3f} |"
        )
    if report["model_findings"]:
        lines += ["", "What a window's status means:"]
        for status, meaning in STATUS_MEANING.items():
            n = sum(f["status"] == status for f in report["model_findings"])
            lines.append(f"- `{status}` ({n} window{'' if n == 1 else 's'}): {meaning}")
    from services.batch_report import batches_markdown

    lines += batches_markdown(report.get("batches", []))
    return "\n".join([*lines, "", "![outlet](outlet.png)", ""])


def _batches(run_dir: Path, recording: str | Path, spec: LineSpec, out: Path) -> list[dict]:
    """Each batch with its lots (``services.batch_report``), from the live twin's own recording
    (its decisions in it), else from the source recording (plant data only)."""
    from services.batch_report import batches_of_recording

    live = Path(run_dir) / (spec.record_path or "")
    return batches_of_recording(live if live.is_file() else recording, spec, out / "batches")


def _tracer_alerts(alerts: list[dict[str, Any]]) -> str:
    """`` (n tracer pulses)`` when alerts are the passage of announced tracer pulses."""
    n = sum(a["cause"].startswith("tracer pulse") for a in alerts)
    return f" ({n} tracer pulse{'' if n == 1 else 's'})" if n else ""


def run_full_twin_demo(
    recording: str | Path | None,
    out_dir: str | Path,
    speed: float = 200.0,
    echo: bool = True,
    opcua: bool = False,
) -> dict[str, Any]:
    """Run the live twin on ``recording`` (default: the bundled ``recordings/line1_30min.mcap``)
    replayed (``opcua``: served by the loopback OPC UA plant and fed through ``twin bridge
    opcua``) at ``speed`` x real time (``inf``: as fast as the bus takes it); write
    ``report.json``, ``report.md`` and ``outlet.png`` to ``out_dir``; return the report dict."""
    from services.recording import read_recording

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if recording is None:
        recording = Path(__file__).resolve().parent.parent / "recordings" / "line1_30min.mcap"
    t0 = time.perf_counter()
    rec = read_recording(recording)
    spec = spec_for_recording(rec, free_port(), out / "state")
    timings: dict[str, float] = {}
    tap, n_sent, health, codes, run_dir, written = _run_twin(rec, spec, speed, echo, timings, opcua)
    reference = reference_prediction(rec, spec)
    comparison = None
    if spec.blender.kind != "rtd":
        from twin_core.online.blender import declared_kernel

        comparison = blender_comparison(
            tap.meas,
            tap.pred,
            reference,
            tracer_injections(rec),
            declared_kernel(spec),
            declared_kernel(reference_spec(spec)),
            spec.dt_s,
            f"{spec.blender.kind} model",
        )
    timings["total_s"] = time.perf_counter() - t0
    span = rec.duration_s
    report = {
        "recording": str(recording),
        "recording_status": rec.loss_report(),
        "line": spec.name,
        "spec": spec.limits(spec.sensor.component).model_dump(),
        "messages_replayed": n_sent,
        "plant_span_s": span,
        "speed_requested": speed,
        "speedup_achieved": span / timings["replay_wall_s"]
        if timings["replay_wall_s"] > 0
        else math.inf,
        "predictions": len(tap.pred),
        "blender_model": spec.blender.kind,
        "models_in_use": [m.model_dump(mode="json") for _, m in sorted(tap.models_in_use.items())],
        "prediction_error_pct_w_w": prediction_error(tap.meas, tap.pred),
        "reference_prediction_error_pct_w_w": prediction_error(tap.meas, reference),
        "blender_comparison": comparison,
        "alerts": [
            a.model_dump(mode="json")
            for a in sorted(tap.alerts.values(), key=lambda a: a.t_start_s)
        ],
        "divert_commands": [d.model_dump(mode="json") for d in tap.diverts.values()],
        "rtd_estimates": [r.model_dump(mode="json") for r in tap.rtd],
        "rtd_skipped": [r.model_dump(mode="json") for r in tap.rtd_skipped],
        "model_findings": [
            f.model_dump(mode="json") for f in sorted(tap.findings.values(), key=lambda f: f.t)
        ],
        "duplicates_seen": tap.duplicates,
        "service_health": health,
        "exit_codes": codes,
        "timings_s": timings,
        "run_dir": str(run_dir),
        "feed": "opcua" if opcua else "replay",
        "divert_commands_written_to_gate": written,
    }
    report["batches"] = _batches(run_dir, recording, spec, out)
    (out / "report.json").write_text(json.dumps(report, indent=2))
    _figure(out / "outlet.png", tap, spec, reference)
    (out / "report.md").write_text(report_markdown(report))
    return report
