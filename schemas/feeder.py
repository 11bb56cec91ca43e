"""Configuration of a loss-in-weight (LIW) feeder simulation.

The numbers default to a bench-scale twin-screw feeder (K-Tron KT20 class) dosing a
microcrystalline-cellulose-like excipient at 12 kg/h, the operating point of the seed's
chapter 6 experiments. Units are part of every field name.

The feed factor follows the seed's Eq. (2) (Escotet-Espinoza et al.):
``FF(W) = ff_max - (ff_max - ff_min) exp(-beta W)`` with W the hopper mass in kg.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["FeederConfig", "loop_spectral_radius"]

#: g/rev * rev/min -> kg/h
G_PER_MIN_TO_KG_PER_H = 60.0 / 1000.0


class FeederConfig(BaseModel):
    """Loss-in-weight feeder: feed factor, hopper and refill, PID controller, noise.

    Controller: the PID acts on the flow error (kg/h) and outputs a flow demand (kg/h) that is
    divided by the feed factor FF(W) at the measured weight to give the screw speed, so ``kp``
    is dimensionless, ``ki`` in 1/s and ``kd`` in s. The gains are checked for closed-loop
    stability of the linearised loop (:func:`loop_spectral_radius`).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field("feeder", description="feeder id (e.g. 'api', 'excipient')")
    mode: Literal["gravimetric", "volumetric"] = Field(
        "gravimetric",
        description="gravimetric: PID on screw speed from the load-cell flow estimate; "
        "volumetric: constant screw speed (open loop)",
    )
    setpoint_kg_h: float = Field(12.0, gt=0, description="mass-flow set point (kg/h)")
    setpoint_schedule: list[tuple[float, float]] = Field(
        default_factory=list,
        description="optional set-point changes as (t_s, setpoint_kg_h), applied from t_s on",
    )
    volumetric_speed_rpm: float | None = Field(
        None, gt=0, description="screw speed in volumetric mode; default: the set point at FF(W0)"
    )

    # feed factor, seed Eq. (2)
    ff_max_g_rev: float = Field(6.0, gt=0, description="feed factor of a full hopper (g/rev)")
    ff_min_g_rev: float = Field(3.5, ge=0, description="feed factor extrapolated to W = 0 (g/rev)")
    beta_per_kg: float = Field(0.8, ge=0, description="feed-factor decay constant (1/kg)")

    # hopper and refill
    initial_mass_kg: float = Field(5.0, ge=0, description="hopper mass at t = 0 (kg)")
    refill_low_kg: float = Field(1.5, ge=0, description="refill starts at this load-cell mass")
    refill_high_kg: float = Field(5.0, gt=0, description="refill stops at this load-cell mass")
    refill_rate_kg_s: float = Field(0.5, gt=0, description="mass added per second while refilling")
    refill_settle_s: float = Field(
        5.0, ge=0, description="volumetric hold after the refill stops (load cell settling)"
    )
    refill_enabled: bool = True

    # screw drive
    screw_min_rpm: float = Field(0.0, ge=0)
    screw_max_rpm: float = Field(150.0, gt=0)
    motor_tau_s: float = Field(0.5, ge=0, description="first-order lag of the screw drive")

    # controller and flow estimation from the load cell
    kp: float = Field(0.3, ge=0, description="proportional gain (flow demand per flow error)")
    ki: float = Field(0.1, ge=0, description="integral gain (1/s)")
    kd: float = Field(0.0, ge=0, description="derivative gain (s)")
    control_period_s: float = Field(0.1, gt=0, description="controller update period")
    flow_window_s: float = Field(
        5.0, gt=0, description="load-cell regression window for the flow estimate"
    )
    flow_filter_tau_s: float = Field(
        1.0, ge=0, description="first-order filter on the flow estimate"
    )

    # noise
    flow_noise_rel: float = Field(
        0.02, ge=0, description="std of the relative process noise on the feed factor"
    )
    flow_noise_tau_s: float = Field(
        2.0, gt=0, description="correlation time of the process noise (Ornstein-Uhlenbeck)"
    )
    load_cell_noise_kg: float = Field(0.0005, ge=0, description="std of the load-cell noise")

    @model_validator(mode="after")
    def _check_consistency(self) -> FeederConfig:
        if self.ff_min_g_rev > self.ff_max_g_rev:
            raise ValueError(
                f"ff_min_g_rev must be <= ff_max_g_rev, got {self.ff_min_g_rev} > {self.ff_max_g_rev}"
            )
        if self.screw_min_rpm >= self.screw_max_rpm:
            raise ValueError(
                f"screw_min_rpm must be < screw_max_rpm, got {self.screw_min_rpm} >= "
                f"{self.screw_max_rpm}"
            )
        if self.refill_enabled and self.refill_low_kg >= self.refill_high_kg:
            raise ValueError(
                f"refill_low_kg must be < refill_high_kg, got {self.refill_low_kg} >= "
                f"{self.refill_high_kg}"
            )
        if self.mode == "gravimetric" and self.kp == 0 and self.ki == 0:
            raise ValueError("gravimetric mode needs kp > 0 or ki > 0, got kp=0.0 and ki=0.0")
        if self.flow_window_s < 2 * self.control_period_s:
            raise ValueError(
                f"flow_window_s must be >= 2 control periods ({2 * self.control_period_s} s), "
                f"got {self.flow_window_s}"
            )
        if self.volumetric_speed_rpm is not None and not (
            self.screw_min_rpm <= self.volumetric_speed_rpm <= self.screw_max_rpm
        ):
            raise ValueError(
                f"volumetric_speed_rpm must lie in [{self.screw_min_rpm}, {self.screw_max_rpm}], "
                f"got {self.volumetric_speed_rpm}"
            )
        times = [t for t, _ in self.setpoint_schedule]
        if any(b < a for a, b in zip(times, times[1:])):
            raise ValueError(f"setpoint_schedule times must be increasing, got {times}")
        for t, sp in self.setpoint_schedule:
            if t < 0 or sp <= 0:
                raise ValueError(
                    f"setpoint_schedule entries need t_s >= 0 and setpoint_kg_h > 0, got ({t}, {sp})"
                )
        top_sp = max([self.setpoint_kg_h] + [sp for _, sp in self.setpoint_schedule])
        if self.refill_enabled and self.refill_rate_kg_s * 3600.0 <= top_sp:
            raise ValueError(
                f"refill_rate_kg_s {self.refill_rate_kg_s} ({self.refill_rate_kg_s * 3600:.4g} kg/h) "
                f"must exceed the set point {top_sp} kg/h, or the hopper never refills"
            )
        # the set point must be reachable at the lowest hopper level the feeder runs at
        w_low = self.refill_low_kg if self.refill_enabled else 0.0
        ff_low = self.ff_max_g_rev - (self.ff_max_g_rev - self.ff_min_g_rev) * math.exp(
            -self.beta_per_kg * w_low
        )
        max_flow = self.screw_max_rpm * ff_low * G_PER_MIN_TO_KG_PER_H
        if self.mode == "gravimetric":
            top = max([self.setpoint_kg_h] + [sp for _, sp in self.setpoint_schedule])
            if top > max_flow:
                raise ValueError(
                    f"setpoint_kg_h {top} is unreachable: screw_max_rpm {self.screw_max_rpm} x "
                    f"FF({w_low} kg) = {ff_low:.4g} g/rev gives at most {max_flow:.4g} kg/h"
                )
        if self.mode == "gravimetric":
            rho = loop_spectral_radius(self)
            if rho >= 1.0:
                raise ValueError(
                    f"PID gains kp={self.kp}, ki={self.ki}, kd={self.kd} make the flow loop "
                    f"unstable (spectral radius {rho:.4f} >= 1 with control_period_s="
                    f"{self.control_period_s}, flow_window_s={self.flow_window_s}, "
                    f"flow_filter_tau_s={self.flow_filter_tau_s}, motor_tau_s={self.motor_tau_s}); "
                    "lower the gains or shorten the flow window"
                )
        return self


