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

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["FeederConfig"]

#: g/rev * rev/min -> kg/h
G_PER_MIN_TO_KG_PER_H = 60.0 / 1000.0


class FeederConfig(BaseModel):
    """Loss-in-weight feeder: feed factor, hopper and refill, PID controller, noise.

    Controller units: the PID acts on the flow error in kg/h and outputs screw speed in rpm,
    so ``kp`` is rpm/(kg/h), ``ki`` rpm/(kg/h s) and ``kd`` rpm s/(kg/h).
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
    screw_min_rpm: float = Field(1.0, ge=0)
    screw_max_rpm: float = Field(150.0, gt=0)
    motor_tau_s: float = Field(0.5, ge=0, description="first-order lag of the screw drive")

    # controller and flow estimation from the load cell
    kp: float = Field(1.0, ge=0, description="proportional gain, rpm/(kg/h)")
    ki: float = Field(0.3, ge=0, description="integral gain, rpm/(kg/h s)")
    kd: float = Field(0.0, ge=0, description="derivative gain, rpm s/(kg/h)")
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
        return self
