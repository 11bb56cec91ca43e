"""The close-loop on a running line: stream samples in, get a finding per window.

:class:`OnlineCloseLoop` keeps the recent feeder flows (with refill flags), NIR readings and
tracer pulses on the line's tick grid (``twin_core.closeloop.record.LineRecord``, the twin's one
message-to-array adapter, also used offline by ``twin close-loop``). Every ``interval_s`` of
plant time, once ``min_window_s`` of data is in, the current model (the declared one plus the
effects adopted so far) is checked on the last ``window_s`` with
:func:`twin_core.closeloop.report.online_finding` (residual -> candidate effects -> held-out
test; Schwarz selection and the held-out likelihood-ratio test of
``twin_core.closeloop.identify``; the data-quality check first, on the window's arrays and its
streams' raw message stamps). An ``explained`` finding is adopted: the model used for the next
windows is the augmented one (its product-side reading when the product is at risk), so an
effect is found once and later windows check that the fix holds (``consistent``).

Windows are closed in plant time, when every stream has passed their end, so the findings do not
depend on the order or the speed at which the samples arrive.

Error control over time. A check every ``interval_s``, each at its own 5 % level, claims an
effect sooner or later on any line: what is controlled is ``false_claims_per_day``, the
probability of at least one false claim in a day of operation, spent at a constant rate over
the day's windows (:func:`claim_alpha`; Lan & DeMets 1983, Biometrika 70:659, with a linear
spending function; the bound is Bonferroni's and holds however the overlapping windows
correlate). Each window is a segment of the probe's 1/f noise over ``noise_span_s``
(``twin_core.closeloop.data.RunData.noise_span_s``): its slow wander is noise to the tests.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from schemas.line import LineConfig
from twin_core.closeloop.data import StreamStamps
from twin_core.closeloop.record import LineRecord
from twin_core.closeloop.report import Finding, online_finding
from twin_core.plant.model import LineInputs, LineModel

#: plant seconds of the close-loop's false-claim budget
DAY_S = 86400.0


def claim_alpha(false_claims_per_day: float, interval_s: float) -> float:
    """Level of one window's claim test under constant-rate alpha spending over a day:

        alpha_w = min(0.05, alpha_day * interval_s / 86400)

    so that P(any false claim in a day) <= sum of the day's alpha_w = alpha_day (Bonferroni;
    Lan & DeMets 1983, Biometrika 70:659, linear spending function)."""
    if not 0 < false_claims_per_day < 1:
        raise ValueError(f"false_claims_per_day must be in (0, 1), got {false_claims_per_day!r}")
    if interval_s <= 0:
        raise ValueError(f"interval_s must be > 0, got {interval_s!r}")
    return min(0.05, false_claims_per_day * interval_s / DAY_S)


def spec_limits(config: LineConfig) -> tuple[float, float] | None:
    """(lower, upper) % w/w of the measured component in a ``LineSpec``'s ``spec``, or None."""
    comp = config.sensor.component
    for lim in getattr(config, "spec", None) or []:
        if lim.component == comp:
            return (float(lim.lower_pct_w_w), float(lim.upper_pct_w_w))
    return None


@dataclass(frozen=True)
class Window:
    """A window of plant time [t_start_s, t_end_s] due for a check."""

    t_start_s: float
    t_end_s: float


@dataclass
class WindowData:
    """The arrays of one window (:meth:`OnlineCloseLoop.snapshot`), ready to evaluate."""

    window: Window
    t_s: np.ndarray
    measured: np.ndarray
    inputs: LineInputs
    events: list[dict[str, Any]]
    skip_s: float
    stamps: dict[str, StreamStamps] = field(default_factory=dict)