def loop_spectral_radius(cfg: FeederConfig) -> float:
    """Spectral radius of the linearised gravimetric loop, sampled at the control period.

    Loop: flow F_k (screw speed x FF, with the controller's FF model exact) through the drive
    lag ``F_k = F_{k-1} + a_m (u_k - F_{k-1})``; load-cell least-squares slope over the window,
    which is a weighted sum of past flows ``raw_k = sum_j c_j F_{k-j}``; first-order filter
    ``f_k = f_{k-1} + a_f (raw_k - f_{k-1})``; PID ``u_k = kp e_k + I_k + kd (e_k - e_{k-1})/T``
    with ``e_k = -f_k`` (deviation variables), ``I_k = I_{k-1} + ki T e_k``. Stable iff < 1.
    """
    tc = cfg.control_period_s
    nw = max(2, int(round(cfg.flow_window_s / tc)))
    lag = np.arange(nw) - (nw - 1) / 2.0
    s = lag / float(lag @ lag) / tc  # slope weights on m_{k-nw+1..k}
    # m_i = m_k + T sum_{l=i}^{k-1} F_l  ->  -slope = sum_j c_j F_{k-j}, j = 1..nw-1
    cum = np.cumsum(s)  # sum over window positions 0..p
    c = np.array([-tc * cum[nw - 1 - j] for j in range(1, nw)])
    a_f = 1.0 - math.exp(-tc / cfg.flow_filter_tau_s) if cfg.flow_filter_tau_s > 0 else 1.0
    a_m = 1.0 - math.exp(-tc / cfg.motor_tau_s) if cfg.motor_tau_s > 0 else 1.0
    nb = nw - 1  # flow history F_k .. F_{k-nw+2}
    dim = nb + 3  # + f, I, e

    def step(x: np.ndarray) -> np.ndarray:
        hist, f, integ, e_prev = x[:nb], x[nb], x[nb + 1], x[nb + 2]
        raw = float(c @ hist)
        f_new = f + a_f * (raw - f)
        e = -f_new
        integ_new = integ + cfg.ki * tc * e
        u = cfg.kp * e + integ_new + cfg.kd * (e - e_prev) / tc
        flow = hist[0] + a_m * (u - hist[0])
        out = np.empty(dim)
        out[0] = flow
        out[1:nb] = hist[: nb - 1]
        out[nb], out[nb + 1], out[nb + 2] = f_new, integ_new, e
        return out

    a = np.column_stack([step(col) for col in np.eye(dim)])
    return float(np.max(np.abs(np.linalg.eigvals(a))))
