"""Loss-in-weight (LIW) twin-screw feeder: PID on screw speed, refills in volumetric mode.

Model (seed ch. 3.1; Engisch & Muzzio 2016 for the LIW control scheme):

* outflow ``F(t) = w(t) FF(W(t)) (1 + eps(t))`` (seed Eq. 1), ``w`` the screw speed (rpm),
  ``FF(W)`` the feed factor of seed Eq. (2) in g/rev, ``eps`` an Ornstein-Uhlenbeck process
  noise (std ``flow_noise_rel``, correlation time ``flow_noise_tau_s``);
* hopper mass balance ``dW/dt = -F + R(t)`` with R the refill rate while refilling;
* screw drive: first-order lag ``tau_m dw/dt = w_cmd - w``;
* load cell ``m_k = W(t_k) + N(0, sigma_lc^2)`` sampled every control period; the flow
  estimate is minus the least-squares slope of ``m`` over the last ``flow_window_s``, passed
  through a first-order filter;
* gravimetric mode: positional PID on the flow error ``e = F_sp - F_est`` (kg/h) giving a
  flow demand ``u = kp e + I + kd de/dt`` (kg/h), turned into a screw speed through the
  controller's feed-factor model at the measured weight, ``w_cmd = u / FF(m)`` (gain
  scheduling, so the loop gain is ~1 whatever the powder); the integrator holds the bias
  (bumpless start and restart from the held speed); clamping anti-windup at the speed limits;
* refill: when the load cell reads ``<= refill_low_kg`` the controller switches to
  volumetric mode, holding the mean commanded speed of the last window, and powder is added
  at ``refill_rate_kg_s`` until the load cell reads ``>= refill_high_kg``; after
  ``refill_settle_s`` the weight history is restarted and gravimetric control resumes once a
  full window is available. During the refill FF(W) rises with W at constant speed: this is
  the refill flow surge, of relative size ``FF(W_high)/FF(W_low) - 1``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from schemas.feeder import G_PER_MIN_TO_KG_PER_H, FeederConfig

__all__ = ["FeederTrace", "LossInWeightFeeder"]


@dataclass
class FeederTrace:
    """Time series of one LIW feeder simulation (uniform grid ``t_s``)."""

    t_s: np.ndarray
    mass_flow_kg_h: np.ndarray
    screw_speed_rpm: np.ndarray
    hopper_mass_kg: np.ndarray
    refilling: np.ndarray
    feed_factor_g_rev: np.ndarray
    refills: list[tuple[float, float]] = field(default_factory=list)
    #: True while the controller runs open loop (refill, settling, start-up, volumetric mode)
    volumetric: np.ndarray | None = None
    setpoint_kg_h: np.ndarray | None = None
    load_cell_kg: np.ndarray | None = None
    flow_estimate_kg_h: np.ndarray | None = None

    def to_frame(self) -> Any:
        """The arrays as a pandas DataFrame indexed by nothing (one row per time step)."""
        import pandas as pd

        cols = {
            "t_s": self.t_s,
            "mass_flow_kg_h": self.mass_flow_kg_h,
            "screw_speed_rpm": self.screw_speed_rpm,
            "hopper_mass_kg": self.hopper_mass_kg,
            "refilling": self.refilling,
            "feed_factor_g_rev": self.feed_factor_g_rev,
        }
        for name in ("volumetric", "setpoint_kg_h", "load_cell_kg", "flow_estimate_kg_h"):
            val = getattr(self, name)
            if val is not None:
                cols[name] = val
        return pd.DataFrame(cols)

    def dispensed_kg(self, t0: float | None = None, t1: float | None = None) -> float:
        """Mass delivered between t0 and t1 (trapezoidal integral of the outflow)."""
        sel = np.ones_like(self.t_s, dtype=bool)
        if t0 is not None:
            sel &= self.t_s >= t0
        if t1 is not None:
            sel &= self.t_s <= t1
        return float(np.trapezoid(self.mass_flow_kg_h[sel], self.t_s[sel]) / 3600.0)


class LossInWeightFeeder:
    """Loss-in-weight feeder simulator.

    ``LossInWeightFeeder(config)`` or ``LossInWeightFeeder(setpoint_kg_h=8.0, ...)``: keyword
    arguments override fields of ``config`` (default :class:`schemas.feeder.FeederConfig`) and
    are validated by it (a bad value raises ``ValueError`` naming the field).
    """

    def __init__(self, config: FeederConfig | None = None, **overrides: Any) -> None:
        if config is None:
            config = FeederConfig(**overrides)
        elif overrides:
            config = FeederConfig(**{**config.model_dump(), **overrides})
        self.config = config

    def feed_factor(self, w_kg: float | np.ndarray) -> float | np.ndarray:
        """FF(W) in g/rev from the configured Eq. (2) parameters."""
        from .feed_factor import feed_factor

        c = self.config
        return feed_factor(w_kg, c.ff_max_g_rev, c.ff_min_g_rev, c.beta_per_kg)

    def _setpoint(self, t: float) -> float:
        sp = self.config.setpoint_kg_h
        for ts, value in self.config.setpoint_schedule:
            if t >= ts:
                sp = value
        return sp

    def simulate(
        self,
        duration_s: float,
        dt_s: float = 0.1,
        seed: int | np.random.Generator | None = None,
    ) -> FeederTrace:
        """Simulate ``duration_s`` seconds on a grid of step ``dt_s``; see the module docstring.

        The controller runs every ``control_period_s`` (rounded to a whole number of steps,
        so ``dt_s`` must not exceed it). ``seed`` seeds the process and load-cell noise.
        """
        c = self.config
        if not (duration_s > 0 and math.isfinite(duration_s)):
            raise ValueError(f"duration_s must be > 0, got {duration_s}")
        if not (dt_s > 0 and math.isfinite(dt_s)):
            raise ValueError(f"dt_s must be > 0, got {dt_s}")
        if dt_s > c.control_period_s * (1 + 1e-9):
            raise ValueError(f"dt_s must be <= control_period_s ({c.control_period_s}), got {dt_s}")
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        n = int(round(duration_s / dt_s)) + 1
        t = np.arange(n) * dt_s
        n_ctrl = max(1, int(round(c.control_period_s / dt_s)))
        tc = n_ctrl * dt_s
        nw = max(2, int(round(c.flow_window_s / tc)))
        lag = (np.arange(nw) - (nw - 1) / 2.0) * tc
        slope_w = lag / float(lag @ lag)  # least-squares slope weights, oldest first
        a_filt = 1.0 - math.exp(-tc / c.flow_filter_tau_s) if c.flow_filter_tau_s > 0 else 1.0
        a_motor = 1.0 - math.exp(-dt_s / c.motor_tau_s) if c.motor_tau_s > 0 else 1.0
        a_ou = math.exp(-dt_s / c.flow_noise_tau_s)
        ou_kick = c.flow_noise_rel * math.sqrt(1.0 - a_ou * a_ou)
        ou_noise = rng.standard_normal(n) * ou_kick
        lc_noise = rng.standard_normal(n) * c.load_cell_noise_kg
        ff_max, ff_min, beta = c.ff_max_g_rev, c.ff_min_g_rev, c.beta_per_kg
        k_flow = G_PER_MIN_TO_KG_PER_H  # rpm * g/rev -> kg/h
        lo_rpm, hi_rpm = c.screw_min_rpm, c.screw_max_rpm

        def ff_of(w: float) -> float:
            return ff_max - (ff_max - ff_min) * math.exp(-beta * w)

        def clamp(x: float) -> float:
            return min(max(x, lo_rpm), hi_rpm)

        out_flow = np.empty(n)
        out_speed = np.empty(n)
        out_mass = np.empty(n)
        out_ff = np.empty(n)
        out_refill = np.zeros(n, dtype=bool)
        out_vol = np.zeros(n, dtype=bool)
        out_sp = np.empty(n)
        out_lc = np.full(n, np.nan)
        out_fest = np.full(n, np.nan)

        w_mass = float(c.initial_mass_kg)
        sp = self._setpoint(0.0)
        if c.mode == "volumetric" and c.volumetric_speed_rpm is not None:
            speed0 = c.volumetric_speed_rpm
        else:
            speed0 = clamp(sp / (max(ff_of(w_mass), 1e-12) * k_flow))
        speed = speed0
        speed_cmd = speed0
        integ = speed0
        eps = rng.standard_normal() * c.flow_noise_rel
        buf = np.zeros(2 * nw)  # each sample written twice: buf[i:i+nw] is the window
        cmd_buf = np.full(nw, speed0)
        n_valid = 0
        head = 0
        f_est = float("nan")
        prev_err: float | None = None
        refilling = False
        settle_until = -1.0
        hold_speed = speed0
        refills: list[tuple[float, float]] = []
        refill_start = 0.0
        gravimetric = False  # closed loop active (needs a full weight window first)

        for k in range(n):
            tk = t[k]
            if k % n_ctrl == 0:
                m = w_mass + lc_noise[k]
                out_lc[k] = m
                sp = self._setpoint(tk)
                # refill state machine (acts on the load-cell reading)
                if refilling and m >= c.refill_high_kg:
                    refilling = False
                    refills.append((refill_start, float(tk)))
                    settle_until = tk + c.refill_settle_s
                if c.refill_enabled and not refilling and settle_until < 0 and m <= c.refill_low_kg:
                    refilling = True
                    refill_start = float(tk)
                    hold_speed = float(np.mean(cmd_buf)) if gravimetric else speed_cmd
                    gravimetric = False
                    n_valid = 0
                if settle_until >= 0 and not refilling and tk >= settle_until - 1e-12:
                    settle_until = -1.0
                    n_valid = 0
                in_hold = refilling or settle_until >= 0
                if not in_hold:
                    buf[head] = m
                    buf[head + nw] = m
                    head = (head + 1) % nw
                    n_valid += 1
                if c.mode == "gravimetric" and not in_hold and n_valid >= nw:
                    raw = -float(slope_w @ buf[head : head + nw]) * 3600.0
                    # the controller's own feed-factor model at the measured weight (kg/h per rpm)
                    ffm = max(ff_of(max(m, 0.0)), 1e-12) * k_flow
                    if not gravimetric:  # (re)start: bumpless from the held speed
                        gravimetric = True
                        f_est = raw
                        integ = speed_cmd * ffm
                        prev_err = None
                    else:
                        f_est += a_filt * (raw - f_est)
                    err = sp - f_est
                    deriv = 0.0 if prev_err is None else (err - prev_err) / tc
                    prev_err = err
                    trial = (c.kp * err + integ + c.ki * err * tc + c.kd * deriv) / ffm
                    if (
                        lo_rpm < trial < hi_rpm
                        or (trial >= hi_rpm and err < 0)
                        or (trial <= lo_rpm and err > 0)
                    ):
                        integ += c.ki * err * tc
                    speed_cmd = clamp((c.kp * err + integ + c.kd * deriv) / ffm)
                elif c.mode == "gravimetric" and in_hold:
                    speed_cmd = hold_speed
                cmd_buf[(k // n_ctrl) % nw] = speed_cmd
                out_fest[k] = f_est if gravimetric else np.nan
            # screw drive, process noise, outflow
            speed += a_motor * (speed_cmd - speed)
            eps = a_ou * eps + ou_noise[k]
            ff = max(ff_of(w_mass) * (1.0 + eps), 0.0) if w_mass > 0 else 0.0
            flow = speed * ff * k_flow  # kg/h
            out_flow[k] = flow
            out_speed[k] = speed
            out_mass[k] = w_mass
            out_ff[k] = ff
            out_refill[k] = refilling
            out_vol[k] = not gravimetric
            out_sp[k] = sp
            # mass balance to t[k+1]
            w_mass -= min(flow * dt_s / 3600.0, w_mass)
            if refilling:
                w_mass += c.refill_rate_kg_s * dt_s

        if refilling:  # still refilling at the end: close the interval at the last time
            refills.append((refill_start, float(t[-1])))
        return FeederTrace(
            t_s=t,
            mass_flow_kg_h=out_flow,
            screw_speed_rpm=out_speed,
            hopper_mass_kg=out_mass,
            refilling=out_refill,
            feed_factor_g_rev=out_ff,
            refills=refills,
            volumetric=out_vol,
            setpoint_kg_h=out_sp,
            load_cell_kg=out_lc,
            flow_estimate_kg_h=out_fest,
        )
