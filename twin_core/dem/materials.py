"""Materials, pair interaction tables and time-step rules of the DEM engine.

The contact law (see :mod:`twin_core.dem.contact`) needs, for every pair of materials
(particle-particle or particle-wall), the effective moduli and the friction, rolling-friction
and damping coefficients. They are collected here in dense ``(n_mat, n_mat)`` tables.

References
----------
- Hertz (1882); Mindlin & Deresiewicz (1953): effective moduli
  ``1/E* = (1-nu1^2)/E1 + (1-nu2^2)/E2`` and ``1/G* = 2(2-nu1)(1+nu1)/E1 + 2(2-nu2)(1+nu2)/E2``.
- Tsuji, Tanaka & Ishida (1992), in the form used by LIGGGHTS/EDEM:
  damping ``-2 sqrt(5/6) beta sqrt(S m*) v`` with ``beta = ln e / sqrt(ln^2 e + pi^2)``.
- Antypov & Elliott (2011), EPL 94, 50004: for Hertz contacts with this damping the restitution
  coefficient is velocity independent but differs from ``e``; the exact mapping is obtained here
  by integrating the dimensionless contact ODE (see :func:`damping_coefficient`).
- Rayleigh time step, seed Eq. (9) (corrected, docs/seed.md):
  ``T_R = pi R sqrt(rho/G) / (0.1631 nu + 0.8766)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

__all__ = [
    "Material",
    "MaterialTable",
    "rayleigh_time",
    "hertz_contact_time",
    "tsuji_beta",
    "damping_coefficient",
    "restitution_from_damping",
    "effective_young",
    "effective_shear",
]

_SQRT56 = math.sqrt(5.0 / 6.0)


@dataclass(frozen=True)
class Material:
    """An elastic material with its self-interaction coefficients.

    Parameters
    ----------
    density : float
        kg/m^3 (> 0).
    shear_modulus : float
        G in Pa (> 0); Young's modulus is ``E = 2 G (1 + nu)`` (isotropic relation, seed Eq. 6).
    poisson : float
        Poisson ratio nu in [0, 0.5).
    friction, rolling_friction, restitution : float
        Coefficients used for contacts between two bodies of this material (seed Table 3.1
        ``PP_SF``, ``PP_RF``, ``PP_COR``); pairs of different materials default to the mean of the
        two materials' values unless set with :meth:`MaterialTable.set_pair`.
    name : str
        Label only.
    """

    density: float
    shear_modulus: float
    poisson: float
    friction: float = 0.5
    rolling_friction: float = 0.0
    restitution: float = 0.5
    name: str = ""

    def __post_init__(self) -> None:
        if not self.density > 0:
            raise ValueError(f"density must be > 0, got {self.density}")
        if not self.shear_modulus > 0:
            raise ValueError(f"shear_modulus must be > 0, got {self.shear_modulus}")
        if not 0.0 <= self.poisson < 0.5:
            raise ValueError(f"poisson must be in [0, 0.5), got {self.poisson}")
        _check_coeffs(self.friction, self.rolling_friction, self.restitution)

    @property
    def young_modulus(self) -> float:
        """Young's modulus ``E = 2 G (1 + nu)`` (Pa)."""
        return 2.0 * self.shear_modulus * (1.0 + self.poisson)


def _check_coeffs(friction: float, rolling_friction: float, restitution: float) -> None:
    if not friction >= 0:
        raise ValueError(f"friction must be >= 0, got {friction}")
    if not rolling_friction >= 0:
        raise ValueError(f"rolling_friction must be >= 0, got {rolling_friction}")
    if not 0 < restitution <= 1:
        raise ValueError(f"restitution must be in (0, 1], got {restitution}")


def effective_young(m1: Material, m2: Material) -> float:
    """Effective modulus ``1/E* = (1-nu1^2)/E1 + (1-nu2^2)/E2`` (Hertz 1882)."""
    return 1.0 / (
        (1.0 - m1.poisson**2) / m1.young_modulus + (1.0 - m2.poisson**2) / m2.young_modulus
    )


def effective_shear(m1: Material, m2: Material) -> float:
    """Effective shear modulus ``1/G* = 2(2-nu1)(1+nu1)/E1 + 2(2-nu2)(1+nu2)/E2`` (Mindlin)."""
    return 1.0 / (
        2.0 * (2.0 - m1.poisson) * (1.0 + m1.poisson) / m1.young_modulus
        + 2.0 * (2.0 - m2.poisson) * (1.0 + m2.poisson) / m2.young_modulus
    )


