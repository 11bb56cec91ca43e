"""Validation cases for the structure searches, generated independently of them.

Each case is a recording of the seed line whose truth lies outside the twin's declared model
and its candidate library, made by a code path the searches do not use:

- ``pulsation``: the API feeder delivers its reported flow times (1 + a sin(2 pi f t + phi)),
  either at the screw's rotation frequency (a screw-locked pulsation the reported flow and
  speed do not show) or as a slow controller limit cycle that the reported screw speed carries
  (the load cell's flow filter hides it from the reported flow);
- ``throughput_tau``: the blender's dispersion time scales with the throughput,
  tau(Q) = tau_ref (Q_ref / Q)^k (a constant hold-up at k = 1; Gao et al. 2012 for the
  throughput dependence of the mean residence time), simulated piecewise: the outlet of every
  throughput level is the declared model's with that level's tau, spliced at the set-point
  changes;
- ``two_zone``: the blender is a plug-flow delay followed by an active well-mixed zone of
  hold-up H1 exchanging with a stagnant zone H2 at k (kg/s), the component mass balances
  integrated as an ODE (exactly over each sample interval, matrix exponential; checked against
  scipy's ``solve_ivp`` in the tests), no RTD convolution;

and ``none`` (the declared model is the truth). The line runs 2 h at 1 Hz (``structure_scenario``):
API set-point steps of +-10 % every 10 min, hopper refills, optionally tracer pulses, and, for
the throughput case, throughput levels of 100 / 125 / 85 / 110 % for a quarter of the run each.
The feeders' screw speeds follow their set-point changes (speed proportional to flow). The NIR
reading is the noise-free signal plus the seed's noise (``twin_core.plant.nir``), optionally
scaled (``with_noise_scale``: the declared noise is scaled the same way).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.linalg import expm

from schemas.line import LineConfig
from twin_core.closeloop.data import RunData
from twin_core.online.inlet import event_record
from twin_core.plant.model import (
    LineInputs,
    LineModel,
    inlet_component_flows,
    outlet_concentration,
    sensor_signal,
)
from twin_core.plant.nir import add_nir_noise
from twin_core.plant.seed import seed_line
from twin_core.plant.simulate import FlowDisturbance, LineRun, simulate_line

#: relative throughput levels of the varying-throughput scenario (a quarter of the run each)
THROUGHPUT_LEVELS = (1.0, 1.25, 0.85, 1.1)
#: relative API set-point steps, cycled every ``API_STEP_S``
API_STEPS = (0.0, 0.1, -0.1, 0.05, -0.05, 0.1)
API_STEP_S = 600.0


def structure_scenario(
    duration_s: float = 7200.0,
    vary_throughput: bool = False,
    tracer_pulses: bool = False,
) -> tuple[LineConfig, list[FlowDisturbance]]:
    """The seed line (12 kg/h, 10 % API, seed NIR noise) with API set-point steps every
    10 min, API hopper refills (1.2 -> 0.4 kg: about three in 2 h), optionally the throughput
    levels of ``THROUGHPUT_LEVELS`` and API tracer pulses of 5 g every 15 min."""
    if not (math.isfinite(duration_s) and duration_s >= 1200.0):
        raise ValueError(f"duration_s must be >= 1200, got {duration_s!r}")
    times = tuple(450.0 + 900.0 * i for i in range(int((duration_s - 600.0) // 900.0) + 1))
    cfg = seed_line(
        tracer_g=tuple(5.0 for _ in times) if tracer_pulses else (),
        tracer_times_s=times if tracer_pulses else (),
        api_liw=dict(initial_mass_kg=1.2, refill_low_kg=0.4, refill_high_kg=1.2),
        excipient_liw=dict(initial_mass_kg=8.0, refill_low_kg=1.5, refill_high_kg=8.0),
    )
    levels = THROUGHPUT_LEVELS if vary_throughput else (1.0,)
    quarter = duration_s / len(levels)
    dist: list[FlowDisturbance] = []
    for i, lev in enumerate(levels):
        if lev != 1.0:
            for f in cfg.feeders:
                dist.append(
                    FlowDisturbance(f.id, i * quarter, (lev - 1.0) * f.setpoint_kg_h, quarter)
                )
    api = cfg.feeders[0]
    k = 1
    while k * API_STEP_S < duration_s:
        rel = API_STEPS[k % len(API_STEPS)]
        if rel != 0.0:
            lev = levels[min(int(k * API_STEP_S // quarter), len(levels) - 1)]
            dist.append(
                FlowDisturbance(api.id, k * API_STEP_S, rel * lev * api.setpoint_kg_h, API_STEP_S)
            )
        k += 1
    return cfg, dist


def with_noise_scale(run: LineRun, scale: float) -> LineRun:
    """A copy of ``run`` whose sensor noise (declared and simulated) is the seed's times
    ``scale`` (white, 1/f and proportional parts; the feeders are shared)."""
    if not scale > 0:
        raise ValueError(f"scale must be > 0, got {scale!r}")
    n = run.config.sensor.noise
    noise = n.model_copy(
        update={
            "white_sd": n.white_sd * scale,
            "pink_sd": n.pink_sd * scale,
            "proportional_rel": n.proportional_rel * scale,
        }
    )
    sensor = run.config.sensor.model_copy(update={"noise": noise})
    return replace(run, config=run.config.model_copy(update={"sensor": sensor}))


def throughput_level_index(cfg: LineConfig, t_s: np.ndarray, duration_s: float) -> np.ndarray:
    """Index into ``THROUGHPUT_LEVELS`` of every sample of the varying-throughput scenario."""
    quarter = duration_s / len(THROUGHPUT_LEVELS)
    return np.minimum((np.asarray(t_s) // quarter).astype(int), len(THROUGHPUT_LEVELS) - 1)


def base_run(
    duration_s: float = 7200.0,
    seed: int = 0,
    vary_throughput: bool = False,
    tracer_pulses: bool = False,
    noise_scale: float = 1.0,
) -> LineRun:
    """The scenario simulated without any effect; screw speeds scaled with the set-point
    changes (the simulator's feeders do not see the disturbances)."""
    cfg, dist = structure_scenario(duration_s, vary_throughput, tracer_pulses)
    run = simulate_line(cfg, duration_s, seed=seed, disturbances=dist)
    for fid, rec in run.feeders.items():
        delta = np.zeros_like(run.t_s)
        for d in dist:
            if d.feeder == fid:
                delta += np.where((run.t_s >= d.t_s) & (run.t_s < d.t_s + d.duration_s), 1, 0) * (
                    d.delta_kg_h
                )
        own = np.maximum(rec.flow_kg_h - delta, 1e-9)
        rec.screw_speed_rpm = rec.screw_speed_rpm * rec.flow_kg_h / own
    return with_noise_scale(run, noise_scale) if noise_scale != 1.0 else run


@dataclass
class StructureCase:
    """A validation record: ``data``, the declared ``model``, the noise-free probe ``signal``
    and the ``truth`` (kind and true values for interval coverage)."""

    name: str
    data: RunData
    model: LineModel
    signal: np.ndarray
    truth: dict[str, Any] = field(default_factory=dict)


def _record(run: LineRun, signal: np.ndarray, seed: int, name: str, inputs=None) -> RunData:
    noise = run.config.sensor.noise.model_copy(update={"baseline_offset": 0.0})
    rng = np.random.default_rng([seed, 7919])
    measured, _ = add_nir_noise(signal, noise, rng)
    return RunData(
        run.t_s,
        measured,
        inputs if inputs is not None else run.inputs(),
        [event_record(e) for e in run.events],
        name=name,
    )


def _probe(run: LineRun, c: np.ndarray) -> np.ndarray:
    return sensor_signal(run.t_s, c, [], run.config.sensor.noise.baseline_offset)


def none_case(run: LineRun, seed: int) -> StructureCase:
    """The declared model is the truth."""
    sig = run.predicted_declared()
    return StructureCase(
        "none", _record(run, sig, seed, "none"), LineModel(run.config), sig, {"kind": None}
    )


def _sinusoid_amplitude(t: np.ndarray, y: np.ndarray, f_hz: float) -> float:
    cols = np.column_stack(
        [np.ones_like(t), np.cos(2 * np.pi * f_hz * t), np.sin(2 * np.pi * f_hz * t)]
    )
    beta = np.linalg.lstsq(cols, y, rcond=None)[0]
    return float(math.hypot(beta[1], beta[2]))


def pulsation_case(
    run: LineRun,
    seed: int,
    amplitude: float,
    period_s: float | None = None,
    screw_shows_it: bool = False,
) -> StructureCase:
    """API flow pulsation of relative ``amplitude``: at the API screw's rotation frequency
    (``period_s`` None) or at ``period_s``; ``screw_shows_it``: the reported API screw speed
    carries the same relative oscillation."""
    t = run.t_s
    api = run.feeders["api"]
    f_hz = float(np.median(api.screw_speed_rpm)) / 60.0 if period_s is None else 1.0 / period_s
    phase = float(np.random.default_rng([seed, 31]).uniform(0, 2 * np.pi))
    wave = amplitude * np.sin(2 * np.pi * f_hz * t + phase)
    inputs = run.inputs()
    delivered = LineInputs(
        t_s=t,
        flows_kg_h={
            k: (v * (1.0 + wave) if k == "api" else v) for k, v in inputs.flows_kg_h.items()
        },
        components=inputs.components,
        refilling=inputs.refilling,
        tracers=inputs.tracers,
    )
    sig = _probe(run, outlet_concentration(delivered, run.config.blender)["api"])
    if screw_shows_it:
        inputs.screw_speed_rpm["api"] = inputs.screw_speed_rpm["api"] * (1.0 + wave)
    declared = run.predicted_declared()
    truth = {
        "kind": "periodic",
        "frequency_hz": f_hz,
        "amplitude_pct_w_w": _sinusoid_amplitude(t, sig - declared, f_hz),
        "source": "api:screw_speed" if screw_shows_it else "api",
    }
    return StructureCase(
        "pulsation", _record(run, sig, seed, "pulsation", inputs), LineModel(run.config), sig, truth
    )


def throughput_tau_case(run: LineRun, seed: int, exponent: float = 1.0) -> StructureCase:
    """Piecewise simulation of tau(Q) = tau_ref (Q_ref / Q)^exponent at the scenario's
    throughput levels (``run`` from ``base_run(vary_throughput=True)``)."""
    cfg = run.config
    t = run.t_s
    duration = float(t[-1] - t[0]) + float(t[1] - t[0])
    idx = throughput_level_index(cfg, t - t[0], duration)
    tau_ref = cfg.blender.params["tau"]
    q_ref = sum(f.setpoint_kg_h for f in cfg.feeders)
    sig = np.zeros_like(t)
    taus = []
    for i, lev in enumerate(THROUGHPUT_LEVELS):
        tau = tau_ref * (1.0 / lev) ** exponent
        taus.append(tau)
        params = dict(cfg.blender.params, tau=tau)
        blender = cfg.blender.model_copy(update={"params": params})
        c = outlet_concentration(run.inputs(), blender)["api"]
        sig = np.where(idx == i, _probe(run, c), sig)
    truth = {
        "kind": "parameter_dependence",
        "param": "blender.tau",
        "covariate": "throughput",
        "q_levels": [q_ref * lev for lev in THROUGHPUT_LEVELS],
        "tau_levels": taus,
        "tau_ref": tau_ref,
        "q_ref": q_ref,
        "exponent": exponent,
    }
    return StructureCase(
        "throughput_tau", _record(run, sig, seed, "throughput_tau"), LineModel(cfg), sig, truth
    )


def two_zone_rtd(
    lag_s: np.ndarray, q_kg_s: float, h1_kg: float, h2_kg: float, k_kg_s: float, delay_s: float
) -> np.ndarray:
    """Impulse response (1/s) of the two-zone blender at constant throughput: c1' =
    (q (c_in - c1) - k (c1 - c2)) / H1, c2' = k (c1 - c2) / H2, outlet c1 after ``delay_s``
    (matrix exponential of the linear system)."""
    a = np.array([[-(q_kg_s + k_kg_s) / h1_kg, k_kg_s / h1_kg], [k_kg_s / h2_kg, -k_kg_s / h2_kg]])
    b = np.array([q_kg_s / h1_kg, 0.0])
    out = np.zeros_like(lag_s, dtype=float)
    dt = float(lag_s[1] - lag_s[0])
    step = expm(a * dt)
    start = int(np.searchsorted(lag_s, delay_s))
    frac = (lag_s[start] - delay_s) if start < lag_s.size else 0.0
    x = expm(a * frac) @ b
    for i in range(start, lag_s.size):
        out[i] = x[0]
        x = step @ x
    return out


def two_zone_outlet(
    m_c: np.ndarray,
    m_tot: np.ndarray,
    dt: float,
    h1_kg: float,
    h2_kg: float,
    k_kg_s: float,
    delay_steps: int,
) -> np.ndarray:
    """Outlet mass fraction (0..1) of the two-zone exchange blender on the sample grid.

    Component masses M1 (active, hold-up H1, outflow = inflow) and M2 (stagnant, H2):
    M1' = m_c(t - d) - (m_tot(t - d) + k) M1 / H1 + k M2 / H2, M2' = k M1 / H1 - k M2 / H2,
    the flows (kg/s) held over each sample interval and delayed by ``delay_steps`` samples
    (plug flow before the zones); integrated exactly per interval (zero-order hold: the
    matrix exponential of the augmented system [[A, b], [0, 0]]), starting at the steady
    state of the first flows. The outlet is M1 / H1."""
    n = m_c.size
    idx = np.clip(np.arange(n) - delay_steps, 0, n - 1)
    c_in0 = float(m_c[0] / m_tot[0])
    x = np.array([h1_kg * c_in0, h2_kg * c_in0, 1.0])
    out = np.empty(n)
    aug = np.zeros((3, 3))
    aug[0, 1], aug[1, 0], aug[1, 1] = k_kg_s / h2_kg, k_kg_s / h1_kg, -k_kg_s / h2_kg
    for i in range(n):
        out[i] = x[0] / h1_kg
        j = idx[i]
        aug[0, 0] = -(m_tot[j] + k_kg_s) / h1_kg
        aug[0, 2] = m_c[j]
        x = expm(aug * dt) @ x
    return out


def two_zone_case(
    run: LineRun,
    seed: int,
    active_s: float = 20.0,
    stagnant_kg: float = 0.04,
    exchange_kg_h: float = 3.6,
    delay_s: float = 10.0,
) -> StructureCase:
    """The two-zone exchange blender (:func:`two_zone_outlet`, see module): active hold-up
    ``active_s`` x the nominal throughput, stagnant hold-up ``stagnant_kg``, exchange
    ``exchange_kg_h``, plug delay ``delay_s`` before the zones."""
    cfg = run.config
    t = run.t_s
    dt = float(t[1] - t[0])
    flows = inlet_component_flows(run.inputs(), [])
    m_api = np.asarray(flows["api"], dtype=float)
    m_tot = np.sum([np.asarray(v, dtype=float) for v in flows.values()], axis=0)
    q_nom = sum(f.setpoint_kg_h for f in cfg.feeders) / 3600.0
    h1, h2, k = active_s * q_nom, stagnant_kg, exchange_kg_h / 3600.0
    c = 100.0 * two_zone_outlet(m_api, m_tot, dt, h1, h2, k, int(round(delay_s / dt)))
    sig = _probe(run, c)
    lag = np.arange(0.0, 600.0, dt)
    truth = {
        "kind": "kernel_correction",
        "rtd_lag_s": lag,
        "rtd": two_zone_rtd(lag, q_nom, h1, h2, k, delay_s),
        "mean_residence_time_s": delay_s + (h1 + h2) / q_nom,
    }
    return StructureCase(
        "two_zone", _record(run, sig, seed, "two_zone"), LineModel(cfg), sig, truth
    )


def openworld_case(
    duration_s: float,
    seed: int,
    noise: float = 1.0,
    amplitude: float = 0.0,
    pulses_per_rev: float = 1.0,
    tracers: bool = False,
) -> StructureCase:
    """A record of the open-world benchmark's scenario (``twin_core.plant.openworld_cases.
    openworld_scenario``: its API and line-rate set-point steps and refills, cut to
    ``duration_s``; the seed's NIR noise times ``noise``) simulated by the plant with the
    finite-volume blender, with the plant's ``screw_pulsation`` of the API feeder
    (``twin_core.plant.openworld``: the delivered flow times 1 + a sin(n theta + phi), theta the
    screw's angle from its reported speed, averaged over each tick) when ``amplitude`` > 0,
    else effect-free. Truth: the relative ``amplitude`` and ``pulses_per_rev`` n (the period
    at a screw speed is 60 / (n rpm))."""
    from twin_core.plant.openworld_cases import Setting, openworld_scenario

    cfg = openworld_scenario(Setting(tracers, noise), duration_s)
    phase = float(np.random.default_rng([seed, 53]).uniform(-math.pi, math.pi))
    ow = (
        [
            {
                "name": "screw_pulsation",
                "target": "api",
                "params": {
                    "amplitude": amplitude,
                    "pulses_per_rev": pulses_per_rev,
                    "phase": phase,
                },
            }
        ]
        if amplitude > 0
        else []
    )
    run = simulate_line(cfg, duration_s, seed=seed, open_world=ow, blender="fv")
    data = RunData(
        run.t_s,
        run.measured_pct_w_w,
        run.inputs(),
        [event_record(e) for e in run.events],
        name="screw_pulsation" if ow else "none",
    )
    truth: dict[str, Any] = {"kind": "periodic" if ow else None}
    if ow:
        truth.update(amplitude=amplitude, pulses_per_rev=pulses_per_rev, feeder="api")
    return StructureCase(data.name, data, LineModel(run.config), run.sensor_true_pct_w_w, truth)


__all__ = [
    "API_STEPS",
    "API_STEP_S",
    "THROUGHPUT_LEVELS",
    "StructureCase",
    "base_run",
    "none_case",
    "openworld_case",
    "pulsation_case",
    "structure_scenario",
    "throughput_level_index",
    "throughput_tau_case",
    "two_zone_case",
    "two_zone_outlet",
    "two_zone_rtd",
    "with_noise_scale",
]
