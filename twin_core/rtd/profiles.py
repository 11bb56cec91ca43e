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

__all__ = [
    "Profile",
    "Moments",
    "TIME_UNITS",
    "CONC_UNITS",
    "canonical_time_unit",
    "canonical_conc_unit",
    "from_arrays",
    "load_csv",
    "e_curve",
    "moments",
]

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


_HDR = re.compile(r"^\s*([A-Za-z_][^\[\]()]*?)\s*(?:\[(.*)\]|\((.*)\))?\s*$")

#: accepted time units (spellings -> canonical)
TIME_SPELLINGS: dict[str, str] = {
    "s": "s",
    "sec": "s",
    "secs": "s",
    "second": "s",
    "seconds": "s",
    "ms": "ms",
    "min": "min",
    "mins": "min",
    "minute": "min",
    "minutes": "min",
    "h": "h",
    "hr": "h",
    "hrs": "h",
    "hour": "h",
    "hours": "h",
}
#: accepted concentration units (canonical) -> factor to % w/w
CONC_UNITS: dict[str, float] = {"% w/w": 1.0, "%": 1.0, "mg/g": 0.1, "fraction": 100.0}
_CONC_SPELLINGS: dict[str, str] = {
    "%w/w": "% w/w",
    "w/w%": "% w/w",
    "%(w/w)": "% w/w",
    "wt%": "% w/w",
    "%wt": "% w/w",
    "wt.%": "% w/w",
    "%": "%",
    "percent": "%",
    "mg/g": "mg/g",
    "fraction": "fraction",
    "g/g": "fraction",
    "w/w": "fraction",
}


def canonical_time_unit(unit: str) -> str:
    """Canonical time unit (s, ms, min, h) of a spelling; unknown units are refused."""
    key = unit.strip().lower()
    if key not in TIME_SPELLINGS:
        raise ValueError(f"time unit must be one of s, ms, min, h, got {unit!r}")
    return TIME_SPELLINGS[key]


def canonical_conc_unit(unit: str) -> str:
    """Canonical concentration unit (% w/w, %, mg/g, fraction) of a spelling (spaces and case
    ignored: '%w/w', 'wt%', 'w/w %' are % w/w); unknown units are refused."""
    key = re.sub(r"\s+", "", unit.strip().lower())
    if key not in _CONC_SPELLINGS:
        raise ValueError(
            f"concentration unit must be one of {', '.join(CONC_UNITS)} (or %w/w, wt%, g/g), "
            f"got {unit!r}"
        )
    return _CONC_SPELLINGS[key]


@dataclass(frozen=True)
class _Column:
    number: int  # 1-based
    name: str
    unit: str | None


def _read_rows(path: Path) -> list[list[str]]:
    """Rows of a delimited text file: comment lines (#) skipped; the delimiter (comma,
    semicolon or tab) sniffed; decimal commas read as points when the delimiter is not a comma."""
    with path.open(newline="", encoding="utf-8-sig") as fh:
        lines = [line for line in fh if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"path {str(path)!r} holds no rows")
    sample = "".join(lines[:20])
    counts = {d: sample.count(d) for d in (";", "\t")}
    delim = max(counts, key=counts.get) if max(counts.values()) >= len(lines[:20]) else ","
    rows = [r for r in csv.reader(lines, delimiter=delim) if any(c.strip() for c in r)]
    if delim != ",":
        rows = [rows[0]] + [[c.replace(",", ".") for c in r] for r in rows[1:]]
    return rows


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _header(rows: list[list[str]]) -> tuple[list[_Column], list[list[str]]]:
    """Columns (number, name, unit) from the header row; a first row of numbers is data (the
    columns are then named by their numbers)."""
    first = rows[0]
    if all(_is_number(c) for c in first):
        return [_Column(i + 1, str(i + 1), None) for i in range(len(first))], rows
    cols = []
    for i, cell in enumerate(first):
        m = _HDR.match(cell)
        if not m:
            raise ValueError(f"header cell {cell!r} is not 'name [unit]' or 'name (unit)'")
        unit = (m.group(2) or m.group(3) or "").strip() or None
        cols.append(_Column(i + 1, " ".join(m.group(1).split()), unit))
    return cols, rows[1:]