def rayleigh_time(radius: float, density: float, shear_modulus: float, poisson: float) -> float:
    """Rayleigh time ``T_R = pi R sqrt(rho/G) / (0.1631 nu + 0.8766)`` (seed Eq. 9, corrected).

    For R = 1 mm, rho = 1500 kg/m^3, G = 2e6 Pa, nu = 0.25 this is 9.378e-5 s (20 % = 1.8757e-5 s,
    the LIGGGHTS benchmark time step).
    """
    if not radius > 0:
        raise ValueError(f"radius must be > 0, got {radius}")
    return math.pi * radius * math.sqrt(density / shear_modulus) / (0.1631 * poisson + 0.8766)


def hertz_contact_time(m_star: float, r_star: float, e_star: float, v: float) -> float:
    """Duration of an elastic Hertz impact ``t_c = 2.868 (m*^2 / (R* E*^2 v))^(1/5)``.

    Reference: Johnson, Contact Mechanics (1985), Sec. 11.1 (2.868 = 2 * 1.434...).
    """
    if not v > 0:
        raise ValueError(f"v must be > 0, got {v}")
    return 2.868 * (m_star**2 / (r_star * e_star**2 * v)) ** 0.2


def tsuji_beta(restitution: float) -> float:
    """``beta = ln e / sqrt(ln^2 e + pi^2)`` (<= 0); the linear-oscillator mapping."""
    if not 0 < restitution <= 1:
        raise ValueError(f"restitution must be in (0, 1], got {restitution}")
    le = math.log(restitution)
    return le / math.sqrt(le * le + math.pi**2)


def restitution_from_damping(d: float) -> float:
    """Restitution of a Hertz contact with damping ``F_d = d sqrt(S_n m*) v_n``.

    Integrates the dimensionless contact ODE (m* = 1, S_n = 2 E* sqrt(R* delta) with 2 E* sqrt(R*)
    = 1, unit approach speed)::

        delta'' = -(2/3) delta^(3/2) - d delta^(1/4) delta'

    until the total normal force vanishes (no attraction: the force is clamped at zero, so the
    bodies separate there). By the power-law scaling of the Hertz law the result does not depend on
    the impact speed (Antypov & Elliott 2011).
    """
    if d <= 0:
        return 1.0

    def rhs(_t: float, y: np.ndarray) -> list[float]:
        x = max(y[0], 0.0)
        return [y[1], -(2.0 / 3.0) * x**1.5 - d * x**0.25 * y[1]]

    def force_zero(_t: float, y: np.ndarray) -> float:
        x = max(y[0], 0.0)
        if y[1] > 0:  # still approaching
            return 1.0
        return (2.0 / 3.0) * x**1.5 + d * x**0.25 * y[1]

    force_zero.terminal = True  # type: ignore[attr-defined]
    force_zero.direction = -1  # type: ignore[attr-defined]
    sol = solve_ivp(
        rhs,
        (0.0, 50.0),
        [1e-12, 1.0],
        events=force_zero,
        rtol=1e-10,
        atol=1e-13,
        max_step=0.01,
    )
    if sol.t_events[0].size == 0:
        return 0.0
    return float(-sol.y_events[0][0][1])


@lru_cache(maxsize=256)
def damping_coefficient(restitution: float, corrected: bool = True) -> float:
    """Damping factor ``d = 2 sqrt(5/6) |beta|`` of the normal and tangential dashpots.

    The force is ``F_d = d sqrt(S m*) v`` with S the normal (S_n = 2 E* sqrt(R* delta)) or
    tangential (S_t = 8 G* sqrt(R* delta)) stiffness (Tsuji et al. 1992; LIGGGHTS/EDEM form).
    With ``corrected=False``, ``beta = ln e / sqrt(ln^2 e + pi^2)`` (the linear-spring mapping):
    for the Hertz law this gives a measured restitution above the target (e.g. 0.1 -> 0.17).
    With ``corrected=True`` (default), ``d`` is solved from :func:`restitution_from_damping` so
    that the measured normal restitution equals ``restitution`` (Antypov & Elliott 2011 mapping).
    """
    if not 0 < restitution <= 1:
        raise ValueError(f"restitution must be in (0, 1], got {restitution}")
    if restitution == 1.0:
        return 0.0
    d_std = 2.0 * _SQRT56 * abs(tsuji_beta(restitution))
    if not corrected:
        return d_std
    lo, hi = 0.0, max(4.0 * d_std, 0.5)
    while restitution_from_damping(hi) > restitution:
        hi *= 2.0
        if hi > 1e4:
            raise ValueError(f"restitution too small to reach, got {restitution}")
    return float(brentq(lambda d: restitution_from_damping(d) - restitution, lo, hi, xtol=1e-10))


