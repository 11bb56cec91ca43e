"""Plant simulator: a line run with known (and optionally hidden) behaviour.

``simulate_line(config, duration_s, dt_s, seed, effects, disturbances)``:

1. each feeder is simulated by ``twin_core.feeder.LossInWeightFeeder.simulate`` (PID, refills,
   feed-factor curve) at the controller step and averaged onto the run grid (mass conserving);
   ``ideal`` feeders deliver their set point;
2. disturbances (known flow steps/pulses) are added to the feeder flows; these are the flows the
   feeders *report* (the twin's inputs);
3. hidden ``effects`` (``twin_core.plant.effects``) act on the truth only: feeder effects change
   delivered vs reported flows, rtd effects change the blender's E(t), sensor effects the probe;
   hidden ``open_world`` effects (``twin_core.plant.openworld``, not close-loop candidates) act
   at their feeder, blender or sensor stage;
4. the outlet composition is the mass-flow-weighted convolution of the declared model
   (``twin_core.plant.model``), tracer pulses included; or, with ``blender="fv"``, the blender
   integrated as a finite-volume ODE (``twin_core.plant.blender_fv``: the code path independent
   of the twin's E(t), needed by the open-world blender effects);
5. the NIR probe samples every ``sensor.sample_period_s`` and adds the seed's noise
   (``twin_core.plant.nir``).

Data faults of the records (stuck readings, gaps, clipping, spike bursts, time jumps,
duplicate stamps) are injected into the run's messages: ``twin_core.plant.faults``.

Everything random derives from ``seed`` (numpy SeedSequence: one child per feeder, one for the
NIR noise), so a run is reproducible.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from schemas.line import FeederLine, LineConfig, NIRNoise, TracerPulse
from schemas.messages import Event
from twin_core.plant.effects import Effect, make_effect
from twin_core.plant.model import (
    LineInputs,
    LineModel,
    inlet_component_flows,
    outlet_concentration,
    rtd_blender_config,
    sensor_signal,
)
from twin_core.plant.nir import add_nir_noise
from twin_core.plant.openworld import OpenWorldEffect, make_open_world, open_world_line


@dataclass
class FlowDisturbance:
    """A known change of one feeder's flow: ``delta_kg_h`` added during [t_s, t_s + duration_s).

    ``duration_s = inf`` is a step. It is an input the twin sees (the feeder reports it).
    """

    feeder: str
    t_s: float
    delta_kg_h: float
    duration_s: float = math.inf

    def __post_init__(self) -> None:
        if not (math.isfinite(self.t_s) and self.t_s >= 0):
            raise ValueError(f"disturbance.t_s must be >= 0, got {self.t_s!r}")
        if not math.isfinite(self.delta_kg_h):
            raise ValueError(f"disturbance.delta_kg_h must be finite, got {self.delta_kg_h!r}")
        if not self.duration_s > 0:
            raise ValueError(f"disturbance.duration_s must be > 0, got {self.duration_s!r}")


@dataclass
class FeederRecord:
    """One feeder on the run grid. ``flow_kg_h`` is what the feeder reports (twin input);
    ``delivered_kg_h`` what really entered the blender (differs under hidden feeder effects)."""

    id: str
    component: str
    flow_kg_h: np.ndarray
    delivered_kg_h: np.ndarray
    screw_speed_rpm: np.ndarray
    hopper_mass_kg: np.ndarray
    refilling: np.ndarray
    feed_factor_g_rev: np.ndarray
    refills: list[tuple[float, float]] = field(default_factory=list)


@dataclass
class LineRun:
    """Result of :func:`simulate_line`.

    t_s: uniform grid; feeders: feeder id -> :class:`FeederRecord`; outlet_true_pct_w_w: component
    -> true outlet concentration; sensor_component; sensor_true_pct_w_w: noise-free probe signal
    (sensor effects and baseline included); measured_pct_w_w: NIR reading (NaN between samples
    when the sample period exceeds dt); outliers: mask of injected outliers; events; effects:
    ground truth of the hidden effects (dict form); disturbances; config; seed. ``events`` are
    the wire contract's ``schemas.messages.Event`` (refills, disturbances, tracer pulses).
    """

    t_s: np.ndarray
    feeders: dict[str, FeederRecord]
    outlet_true_pct_w_w: dict[str, np.ndarray]
    sensor_component: str
    sensor_true_pct_w_w: np.ndarray
    measured_pct_w_w: np.ndarray
    outliers: np.ndarray
    events: list[Event]
    effects: list[dict[str, Any]]
    disturbances: list[FlowDisturbance]
    config: LineConfig
    seed: int | None = None
    #: ground truth of the hidden open-world effects (dict form) and of the data faults
    open_world: list[dict[str, Any]] = field(default_factory=list)
    faults: list[dict[str, Any]] = field(default_factory=list)
    #: the blender code path of the truth: "convolution" (declared model's) or "fv"
    blender: str = "convolution"

    def inputs(self) -> LineInputs:
        """The twin's view of the inputs: reported flows, refill flags, tracer pulses."""
        return LineInputs(
            t_s=self.t_s,
            flows_kg_h={k: f.flow_kg_h.copy() for k, f in self.feeders.items()},
            components={k: f.component for k, f in self.feeders.items()},
            refilling={k: f.refilling.copy() for k, f in self.feeders.items()},
            tracers=list(self.config.tracers),
            screw_speed_rpm={k: f.screw_speed_rpm.copy() for k, f in self.feeders.items()},
        )

    def predicted_declared(self) -> np.ndarray:
        """The declared model's prediction of the probe reading (no hidden effects)."""
        return LineModel(self.config).predict(self.inputs())

    def summary(self) -> dict[str, Any]:
        return {
            "duration_s": float(self.t_s[-1] - self.t_s[0]),
            "dt_s": float(self.t_s[1] - self.t_s[0]),
            "n": int(self.t_s.size),
            "config": self.config.line_dict(),
            "effects": self.effects,
            "open_world": self.open_world,
            "faults": self.faults,
            "blender": self.blender,
            "events": [e.model_dump(mode="json") for e in self.events],
            "seed": self.seed,
        }


