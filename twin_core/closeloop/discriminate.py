"""The measurement that would separate two explanations the recorded data cannot tell apart.

Given two fitted readings of the same record (a probe-side model A and a product-side model B:
``twin_core.closeloop.attribution``), each candidate experiment is simulated with both models
and its power to tell them apart computed from the difference of their predictions under the
noise (model discrimination design: Box & Hill, Technometrics 9:57, 1967, choose the experiment
whose outcomes the rival models predict most differently relative to the noise; here with the
Gaussian expected log likelihood ratio lambda / 2 and the power of the two-sided level-alpha
test of A against B, Phi(sqrt(lambda) - z) + Phi(-sqrt(lambda) - z), z = z_{1 - alpha/2}):

- ``assay``: n off-line assays of product samples taken over the held-out window; each reads
  the outlet concentration with standard deviation ``assay_sd_pct_w_w`` (HPLC content assay,
  ~1 % relative at the seed's 10 % API); lambda = n Delta^2 / sd^2, Delta the mean difference of
  the two models' *outlet* (not probe) predictions -- the one experiment that reads the product
  itself;
- ``tracer_pulse``: a pulse of m g of the measured component at the inlet, the line held at its
  last operating point, the probe read for ``horizon_s``;
- ``setpoint_step``: the set point of the measured component's feeders raised by a fraction for
  ``horizon_s``.

For the last two lambda = |W((dy_with - dy_without) / sigma)|^2, dy the difference of the two
models' probe predictions with and without the experiment (so only what the experiment adds
counts), W the innovations map of the noise (``twin_core.closeloop.noise.NoiseWhitener``). Each
experiment's smallest size on its grid reaching ``target_power`` is reported (or its largest);
the recommended one is the most powerful, the least intrusive first among equals (an assay
disturbs nothing, a pulse a few minutes of product, a step the operating point).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from schemas.line import TracerPulse
from twin_core.closeloop.data import RunData
from twin_core.closeloop.noise import NoiseWhitener
from twin_core.plant.effects import Effect
from twin_core.plant.model import LineInputs, LineModel
from twin_core.plant.nir import noise_sd

__all__ = ["DesignOptions", "MeasurementOption", "design_measurement"]

#: experiment kinds, least intrusive first (the tie-break of the recommendation)
KINDS = ("assay", "tracer_pulse", "setpoint_step")


@dataclass
class DesignOptions:
    """Settings of :func:`design_measurement` (module docstring)."""

    assay_sd_pct_w_w: float = 0.1
    assays: Sequence[int] = (1, 2, 3, 4, 6, 8, 10, 15, 20)
    pulse_g: Sequence[float] = (2.0, 5.0, 10.0, 20.0)
    step_fraction: Sequence[float] = (0.05, 0.1, 0.2)
    horizon_s: float = 600.0
    lead_s: float = 60.0
    alpha: float = 0.05
    target_power: float = 0.9


@dataclass
class MeasurementOption:
    """One experiment at its chosen size, with its predicted power."""

    kind: str
    size: float
    unit: str
    power: float
    expected_log_lr: float
    text: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "size": float(self.size),
            "unit": self.unit,
            "power": float(self.power),
            "expected_log_lr": float(self.expected_log_lr),
            "text": self.text,
        }


@dataclass
class Design:
    """The recommended measurement, every option, and the two readings compared."""

    best: MeasurementOption
    options: list[MeasurementOption]
    between: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        out = self.best.to_dict()
        out["between"] = list(self.between)
        out["options"] = [o.to_dict() for o in self.options]
        return out


def power_two_sided(lam: float, alpha: float) -> float:
    """Power of the two-sided level-alpha z test at noncentrality sqrt(lam)."""
    z = stats.norm.ppf(1.0 - alpha / 2.0)
    r = math.sqrt(max(lam, 0.0))
    return float(stats.norm.cdf(r - z) + stats.norm.cdf(-r - z))


def _choose(
    sizes: Sequence[float], lams: Sequence[float], opt: DesignOptions
) -> tuple[float, float, float]:
    """(size, power, lambda) of the smallest size reaching the target power, else the
    largest size."""
    for s, lam in zip(sizes, lams):
        pw = power_two_sided(lam, opt.alpha)
        if pw >= opt.target_power:
            return s, pw, lam
    return sizes[-1], power_two_sided(lams[-1], opt.alpha), lams[-1]


class _Horizon:
    """The line held at its last operating point for ``horizon_s``: inputs and the two models'
    probe predictions with and without an experiment."""

    def __init__(self, data: RunData, a: LineModel, b: LineModel, opt: DesignOptions) -> None:
        inp = data.inputs
        dt = inp.dt_s
        last = data.t_s >= data.t_s[-1] - 60.0
        self.t = np.arange(0.0, opt.horizon_s + dt / 2, dt)
        self.flows = {
            k: np.full(self.t.size, float(np.mean(v[last]))) for k, v in inp.flows_kg_h.items()
        }
        self.components = dict(inp.components)
        self.a, self.b, self.opt = a, b, opt
        self.component = a.config.sensor.component
        base = self._inputs(self.flows, [])
        pa = a.predict(base)
        noise = a.config.sensor.noise
        self.sigma = np.maximum(noise_sd(pa, noise), 1e-6)
        self.whiten = NoiseWhitener(self.sigma, noise)
        self.d0 = self.b.predict(base) - pa

    def _inputs(self, flows: dict[str, np.ndarray], tracers: list[TracerPulse]) -> LineInputs:
        return LineInputs(
            self.t, {k: v.copy() for k, v in flows.items()}, self.components, tracers=tracers
        )

    def lam(self, inputs: LineInputs) -> float:
        """Noncentrality of the experiment ``inputs`` (module docstring)."""
        d = self.b.predict(inputs) - self.a.predict(inputs) - self.d0
        e = self.whiten(d / self.sigma)
        return float(e @ e)

    def pulse(self, grams: float) -> LineInputs:
        p = TracerPulse(t_s=self.opt.lead_s, mass_kg=grams / 1000.0, component=self.component)
        return self._inputs(self.flows, [p])

    def step(self, fraction: float) -> LineInputs:
        flows = {k: v.copy() for k, v in self.flows.items()}
        on = self.t >= self.opt.lead_s
        for k, c in self.components.items():
            if c == self.component:
                flows[k][on] *= 1.0 + fraction
        return self._inputs(flows, [])


def design_measurement(
    data: RunData,
    declared: LineModel,
    probe_effects: Sequence[Effect],
    product_effects: Sequence[Effect],
    heldout: np.ndarray,
    labels: Sequence[str] = (),
    options: DesignOptions | None = None,
) -> Design:
    """The experiment that best separates the probe-side and the product-side readings
    (module docstring). ``heldout``: the samples the assays would be taken over."""
    opt = options or DesignOptions()
    a = declared.augmented(list(probe_effects))
    b = declared.augmented(list(product_effects))
    comp = declared.config.sensor.component
    ca = a.outlet(data.inputs)[comp][heldout]
    cb = b.outlet(data.inputs)[comp][heldout]
    delta = float(np.mean(cb - ca))
    lam_assay = [n * delta**2 / opt.assay_sd_pct_w_w**2 for n in opt.assays]
    n, pw, lam = _choose(list(opt.assays), lam_assay, opt)
    options = [
        MeasurementOption(
            "assay",
            n,
            "samples",
            pw,
            lam / 2.0,
            f"off-line assay of {int(n)} product samples from the held-out window (the two "
            f"readings differ by {delta:+.3f} % w/w in the product; assay sd "
            f"{opt.assay_sd_pct_w_w:g} % w/w)",
        )
    ]
    hz = _Horizon(data, a, b, opt)
    lam_pulse = [hz.lam(hz.pulse(g)) for g in opt.pulse_g]
    g, pw, lam = _choose(list(opt.pulse_g), lam_pulse, opt)
    options.append(
        MeasurementOption(
            "tracer_pulse",
            g,
            "g",
            pw,
            lam / 2.0,
            f"tracer pulse of {g:g} g of {comp} at the inlet, probe read for "
            f"{opt.horizon_s:.0f} s at the current operating point",
        )
    )
    lam_step = [hz.lam(hz.step(f)) for f in opt.step_fraction]
    f, pw, lam = _choose(list(opt.step_fraction), lam_step, opt)
    options.append(
        MeasurementOption(
            "setpoint_step",
            100.0 * f,
            "% of set point",
            pw,
            lam / 2.0,
            f"set-point step of the {comp} feeders by +{100 * f:g} % for {opt.horizon_s:.0f} s",
        )
    )
    best = max(options, key=lambda o: (round(o.power, 2), -KINDS.index(o.kind)))
    return Design(best, options, list(labels))
