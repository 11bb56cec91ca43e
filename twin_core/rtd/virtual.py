"""Virtual tracer experiments whose truth is computed independently of ``rtd.models``.

The fits, the lack-of-fit test and the intervals are checked on profiles whose truth does not
come from the functions being fitted:

- :func:`dispersion_pde`: axial dispersion, open-open (infinite domain), by a method-of-lines
  solution of dc/dtheta = -dc/dx + (1/Pe) d2c/dx2 (central differences, ``scipy.integrate``
  BDF), observed at x = 1; with ``r_dead > 0`` a stagnant zone exchanges with the flow,
  dc/dtheta = ... - (r/kappa)(c - m), dm/dtheta = (c - m)/kappa, kappa = tau_x/tau (the
  mobile-immobile model of van Genuchten & Wierenga 1976). theta = (t - tau_d)/tau;
  E(t) = c(1, theta)/tau. The Dirac pulse starts as the exact Gaussian solution of width
  0.01 at theta_s = 5e-5 Pe (pure dispersion; exchange in [0, theta_s] is neglected);
- :func:`tanks_gamma`: tanks in series as ``scipy.stats.gamma`` (shape n, scale tau/n);
- :func:`emg_convolution`: an exponentially tailed peak as the numerical convolution of a
  Gaussian with an exponential decay (FFT convolution on a fine grid);
- :func:`measure`: a measured profile: truth + offset + white + 1/f + proportional noise +
  outliers. The 1/f noise is a window of a record 8 times longer made by spectral shaping
  (``noise.pink_noise``), so it carries power below the record's lowest frequency (drift and
  offset within the window), as real low-frequency noise does.

Concentration of a pulse of ``amount_g`` into the flow Q: c = 100 r m E(t) / Q (% w/w), as the
synthetic campaign (``synthetic.CampaignConfig``: Q = 12 kg/h, apparent recovery r = 0.7).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import sparse, stats
from scipy.integrate import solve_ivp
from scipy.signal import fftconvolve

from twin_core.rtd.noise import pink_noise
from twin_core.rtd.synthetic import CampaignConfig

__all__ = [
    "dispersion_pde",
    "tanks_gamma",
    "emg_convolution",
    "pulse_concentration",
    "NoiseSpec",
    "SEED_NOISE",
    "measure",
]

#: nodes per unit length (the observation point is at x = 1)
PDE_NODES = 400
#: width of the initial Gaussian (in units of the length)
PDE_SIGMA0 = 0.01
#: low-frequency record length of the 1/f noise, in record lengths
PINK_RECORD_FACTOR = 8


def _dispersion_operator(n: int, dx: float, pe: float) -> sparse.csr_matrix:
    """-d/dx + (1/Pe) d2/dx2 by central differences, c = 0 upstream, zero gradient downstream."""
    adv, dif = 1.0 / (2.0 * dx), 1.0 / (pe * dx * dx)
    lower = np.full(n - 1, adv + dif)
    diag = np.full(n, -2.0 * dif)
    upper = np.full(n - 1, -adv + dif)
    lower[-1] = 2.0 * dif  # ghost node c_{n} = c_{n-2} (zero gradient)
    return sparse.diags([lower, diag, upper], [-1, 0, 1], format="csr")


def dispersion_pde(
    t: ArrayLike,
    tau_d: float,
    tau: float,
    pe: float,
    r_dead: float = 0.0,
    tau_x: float = 1.0,
    nodes: int = PDE_NODES,
) -> NDArray[np.float64]:
    """E(t) (1/s) of axial dispersion (open-open) with delay tau_d, optionally with a stagnant
    zone of volume ratio r_dead and exchange time tau_x, by integrating the PDE (module
    docstring) on ``nodes`` nodes per unit length. Zero for t <= tau_d + theta_s tau."""
    tt = np.asarray(t, dtype=float)
    for name, v in (("tau", tau), ("pe", pe), ("tau_x", tau_x)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be finite and > 0, got {v!r}")
    if not (np.isfinite(r_dead) and r_dead >= 0):
        raise ValueError(f"r_dead must be finite and >= 0, got {r_dead!r}")
    theta = (tt - tau_d) / tau
    theta_end = float(theta.max())
    # domain: far enough upstream for back-dispersion, downstream room beyond the probe
    spread = np.sqrt(2.0 * max(theta_end, 1.0) / pe)
    x0 = -min(8.0 * spread, 4.0 + 8.0 / pe)
    x1 = 1.0 + min(8.0 * spread, 3.0 + 8.0 / pe)
    dx = 1.0 / nodes
    up, down = int(np.ceil((1.0 - x0) / dx)), int(np.ceil((x1 - 1.0) / dx))
    x = 1.0 + dx * np.arange(-up, down + 1)  # the probe x = 1 is a node
    n = x.size
    probe = up
    theta_s = 0.5 * pe * PDE_SIGMA0**2
    c0 = np.exp(-0.5 * ((x - theta_s) / PDE_SIGMA0) ** 2) / (PDE_SIGMA0 * np.sqrt(2 * np.pi))
    a = _dispersion_operator(n, dx, pe)
    if r_dead > 0:
        kappa = tau_x / tau
        eye = sparse.identity(n, format="csr")
        a = sparse.bmat(
            [[a - (r_dead / kappa) * eye, (r_dead / kappa) * eye], [eye / kappa, -eye / kappa]],
            format="csr",
        )
        c0 = np.concatenate([c0, np.zeros(n)])
    out = np.zeros_like(tt)
    keep = theta > theta_s
    if not np.any(keep):
        return out
    sol = solve_ivp(
        lambda _, y: a @ y,
        (theta_s, theta_end),
        c0,
        method="BDF",
        t_eval=np.sort(theta[keep]),
        jac=a,
        rtol=1e-7,
        atol=1e-10,
    )
    if not sol.success:
        raise RuntimeError(f"dispersion PDE integration failed: {sol.message}")
    order = np.argsort(theta[keep], kind="stable")
    vals = np.empty(order.size)
    vals[order] = sol.y[probe]
    out[keep] = np.maximum(vals, 0.0) / tau
    return out


def tanks_gamma(t: ArrayLike, tau_d: float, tau: float, n: float) -> NDArray[np.float64]:
    """Tanks in series with delay as ``scipy.stats.gamma`` (shape n, scale tau / n)."""
    tt = np.asarray(t, dtype=float)
    return stats.gamma.pdf(tt - tau_d, a=n, scale=tau / n)


def emg_convolution(
    t: ArrayLike, mu: float, sigma: float, tau_e: float, step: float = 0.01
) -> NDArray[np.float64]:
    """Gaussian (mu, sigma) convolved with exp(-s/tau_e)/tau_e by FFT convolution on a grid
    of spacing ``step`` (s), interpolated to t."""
    tt = np.asarray(t, dtype=float)
    if not (sigma > 0 and tau_e > 0 and step > 0):
        raise ValueError(f"sigma, tau_e and step must be > 0, got {sigma!r}, {tau_e!r}, {step!r}")
    lo = min(float(tt.min()), mu - 10 * sigma)
    grid = np.arange(lo, float(tt.max()) + 10 * sigma + step, step)
    gauss = np.exp(-0.5 * ((grid - mu) / sigma) ** 2) / (sigma * np.sqrt(2 * np.pi))
    s = np.arange(0.0, 40.0 * tau_e, step)
    decay = np.exp(-s / tau_e) / tau_e
    decay[0] *= 0.5  # trapezoid weight of the jump at s = 0
    conv = fftconvolve(gauss, decay)[: grid.size] * step
    return np.interp(tt, grid, conv)


def pulse_concentration(
    e: ArrayLike, amount_g: float, cfg: CampaignConfig | None = None
) -> NDArray[np.float64]:
    """Outlet concentration (% w/w) of a tracer pulse: 100 r m E / Q (module docstring)."""
    c = cfg or CampaignConfig()
    return 100.0 * c.recovery * amount_g / c.flow_g_s * np.asarray(e, dtype=float)


@dataclass(frozen=True)
class NoiseSpec:
    """Measurement noise of a virtual NIR probe (% w/w; proportional as a fraction)."""

    white: float = 0.10
    pink: float = 0.07
    proportional: float = 0.03
    offset_mean: float = -0.05
    offset_std: float = 0.02
    outlier_rate: float = 0.01
    outlier_size: tuple[float, float] = (1.0, 3.0)

    def scaled(self, factor: float) -> NoiseSpec:
        """The same noise with white, pink and proportional parts multiplied by ``factor``."""
        return replace(
            self,
            white=self.white * factor,
            pink=self.pink * factor,
            proportional=self.proportional * factor,
        )


#: the seed's PAT noise (synthetic campaign defaults): baseline sd ~0.12-0.13 % w/w
SEED_NOISE = NoiseSpec()


def measure(
    c_true: ArrayLike, noise: NoiseSpec, rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """(measured profile, outlier indices): truth + offset + white + 1/f + proportional noise +
    outliers (module docstring)."""
    c = np.asarray(c_true, dtype=float)
    n = c.size
    long = pink_noise(PINK_RECORD_FACTOR * n, noise.pink, rng)
    start = int(rng.integers(0, long.size - n + 1))
    y = (
        c
        + rng.normal(noise.offset_mean, noise.offset_std)
        + rng.normal(0.0, noise.white, n)
        + long[start : start + n]
        + noise.proportional * c * rng.normal(size=n)
    )
    count = min(int(rng.poisson(noise.outlier_rate * n)), n)
    idx = np.sort(rng.choice(n, size=count, replace=False)).astype(np.intp)
    y[idx] += rng.choice([-1.0, 1.0], idx.size) * rng.uniform(*noise.outlier_size, idx.size)
    return y, idx