def simulate_feeder(
    spec: FeederLine, duration_s: float, dt_s: float, n: int, seed: np.random.Generator | int
) -> FeederRecord:
    """One feeder of the line on ``n`` ticks of ``dt_s``: the LIW simulator
    (``twin_core.feeder.LossInWeightFeeder``, configured by ``spec.liw_config()``) run at its
    control period, each tick the mean flow of its sub-steps, the screw speed, hopper mass and
    feed factor at the tick's start and the refill flag up if any sub-step refilled; an
    ``ideal`` feeder runs at its set point."""
    t = np.arange(n) * dt_s
    if spec.ideal:
        q = np.full(n, spec.setpoint_kg_h)
        return FeederRecord(
            spec.id,
            spec.component,
            q,
            q.copy(),
            np.full(n, np.nan),
            np.full(n, np.nan),
            np.zeros(n, dtype=bool),
            np.full(n, np.nan),
        )
    from twin_core.feeder import LossInWeightFeeder

    feeder = LossInWeightFeeder(spec.liw_config())
    cp = float(feeder.config.control_period_s)
    sub = max(1, int(math.ceil(dt_s / cp - 1e-9)))
    fdt = dt_s / sub
    tr = feeder.simulate(duration_s + dt_s, fdt, seed=seed)
    m = n * sub
    if tr.t_s.size < m:
        raise ValueError(f"feeder {spec.id}: trace too short ({tr.t_s.size} < {m})")

    def bin_mean(a: np.ndarray) -> np.ndarray:
        return np.asarray(a[:m], dtype=float).reshape(n, sub).mean(axis=1)

    flow = bin_mean(tr.mass_flow_kg_h)
    refilling = np.asarray(tr.refilling[:m]).reshape(n, sub).any(axis=1)
    idx = np.arange(n) * sub
    return FeederRecord(
        spec.id,
        spec.component,
        flow,
        flow.copy(),
        np.asarray(tr.screw_speed_rpm, dtype=float)[idx],
        np.asarray(tr.hopper_mass_kg, dtype=float)[idx],
        refilling,
        np.asarray(tr.feed_factor_g_rev, dtype=float)[idx],
        [(float(a), float(b)) for a, b in tr.refills if a <= t[-1]],
    )