class OnlineCloseLoop:
    """Windows of a running line -> :class:`Finding` s (see the module docstring).

    Args:
        config: the declared line (``schemas.line.LineConfig``; a ``LineSpec`` is one).
        dt_s: tick of the flow stream, s.
        interval_s, window_s, min_window_s, skip_s: as ``schemas.line.CloseLoopSettings``.
        candidates: effect names tried (empty: all registered effects).
        max_effects: effects claimed per window (1 or 2).
        effects: effects already adopted (dict form), e.g. after a restart.
        false_claims_per_day: the daily false-claim budget (module docstring).
        noise_span_s: plant time over which the 1/f noise has its declared sd (module docstring).
        limits: specification (lower, upper, % w/w) of the measured component: a product-side
            reading names the stretches it puts out of specification (what the diverter
            diverts); None: the config's ``spec`` when it has one (a ``LineSpec``).
    """

    def __init__(
        self,
        config: LineConfig,
        dt_s: float = 1.0,
        *,
        interval_s: float = 300.0,
        window_s: float = 1200.0,
        min_window_s: float = 600.0,
        skip_s: float = 150.0,
        candidates: Sequence[str] = (),
        max_effects: int = 1,
        effects: Sequence[Mapping[str, Any]] = (),
        false_claims_per_day: float = 0.05,
        noise_span_s: float = 14400.0,
        limits: tuple[float, float] | None = None,
    ) -> None:
        if dt_s <= 0:
            raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
        if not 0 <= skip_s < min_window_s <= window_s:
            raise ValueError(
                "need 0 <= skip_s < min_window_s <= window_s, got "
                f"{skip_s} / {min_window_s} / {window_s}"
            )
        if interval_s <= 0:
            raise ValueError(f"interval_s must be > 0, got {interval_s!r}")
        self.config = config
        self.dt_s = float(dt_s)
        self.interval_s = float(interval_s)
        self.window_s = float(window_s)
        self.min_window_s = float(min_window_s)
        self.skip_s = float(skip_s)
        self.candidates = list(candidates)
        self.max_effects = int(max_effects)
        self.alpha = claim_alpha(false_claims_per_day, interval_s)
        if not noise_span_s > 0:
            raise ValueError(f"noise_span_s must be > 0, got {noise_span_s!r}")
        self.noise_span_s = float(noise_span_s)
        self.limits = limits if limits is not None else spec_limits(config)
        self.components = config.components
        self.model_ = LineModel(config, list(effects))
        self.record = LineRecord(self.components, self.dt_s, config.sensor.component)
        self._next_due: int | None = None
        self.findings_: list[Finding] = []

    @classmethod
    def from_spec(cls, spec: Any, **kwargs: Any) -> OnlineCloseLoop:
        """The live check of a ``schemas.line.LineSpec`` as its ``closeloop:`` section sets
        it (the closeloop service's); ``kwargs`` override."""
        c = spec.closeloop
        args: dict[str, Any] = dict(
            interval_s=c.interval_s,
            window_s=c.window_s,
            min_window_s=c.min_window_s,
            skip_s=c.skip_s,
            candidates=c.candidates,
            max_effects=c.max_effects,
            false_claims_per_day=c.false_claims_per_day,
            noise_span_s=c.noise_span_s,
        )
        return cls(spec, spec.dt_s, **{**args, **kwargs})

    # -- input -----------------------------------------------------------------------------
    def _tick(self, t: float) -> int:
        return self.record.tick(t)

    @property
    def _t0(self) -> int | None:
        return self.record.first_tick

    def add_flow(
        self,
        feeder: str,
        t: float,
        flow_kg_h: float,
        refilling: bool = False,
        screw_speed_rpm: float = math.nan,
    ) -> None:
        """A reported feeder flow (kg/h) at plant time t (its refill flag and screw speed)."""
        self.record.add_flow(feeder, t, flow_kg_h, refilling, screw_speed_rpm)
        self._start()

    def _start(self) -> None:
        if self._next_due is None and self._t0 is not None:
            self._next_due = self._t0 + int(round(self.min_window_s / self.dt_s))

    def add_measured(self, t: float, c_pct_w_w: float) -> None:
        """A reading of the NIR probe (% w/w) at plant time t."""
        self.record.add_measured(t, c_pct_w_w)

    def add_event(self, event: Mapping[str, Any]) -> None:
        """A plant event as a dict (``kind``, ``t_s``, ``source``, ...); ``tracer_pulse`` events
        with ``mass_kg`` enter the model's inlet as pulses of ``component`` (or ``source``)."""
        self.record.add_event(event)

    def add_message(self, key: str, msg: Any) -> str:
        """A decoded bus message (``LineRecord.add_message``); returns what it was."""
        kind = self.record.add_message(key, msg)
        self._start()
        return kind

    # -- windows ---------------------------------------------------------------------------
    def due(self) -> list[Window]:
        """The windows whose end every stream has passed, oldest first (each returned once)."""
        last = self.record.last_complete_tick()
        out: list[Window] = []
        if last is None or self._next_due is None or self._t0 is None:
            return out
        step = max(1, int(round(self.interval_s / self.dt_s)))
        span = int(round(self.window_s / self.dt_s))
        while self._next_due <= last:
            b = self._next_due
            a = max(self._t0, b - span)
            out.append(Window(a * self.dt_s, b * self.dt_s))
            self._next_due += step
        return out

    def window_data(self, w: Window) -> tuple[np.ndarray, np.ndarray, LineInputs, list[dict]]:
        """(t, measured, inputs, events) of a window on the tick grid
        (``LineRecord.arrays``)."""
        return self.record.arrays(w.t_start_s, w.t_end_s)

    def snapshot(self, w: Window) -> WindowData:
        """The arrays of window ``w``; then forget the data no later window needs. Cheap: the
        streaming side calls it, the slow :meth:`evaluate` may run in another thread (it only
        touches the model)."""
        t, y, inputs, events = self.window_data(w)
        # the run's first window starts with the line at steady state; a later one starts
        # with the response to earlier inputs still in the blender: fit after skip_s
        first = self._t0 is not None and self._tick(w.t_start_s) == self._t0
        stamps = self.record.stamps(w.t_start_s, w.t_end_s)
        data = WindowData(w, t, y, inputs, events, 0.0 if first else self.skip_s, stamps)
        self._prune(self._tick(w.t_end_s))
        return data

    def evaluate(self, data: WindowData) -> Finding:
        """Check the current model on a window; adopt the model of an explained finding (its
        product-side reading when the product is at risk). A partly explained finding is
        reported, not adopted: something the model cannot say is still there."""
        options: dict[str, Any] = {
            "skip_s": data.skip_s,
            "max_effects": self.max_effects,
            "alpha": self.alpha,
        }
        if self.candidates:
            options["candidates"] = list(self.candidates)
        f = online_finding(
            data.t_s,
            data.measured,
            data.inputs,
            self.model_,
            data.events,
            options,
            data.stamps,
            noise_span_s=self.noise_span_s,
            limits=self.limits,
        )
        if f.status == "explained":
            self.model_ = LineModel(self.config, f.augmented_effects)
        self.findings_.append(f)
        return f

    def check(self, w: Window) -> Finding:
        """:meth:`snapshot` then :meth:`evaluate` (single-threaded use)."""
        return self.evaluate(self.snapshot(w))

    def _prune(self, end: int) -> None:
        """Forget what no later window can use."""
        self.record.prune(end - int(round(self.window_s / self.dt_s)) + 1)
