"""Tracer concentration profiles: loading, validation, E(t), F(t) and moments.

E(t) = C(t) / int C dt (seed Eqs. 3 and 5), F(t) = int_0^t E dt (seed Eq. 4); moments by the
trapezoid rule: mean residence time t_m = int t E dt, mean-centred variance
sigma^2 = int (t - t_m)^2 E dt, skewness s = int (t - t_m)^3 E dt / sigma^3
(Levenspiel 1999 ch. 11; Fogler 2016 ch. 16).
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from twin_core.rtd.convolution import cumulative

__all__ = ["Profile", "Moments", "TIME_UNITS", "from_arrays", "load_csv", "e_curve", "moments"]

#: factor to seconds
TIME_UNITS: dict[str, float] = {"s": 1.0, "ms": 1e-3, "min": 60.0, "h": 3600.0}
MIN_POINTS = 10


@dataclass(frozen=True)
class Moments:
    """Moments of an RTD: mean residence time (s), mean-centred variance (s^2), skewness (-)."""

    mean: float
    variance: float
    skewness: float
    area: float

    @property
    def std(self) -> float:
        return float(np.sqrt(self.variance))


@dataclass
class Profile:
    """A tracer concentration profile on times t (s); concentration in `conc_unit`."""

    t: NDArray[np.float64]
    c: NDArray[np.float64]
    conc_unit: str = "% w/w"
    name: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.t, self.c = _validate(self.t, self.c)

    @property
    def dt(self) -> float:
        return float(np.median(np.diff(self.t)))

    def area(self) -> float:
        return _area(self.t, self.c)

    def e(self) -> NDArray[np.float64]:
        """E(t) = C / int C dt (1/s), seed Eq. 3/5."""
        return e_curve(self.t, self.c)

    def f(self) -> NDArray[np.float64]:
        """F(t) = int_0^t E dt, seed Eq. 4."""
        return cumulative(self.t, self.e())

    def moments(self) -> Moments:
        return moments(self.t, self.c)

    def with_c(self, c: ArrayLike, **meta: object) -> Profile:
        """Copy with a new concentration array (same times and unit)."""
        return Profile(
            self.t.copy(), np.asarray(c, float), self.conc_unit, self.name, {**self.meta, **meta}
        )


def _validate(t: ArrayLike, c: ArrayLike) -> tuple[NDArray, NDArray]:
    tt = np.asarray(t, dtype=float)
    cc = np.asarray(c, dtype=float)
    if tt.ndim != 1:
        raise ValueError(f"t must be 1-D, got shape {tt.shape}")
    if cc.shape != tt.shape:
        raise ValueError(f"c must have the shape of t {tt.shape}, got {cc.shape}")
    if tt.size < MIN_POINTS:
        raise ValueError(f"profile must have at least {MIN_POINTS} points, got {tt.size}")
    for name, arr in (("t", tt), ("c", cc)):
        bad = np.nonzero(~np.isfinite(arr))[0]
        if bad.size:
            raise ValueError(
                f"{name} contains NaN or inf at index {int(bad[0])} ({bad.size} values)"
            )
    d = np.diff(tt)
    if np.any(d == 0):
        i = int(np.nonzero(d == 0)[0][0])
        raise ValueError(f"t has duplicate times: t[{i}] = t[{i + 1}] = {tt[i]!r}")
    if np.any(d < 0):
        i = int(np.nonzero(d < 0)[0][0])
        raise ValueError(
            f"t must be sorted increasing: t[{i}] = {tt[i]!r} > t[{i + 1}] = {tt[i + 1]!r}"
        )
    return tt, cc


def _area(t: NDArray, c: NDArray) -> float:
    return float(np.sum(0.5 * (c[1:] + c[:-1]) * np.diff(t)))


def from_arrays(
    t: ArrayLike, c: ArrayLike, time_unit: str = "s", conc_unit: str = "% w/w", name: str = ""
) -> Profile:
    """Build a validated Profile; times are converted to seconds from `time_unit`."""
    if time_unit not in TIME_UNITS:
        raise ValueError(f"time_unit must be one of {sorted(TIME_UNITS)}, got {time_unit!r}")
    return Profile(
        np.asarray(t, float) * TIME_UNITS[time_unit], np.asarray(c, float), conc_unit, name
    )


_HDR = re.compile(r"^\s*([A-Za-z_][\w ]*?)\s*(?:\[(.*)\]|\((.*)\))?\s*$")


def load_csv(
    path: str | Path,
    time_unit: str | None = None,
    conc_unit: str | None = None,
    time_col: str = "time",
    conc_col: str = "concentration",
) -> Profile:
    """Load a profile from a CSV with a header naming the columns and declaring units.

    Header cells are ``time [s]`` and ``concentration [% w/w]`` (units in brackets or
    parentheses); columns are matched by name (case-insensitive). Units not declared in the
    header must be passed as arguments; a declared unit that contradicts the argument is an
    error. Lines starting with ``#`` are comments.
    """
    p = Path(path)
    with p.open(newline="") as fh:
        rows = [
            r for r in csv.reader(line for line in fh if not line.lstrip().startswith("#")) if r
        ]
    if not rows:
        raise ValueError(f"path {str(p)!r} holds no rows")
    names, units = [], []
    for cell in rows[0]:
        m = _HDR.match(cell)
        if not m:
            raise ValueError(f"header cell {cell!r} is not 'name [unit]'")
        names.append(m.group(1).strip().lower())
        units.append((m.group(2) or m.group(3) or "").strip() or None)
    try:
        it, ic = names.index(time_col), names.index(conc_col)
    except ValueError:
        raise ValueError(
            f"header must have columns {time_col!r} and {conc_col!r}, got {names!r}"
        ) from None
    tu = _unit("time_unit", units[it], time_unit)
    cu = _unit("conc_unit", units[ic], conc_unit)
    try:
        data = np.array([[float(r[it]), float(r[ic])] for r in rows[1:]], dtype=float)
    except (ValueError, IndexError) as exc:
        raise ValueError(f"path {str(p)!r} has a non-numeric or short row: {exc}") from None
    if data.size == 0:
        raise ValueError(f"profile must have at least {MIN_POINTS} points, got 0")
    return from_arrays(data[:, 0], data[:, 1], tu, cu, name=p.stem)


def _unit(name: str, declared: str | None, given: str | None) -> str:
    if declared is None and given is None:
        raise ValueError(f"{name} is not declared in the header nor given, got None")
    if declared is not None and given is not None and declared != given:
        raise ValueError(f"{name} given as {given!r} but the header declares {declared!r}")
    return declared if declared is not None else given  # type: ignore[return-value]


def e_curve(t: ArrayLike, c: ArrayLike) -> NDArray[np.float64]:
    """E(t) = C(t) / int C dt (seed Eq. 3). Raises ValueError if the area is not positive."""
    tt, cc = np.asarray(t, float), np.asarray(c, float)
    a = _area(tt, cc)
    if not a > 0:
        raise ValueError(f"profile area must be > 0, got {a!r}")
    return cc / a


def moments(t: ArrayLike, c: ArrayLike) -> Moments:
    """Mean residence time, mean-centred variance and skewness of a profile (trapezoid rule)."""
    tt, cc = _validate(t, c)
    a = _area(tt, cc)
    if not a > 0:
        raise ValueError(f"profile area must be > 0, got {a!r}")
    e = cc / a
    mean = _area(tt, tt * e)
    var = _area(tt, (tt - mean) ** 2 * e)
    skew = _area(tt, (tt - mean) ** 3 * e) / var**1.5 if var > 0 else float("nan")
    return Moments(mean, var, skew, a)