def simulate_line(
    config: LineConfig,
    duration_s: float,
    dt_s: float = 1.0,
    seed: int | None = None,
    effects: Sequence[Effect | Mapping[str, Any]] = (),
    disturbances: Sequence[FlowDisturbance | Mapping[str, Any]] = (),
    open_world: Sequence[OpenWorldEffect | Mapping[str, Any]] = (),
    blender: str = "convolution",
    feeder_records: Mapping[str, FeederRecord] | None = None,
    lot_assays: Sequence[Any] = (),
    hopper_mixing: float = 0.0,
) -> LineRun:
    """Simulate the line for ``duration_s`` on a uniform grid of step ``dt_s``.

    ``effects`` are hidden from the declared model (ground truth in ``LineRun.effects``);
    ``disturbances`` are known flow changes (reported by the feeders, listed as events);
    ``open_world`` effects are hidden too (``LineRun.open_world``). See the module docstring
    for the chain; the outlet is seed 6.2 Eq. (6) convolution applied per component mass flow
    (``blender="convolution"``) or the finite-volume vessel (``"fv"``). ``feeder_records``:
    the feeders of an earlier run of the same configuration, grid and seed (the LIW simulation
    is the slow part of a run), used as copies instead of simulating them again. ``lot_assays``:
    raw-material lots whose content is not the label's (``twin_core.tracking.assay.LotAssay``:
    the truth's API feeder delivers that share of the lot as inert matter; the lot shares of
    its discharge follow the hopper law with stirred share ``hopper_mixing``).
    """
    if not isinstance(config, LineConfig):
        raise ValueError(f"config must be a LineConfig, got {type(config).__name__}")
    config = rtd_blender_config(config)
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"duration_s must be > 0, got {duration_s!r}")
    if not (math.isfinite(dt_s) and 0 < dt_s <= duration_s):
        raise ValueError(f"dt_s must be in (0, duration_s], got {dt_s!r}")
    effs = [make_effect(e) for e in effects]
    ows = [make_open_world(e) for e in open_world]
    if blender not in ("convolution", "fv"):
        raise ValueError(f"blender must be 'convolution' or 'fv', got {blender!r}")
    dists = [d if isinstance(d, FlowDisturbance) else FlowDisturbance(**d) for d in disturbances]
    names = [f.id for f in config.feeders]
    for e in [*effs, *ows]:
        if e.stage == "feeder" and e.target is not None and e.target not in names:
            raise ValueError(f"effect {e.name}.target must be one of {names}, got {e.target!r}")
    for d in dists:
        if d.feeder not in names:
            raise ValueError(f"disturbance.feeder must be one of {names}, got {d.feeder!r}")

    n = int(round(duration_s / dt_s)) + 1
    t = np.arange(n) * dt_s
    ss = np.random.SeedSequence(seed)
    children = ss.spawn(len(config.feeders) + 1)

    feeders: dict[str, FeederRecord] = {}
    for spec, child in zip(config.feeders, children[:-1]):
        if feeder_records is not None:
            feeders[spec.id] = _copied(feeder_records, spec.id, n)
        else:
            rng = np.random.default_rng(child)
            feeders[spec.id] = simulate_feeder(spec, duration_s, dt_s, n, rng)
    for d in dists:
        rec = feeders[d.feeder]
        on = (t >= d.t_s) & (t < d.t_s + d.duration_s)
        rec.flow_kg_h = np.maximum(rec.flow_kg_h + np.where(on, d.delta_kg_h, 0.0), 0.0)
    events = _line_events(feeders, dists, config.tracers)

    run_inputs = LineInputs(
        t_s=t,
        flows_kg_h={k: f.flow_kg_h for k, f in feeders.items()},
        components={k: f.component for k, f in feeders.items()},
        refilling={k: f.refilling for k, f in feeders.items()},
        tracers=list(config.tracers),
    )
    if lot_assays:  # the truth's inputs: lots of other assay (twin_core.tracking.assay)
        from twin_core.tracking.assay import lot_assay_flows

        hoppers = {k: f.hopper_mass_kg for k, f in feeders.items()}
        initial = {f.id: f.initial_lot for f in config.feeders}
        flows, comps = lot_assay_flows(
            t,
            run_inputs.flows_kg_h,
            run_inputs.components,
            hoppers,
            events,
            lot_assays,
            hopper_mixing,
            initial,
        )
        run_inputs = LineInputs(
            t_s=t,
            flows_kg_h=flows,
            components=comps,
            refilling=run_inputs.refilling,
            tracers=run_inputs.tracers,
        )
        if ows or blender == "fv":
            raise ValueError("lot_assays need the convolution blender without open-world effects")
    sensor = config.sensor
    if ows or blender == "fv":
        line = open_world_line(config, t, feeders, effs, ows, blender)
        for name, rec in feeders.items():
            rec.delivered_kg_h = line.delivered_kg_h[name]
        outlet, sig = line.outlet_pct_w_w, line.signal
    else:
        # delivered flows under the hidden feeder effects (per feeder, for the record)
        for name, rec in feeders.items():
            single = LineInputs(
                t_s=t,
                flows_kg_h={name: rec.flow_kg_h},
                components={name: rec.component},
                refilling={name: rec.refilling},
            )
            feeder_effs = [e for e in effs if e.stage == "feeder"]
            rec.delivered_kg_h = inlet_component_flows(single, feeder_effs)[rec.component] * 3600.0
            if lot_assays:  # the lot-assay truth: what of the material is the component
                rec.delivered_kg_h *= _ratio(run_inputs.flows_kg_h[name], rec.flow_kg_h)
        outlet = outlet_concentration(run_inputs, config.blender, effs)
        c = outlet.get(sensor.component, np.zeros(n))
        sig = sensor_signal(t, c, effs, sensor.noise.baseline_offset)
    step = max(1, int(round(sensor.sample_period_s / dt_s)))
    sampled = np.zeros(n, dtype=bool)
    sampled[::step] = True
    noisy, outl = add_nir_noise(sig[sampled], _noise_without_offset(sensor.noise), children[-1])
    measured = np.full(n, np.nan)
    measured[sampled] = noisy
    outliers = np.zeros(n, dtype=bool)
    outliers[sampled] = outl

    return LineRun(
        t_s=t,
        feeders=feeders,
        outlet_true_pct_w_w=outlet,
        sensor_component=sensor.component,
        sensor_true_pct_w_w=sig,
        measured_pct_w_w=measured,
        outliers=outliers,
        events=events,
        effects=[e.to_dict() for e in effs],
        disturbances=dists,
        config=config,
        seed=seed,
        open_world=[e.to_dict() for e in ows],
        blender=blender,
    )