@dataclass
class MaterialTable:
    """Materials plus per-pair coefficients (particle-particle and particle-wall alike).

    Walls (planes, cylinders, meshes) carry a material id too, so the seed's particle-wall
    parameters (``PW_SF``, ``PW_RF``, ``PW_COR``) are the pair entries between the particle
    material and the wall material.

    Parameters
    ----------
    materials : list of Material
    damping : {"corrected", "tsuji"}
        How restitution maps to the dashpot (see :func:`damping_coefficient`).
    """

    materials: list[Material]
    damping: str = "corrected"
    _pairs: dict[tuple[int, int], tuple[float, float, float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if isinstance(self.materials, Material):
            self.materials = [self.materials]
        self.materials = list(self.materials)
        if len(self.materials) == 0:
            raise ValueError("materials must not be empty, got []")
        if self.damping not in ("corrected", "tsuji"):
            raise ValueError(f"damping must be 'corrected' or 'tsuji', got {self.damping!r}")

    @property
    def n(self) -> int:
        """Number of materials."""
        return len(self.materials)

    def add(self, material: Material) -> int:
        """Append a material; return its id."""
        self.materials.append(material)
        return len(self.materials) - 1

    def set_pair(
        self, a: int, b: int, friction: float, rolling_friction: float, restitution: float
    ) -> MaterialTable:
        """Set the coefficients of the (a, b) pair (symmetric)."""
        for name, v in (("a", a), ("b", b)):
            if not 0 <= v < self.n:
                raise ValueError(f"material id {name} must be in [0, {self.n}), got {v}")
        _check_coeffs(friction, rolling_friction, restitution)
        self._pairs[(min(a, b), max(a, b))] = (
            float(friction),
            float(rolling_friction),
            float(restitution),
        )
        return self

    def pair(self, a: int, b: int) -> tuple[float, float, float]:
        """(friction, rolling_friction, restitution) of the pair (a, b)."""
        key = (min(a, b), max(a, b))
        if key in self._pairs:
            return self._pairs[key]
        ma, mb = self.materials[a], self.materials[b]
        return (
            0.5 * (ma.friction + mb.friction),
            0.5 * (ma.rolling_friction + mb.rolling_friction),
            0.5 * (ma.restitution + mb.restitution),
        )

    def tables(self) -> np.ndarray:
        """Dense pair tables, shape (6, n, n): E*, G*, mu_s, mu_r, damping factor d, and
        ``sqrt(4 G*/E*)``, the ratio of the tangential to the normal dashpot of a Hertz-Mindlin
        contact (``sqrt(S_t m*) / sqrt(S_n m*)`` with S_t = 8 G* a, S_n = 2 E* a: one square
        root per contact saved)."""
        n = self.n
        out = np.zeros((6, n, n))
        corrected = self.damping == "corrected"
        for a in range(n):
            for b in range(n):
                ma, mb = self.materials[a], self.materials[b]
                mu, mur, e = self.pair(a, b)
                out[0, a, b] = effective_young(ma, mb)
                out[1, a, b] = effective_shear(ma, mb)
                out[2, a, b] = mu
                out[3, a, b] = mur
                out[4, a, b] = damping_coefficient(round(e, 12), corrected)
                out[5, a, b] = math.sqrt(4.0 * out[1, a, b] / out[0, a, b])
        return out

    def to_dict(self) -> dict:
        """JSON-able description (used by checkpoints)."""
        return {
            "materials": [m.__dict__.copy() for m in self.materials],
            "damping": self.damping,
            "pairs": [[a, b, *v] for (a, b), v in sorted(self._pairs.items())],
        }

    @classmethod
    def from_dict(cls, d: dict) -> MaterialTable:
        """Inverse of :meth:`to_dict`."""
        t = cls([Material(**m) for m in d["materials"]], damping=d["damping"])
        for a, b, mu, mur, e in d["pairs"]:
            t.set_pair(int(a), int(b), mu, mur, e)
        return t