def _pick(cols: list[_Column], want: str | int | None, role: str, exclude: int = 0) -> _Column:
    """The column named ``want`` (case-insensitive) or numbered ``want`` (from 1); by default
    the time column is the one named time/t (else the first) and the concentration column the
    one other column, or the one named concentration."""
    names = [c.name for c in cols]
    if isinstance(want, int) or (isinstance(want, str) and want.strip().isdigit()):
        k = int(want)
        if not 1 <= k <= len(cols):
            raise ValueError(f"{role} column number must be 1..{len(cols)}, got {want!r}")
        return cols[k - 1]
    if want is not None:
        for c in cols:
            if c.name.lower() == want.strip().lower():
                return c
        raise ValueError(f"{role} column {want!r} is not in the header {names!r}")
    if role == "time":
        for c in cols:
            if c.name.lower() in ("time", "t") or c.name.lower().startswith("time"):
                return c
        return cols[0]
    rest = [c for c in cols if c.number != exclude]
    if len(rest) == 1:
        return rest[0]
    for c in rest:
        if c.name.lower().startswith("conc"):
            return c
    raise ValueError(
        f"concentration column is ambiguous among {[c.name for c in rest]!r}; "
        "choose one by name or number (--conc-col)"
    )


def load_csv(
    path: str | Path,
    time_unit: str | None = None,
    conc_unit: str | None = None,
    time_col: str | int | None = None,
    conc_col: str | int | None = None,
) -> Profile:
    """Load a tracer profile from a lab export (CSV, semicolon or tab separated; # comments).

    Columns are chosen by name (case-insensitive, without the unit) or number (from 1); by
    default the time column is the one named ``time`` (else the first) and the concentration
    column the only other one (else the one named ``concentration...``). Units come from the
    header, ``name [unit]`` or ``name (unit)`` (e.g. ``Time (min),API (%w/w)``), or from the
    arguments; a header unit that contradicts an argument is an error, and so is a unit that
    is neither declared nor given. Times are converted to s (s, ms, min, h) and
    concentrations to % w/w (% w/w, %, mg/g x 0.1, fraction x 100; '%' is read as % w/w);
    ``meta`` records the columns, the source units and the factors.
    """
    p = Path(path)
    rows = _read_rows(p)
    cols, data_rows = _header(rows)
    tc = _pick(cols, time_col, "time")
    cc = _pick(cols, conc_col, "concentration", exclude=tc.number)
    if cc.number == tc.number:
        raise ValueError(f"time and concentration columns must differ, got {tc.name!r} twice")
    tu = _unit("time_unit", tc.unit, time_unit, canonical_time_unit)
    cu = _unit("conc_unit", cc.unit, conc_unit, canonical_conc_unit)
    try:
        data = np.array(
            [[float(r[tc.number - 1]), float(r[cc.number - 1])] for r in data_rows], dtype=float
        )
    except (ValueError, IndexError) as exc:
        raise ValueError(f"path {str(p)!r} has a non-numeric or short row: {exc}") from None
    if data.size == 0:
        raise ValueError(f"profile must have at least {MIN_POINTS} points, got 0")
    factor = CONC_UNITS[cu]
    prof = from_arrays(data[:, 0], data[:, 1] * factor, tu, "% w/w", name=p.stem)
    prof.meta.update(
        {
            "time_column": tc.name,
            "conc_column": cc.name,
            "source_time_unit": tu,
            "source_conc_unit": cu,
            "conc_factor_to_pct_w_w": factor,
        }
    )
    return prof


def _unit(name: str, declared: str | None, given: str | None, canon) -> str:
    if declared is None and given is None:
        raise ValueError(f"{name} is not declared in the header nor given, got None")
    d = canon(declared) if declared is not None else None
    g = canon(given) if given is not None else None
    if d is not None and g is not None and d != g:
        raise ValueError(f"{name} given as {given!r} but the header declares {declared!r}")
    return d if d is not None else g  # type: ignore[return-value]


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