def _copied(records: Mapping[str, FeederRecord], feeder: str, n: int) -> FeederRecord:
    """A copy of feeder ``feeder``'s record (its arrays copied), checked for length ``n``."""
    rec = records.get(feeder)
    if rec is None or rec.flow_kg_h.shape != (n,):
        raise ValueError(f"feeder_records must hold feeder {feeder!r} on {n} ticks")
    arrays = {
        k: np.array(getattr(rec, k))
        for k in (
            "flow_kg_h",
            "delivered_kg_h",
            "screw_speed_rpm",
            "hopper_mass_kg",
            "refilling",
            "feed_factor_g_rev",
        )
    }
    return FeederRecord(rec.id, rec.component, refills=list(rec.refills), **arrays)


def _ratio(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a / b where b > 0, else 1."""
    return np.where(b > 0, a / np.where(b > 0, b, 1.0), 1.0)


def _line_events(
    feeders: Mapping[str, FeederRecord],
    disturbances: Sequence[FlowDisturbance],
    tracers: Sequence[TracerPulse],
) -> list[Event]:
    """The run's events as the line reports them (``schemas.messages.Event``, numbered in time
    order): hopper refills (source: the feeder; ``lot_id``: ``<feeder>-L<k>`` for its k-th
    refill, ``twin_core.tracking.refill_lot_id``), disturbances and their ends (source: the
    feeder, ``magnitude``: the flow change in kg/h) and tracer pulses (source: the component)."""
    from twin_core.tracking.tracker import refill_lot_id

    rows: list[dict[str, Any]] = []
    for fid, rec in feeders.items():
        for k, (a, b) in enumerate(rec.refills, start=1):
            for t_s, kind in ((a, "refill_start"), (b, "refill_stop")):
                rows.append(
                    dict(
                        t=t_s,
                        kind=kind,
                        source=fid,
                        component=rec.component,
                        detail="hopper refill",
                        lot_id=refill_lot_id(fid, k),
                    )
                )
    for d in disturbances:
        comp = feeders[d.feeder].component
        rows.append(
            dict(
                t=d.t_s,
                kind="disturbance",
                source=d.feeder,
                component=comp,
                magnitude=d.delta_kg_h,
                duration_s=d.duration_s if math.isfinite(d.duration_s) else None,
                detail=f"{d.delta_kg_h:+g} kg/h flow change",
            )
        )
        if math.isfinite(d.duration_s):
            rows.append(
                dict(
                    t=d.t_s + d.duration_s, kind="disturbance_end", source=d.feeder, component=comp
                )
            )
    for p in tracers:
        rows.append(
            dict(
                t=p.t_s,
                kind="tracer_pulse",
                source=p.component,
                component=p.component,
                mass_kg=p.mass_kg,
                duration_s=p.duration_s,
                detail=f"{p.mass_kg * 1000:g} g {p.component} tracer pulse",
            )
        )
    rows.sort(key=lambda r: r["t"])
    return [Event(seq=i, **r) for i, r in enumerate(rows)]


def _noise_without_offset(noise: NIRNoise) -> NIRNoise:
    """The baseline offset is already in the sensor signal; the random part only."""
    return noise.model_copy(update={"baseline_offset": 0.0})
