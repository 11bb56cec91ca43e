"""Closeloop service: checks the twin's model against the plant while the line runs.

Shell over :class:`twin_core.closeloop.online.OnlineCloseLoop` (fed the decoded messages:
``twin_core.closeloop.record.LineRecord``): subscribes the feeder flows
(``twin/<line>/feeder/*/flow``, with their refill flags), the NIR readings
(``twin/<line>/pat/<sensor>/concentration``) and the plant events (tracer pulses with their
mass, disturbances); every ``closeloop.interval_s`` of plant time it checks the declared model plus
the effects adopted so far on the last ``closeloop.window_s`` (residual -> candidate effects ->
held-out test, ``twin_core.closeloop``) and publishes a :class:`~schemas.closeloop.ModelFinding`
on ``twin/<line>/closeloop/finding``: status (five values), the data faults flagged, the effects
claimed with their uncertainties and equivalent explanations, whether the product is at risk
with its product-side reading and the measurement that would settle it, structure beyond the
effect library, the model's full effect list (what the blender adopts; the product-side reading
when the product is at risk: the diverter acts on it) and RMSE / MAE before and after.

Each finding applies from the end of its window plus ``blender.adoption_delay_s``
(``applies_from_s``); the service reports on ``twin/<line>/closeloop/progress``
(:class:`~schemas.messages.AdoptionProgress`, from the worker, after the findings before it)
that every finding applying up to the last complete tick plus that delay is out: the blender
and the diverter adopt each finding at its plant time whatever the machine load, and a window
that fails (``window_errors``) holds nobody back.

The identification of a window (about a second) runs in a worker thread, windows in plant-time
order, so the bus callbacks never wait for it and the findings do not depend on timing. A
restarted service recomputes the findings from the publishers' history (the adopted model
follows) and does not publish a finding again (ids in the run's output log).
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Any

from schemas import keys
from schemas.closeloop import ModelFinding
from schemas.line import LineSpec
from schemas.messages import AdoptionProgress, Event, FeederFlow, MeasuredConcentration
from services.common import OutputLog, ProgressReport, publish_once
from services.service import Service
from twin_core.closeloop.online import OnlineCloseLoop, WindowData
from twin_core.closeloop.report import Finding

log = logging.getLogger(__name__)


def finding_id(line: str, t_end_s: float) -> str:
    """Stable id of the finding of the window ending at ``t_end_s``."""
    return f"{line}.closeloop-{int(round(t_end_s * 1000)):012d}"


def to_message(f: Finding, line: str, seq: int, applies_from_s: float) -> ModelFinding:
    """The wire message of a finding (validated: a finding that does not fit raises)."""
    return ModelFinding.model_validate(
        {
            "t": f.t_end_s,
            "seq": seq,
            "finding_id": finding_id(line, f.t_end_s),
            "status": f.status,
            "t_start_s": f.t_start_s,
            "t_end_s": f.t_end_s,
            "data_quality": f.data_quality,
            "effects": f.effects,
            "possible_explanations": f.possible_explanations,
            "model_effects": f.augmented_effects,
            "product_at_risk": f.product_at_risk,
            "product_reading": f.product_reading,
            "discriminating_measurement": f.discriminating_measurement,
            "structure": f.structure,
            "remaining": f.remaining,
            "errors": f.errors,
            "applies_from_s": applies_from_s,
        }
    )


class CloseLoopService(Service):
    """See the module docstring."""

    #: inputs in plant-time order whatever their arrival, up to two publisher heartbeats late
    #: (``services.service.Service``): the findings are a function of the plant data only
    reorder_s = 1.0
    #: plant seconds between two progress reports
    progress_step_s = 5.0

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("closeloop", spec=spec, **kwargs)
        self.core = OnlineCloseLoop.from_spec(spec)
        self.log_ids = OutputLog(self.state_path / "closeloop.published")
        self.progress = ProgressReport(self.state_path / "closeloop.progress", self.progress_step_s)
        #: the worker's jobs in order: a window, a progress report (t, complete to), a flush
        #: of the progress report (True), the end (None)
        self._jobs: queue.SimpleQueue[WindowData | tuple[float, float] | bool | None] = (
            queue.SimpleQueue()
        )
        self._worker: threading.Thread | None = None

    def setup(self) -> None:
        line = self.spec.name
        self.pub = self.publisher(keys.model_finding(line), ModelFinding, history=True)
        self.pub.seq = self.log_ids.next_seq("finding")
        self.progress.pub = self.publisher(
            keys.adoption_progress(line, "closeloop"), AdoptionProgress, history=True
        )
        self.history_subscribe(keys.feeder_flows(line), FeederFlow)
        self.history_subscribe(
            keys.measured_concentration(line, self.spec.sensor.id), MeasuredConcentration
        )
        self.history_subscribe(keys.events(line), Event)
        self._worker = threading.Thread(target=self._work, name="closeloop-worker", daemon=True)
        self._worker.start()

    #: health counter of each kind of input the record did not take
    IGNORED = {"unknown_feeder": "rejected_unknown", "ignored": "ignored_measurements"}

    def handle(self, key: str, msg: Any) -> None:
        kind = self.core.add_message(key, msg)
        if kind in self.IGNORED:
            self.counters.inc(self.IGNORED[kind])
        if kind in ("flow", "measured"):
            for w in self.core.due():
                self._jobs.put(self.core.snapshot(w))
            last = self.core.record.last_complete_tick()
            if last is not None:
                # every later window ends after the last complete tick
                t_last = last * self.spec.dt_s
                self._jobs.put((t_last, t_last + self.spec.blender.adoption_delay_s))

    def idle(self) -> None:
        self._jobs.put(True)

    def _work(self) -> None:
        while True:
            data = self._jobs.get()
            if data is None:
                return
            if data is True:
                self.progress.flush()
                continue
            if isinstance(data, tuple):
                self.progress.advance(*data)
                continue
            try:
                f = self.core.evaluate(data)
                self._publish(f, data.window.t_end_s + self.spec.blender.adoption_delay_s)
            except Exception as exc:  # noqa: BLE001 - one bad window must not stop the loop
                self.counters.inc("window_errors")
                self.counters.last_error = f"{type(exc).__name__}: {exc}"[:500]
                log.exception("closeloop: window %s failed", data.window)

    def _publish(self, f: Finding, applies_from_s: float) -> None:
        self.counters.inc("windows_checked")
        self.counters.inc(f"status_{f.status}")
        fid = finding_id(self.spec.name, f.t_end_s)
        msg = publish_once(
            self.log_ids,
            self.pub,
            fid,
            "finding",
            lambda seq: to_message(f, self.spec.name, seq, applies_from_s),
            self.counters,
        )
        if msg is None:
            return
        self.progress.updated(msg.t)
        if f.status in ("explained", "partly_explained"):
            log.info(
                "closeloop: window %.0f-%.0f s %s by %s (held-out RMSE %.3f -> %.3f)%s",
                f.t_start_s,
                f.t_end_s,
                f.status.replace("_", " "),
                ", ".join(e.label for e in msg.effects),
                msg.errors.before.heldout.rmse,
                msg.errors.after.heldout.rmse,
                "; product at risk" if msg.product_at_risk else "",
            )
        if msg.product_at_risk:
            self.counters.inc("product_at_risk")

    def finish(self) -> None:
        self._jobs.put(True)
        self._jobs.put(None)
        if self._worker is not None:
            self._worker.join(timeout=30.0)
        self.progress.close()
        self.log_ids.close()
