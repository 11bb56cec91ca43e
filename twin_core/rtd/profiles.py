"""Tracer concentration profiles: loading, validation, E(t), F(t) and moments.

E(t) = C(t) / int C dt (seed Eqs. 3 and 5), F(t) = int_0^t E dt (seed Eq. 4); moments by the
trapezoid rule: mean residence time t_m = int t E dt, mean-centred variance
sigma^2 = int (t - t_m)^2 E dt, skewness s = int (t - t_m)^3 E dt / sigma^3
(Levenspiel 1999 ch. 11; Fogler 2016 ch. 16).
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Callable
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
    "fill_gaps",
    "MISSING_CELLS",
    "UNIT_SUFFIXES",
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


#: cells read as a missing value (what lab exports and spreadsheets write for one)
MISSING_CELLS = frozenset({"", "nan", "na", "n/a", "#n/a", "null", "none", "-", "--"})
#: unit suffixes of field names (README, "wire contract": units in field names, e.g. ``time_s``,
#: ``concentration_pct_w_w``), longest first
UNIT_SUFFIXES: dict[str, str] = {
    "_pct_w_w": "% w/w",
    "_fraction": "fraction",
    "_mg_g": "mg/g",
    "_min": "min",
    "_ms": "ms",
    "_s": "s",
    "_h": "h",
}


@dataclass(frozen=True)
class _Column:
    number: int  # 1-based
    name: str
    unit: str | None
    header: str = ""
    """the header cell as written ('' without a header)"""

    def where(self, line: int | None) -> str:
        """``line L, column C (name)`` (``column C (no header)`` for a headerless file)."""
        label = f"column {self.number} ({self.header or 'no header'})"
        return f"line {line}, {label}" if line is not None else label


#: one row of a file: (line number from 1, cells); blank rows have no non-blank cell
_Row = tuple[int, list[str]]


def _read_rows(path: Path) -> list[_Row]:
    """Numbered rows of a delimited text file: comment lines (#) left out; the delimiter (comma,
    semicolon or tab) sniffed; decimal commas read as points when the delimiter is not a comma.
    Blank rows (no cell holds anything) are kept, for the caller to report."""
    with path.open(newline="", encoding="utf-8-sig") as fh:
        lines = [
            (i, line)
            for i, line in enumerate(fh.read().splitlines(), 1)
            if not line.lstrip().startswith("#")
        ]
    text = [line for _, line in lines if line.strip()]
    if not text:
        raise ValueError(f"path {str(path)!r} holds no rows")
    sample = "\n".join(text[:20])
    counts = {d: sample.count(d) for d in (";", "\t")}
    delim = max(counts, key=counts.get) if max(counts.values()) >= len(text[:20]) else ","
    rows = [(i, next(csv.reader([line], delimiter=delim), [])) for i, line in lines]
    if delim != ",":
        first = next(k for k, (_, r) in enumerate(rows) if any(c.strip() for c in r))
        rows = rows[: first + 1] + [
            (i, [c.replace(",", ".") for c in r]) for i, r in rows[first + 1 :]
        ]
    return rows


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _blank(row: list[str]) -> bool:
    return not any(c.strip() for c in row)


def _header_column(number: int, cell: str, line: int) -> _Column:
    """A header cell: ``name [unit]``, ``name (unit)``, or ``name_unit`` with a unit suffix of
    ``UNIT_SUFFIXES`` (``time_s``), or a name without a unit."""
    m = _HDR.match(cell)
    if not m:
        raise ValueError(
            f"line {line}, column {number}: header cell {cell!r} is not 'name [unit]', "
            "'name (unit)' or 'name_unit' (time_s, concentration_pct_w_w)"
        )
    name = " ".join(m.group(1).split())
    unit = (m.group(2) or m.group(3) or "").strip() or None
    if unit is None:
        for suffix, u in UNIT_SUFFIXES.items():
            if name.lower().endswith(suffix) and len(name) > len(suffix):
                name, unit = name[: -len(suffix)], u
                break
    return _Column(number, name, unit, cell.strip())


def _header(rows: list[_Row]) -> tuple[list[_Column], int | None, list[_Row]]:
    """(columns, header line or None, data rows) from the first non-blank row: its cells name
    the columns, unless they are all numbers (data; the columns are then named by number)."""
    k = next(k for k, (_, r) in enumerate(rows) if not _blank(r))
    line, first = rows[k]
    if all(_is_number(c) for c in first):
        return [_Column(i + 1, str(i + 1), None) for i in range(len(first))], None, rows[k:]
    return [_header_column(i + 1, c, line) for i, c in enumerate(first)], line, rows[k + 1 :]


def _pick(
    cols: list[_Column], want: str | int | None, role: str, line: int | None, exclude: int = 0
) -> _Column:
    """The column named ``want`` (case-insensitive; with or without its unit) or numbered
    ``want`` (from 1); by default the time column is the one named time/t (else the first)
    and the concentration column the one other column, or the one named concentration."""
    names = [c.name for c in cols]
    at = f" (line {line})" if line is not None else ""
    if isinstance(want, int) or (isinstance(want, str) and want.strip().isdigit()):
        k = int(want)
        if not 1 <= k <= len(cols):
            raise ValueError(f"{role} column number must be 1..{len(cols)}, got {want!r}{at}")
        return cols[k - 1]
    if want is not None:
        key = want.strip().lower()
        for c in cols:
            if key in (c.name.lower(), c.header.lower()):
                return c
        raise ValueError(f"{role} column {want!r} is not in the header {names!r}{at}")
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
        f"concentration column is ambiguous among {[c.name for c in rest]!r} (columns "
        f"{', '.join(str(c.number) for c in rest)}{at}); choose one by name or number (--conc-col)"
    )


def _lines(numbers: list[int]) -> str:
    """``14, 20-22, 31``: line numbers as ranges."""
    out, start = [], 0
    for k in range(1, len(numbers) + 1):
        if k == len(numbers) or numbers[k] != numbers[k - 1] + 1:
            a, b = numbers[start], numbers[k - 1]
            out.append(str(a) if a == b else f"{a}-{b}")
            start = k
    return ", ".join(out)


def _cell(row: list[str], col: _Column, line: int) -> float:
    """The number in ``col`` of a row; NaN for a missing value (``MISSING_CELLS``, or a row too
    short to hold the column). ValueError naming line and column for anything else that is
    not a finite number."""
    if col.number > len(row):
        return math.nan
    cell = row[col.number - 1].strip()
    if cell.lower() in MISSING_CELLS:
        return math.nan
    try:
        value = float(cell)
    except ValueError:
        raise ValueError(f"{col.where(line)}: {cell!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{col.where(line)}: {cell!r} is not finite")
    return value


def _data(
    rows: list[_Row], tc: _Column, cc: _Column, strict: bool
) -> tuple[NDArray, list[int], list[str]]:
    """(array of (t, c), line of each row, warnings): blank rows and rows with a missing value
    in the time or concentration column skipped, each line named in a warning (``strict``:
    refused, naming line and column); times must increase from row to row."""
    last = max((i for i, r in rows if not _blank(r)), default=0)
    blank = [i for i, r in rows if _blank(r) and i < last]
    values, lines, missing = [], [], []
    for line, row in rows:
        if _blank(row):
            if strict and line < last:
                raise ValueError(
                    f"{tc.where(line)}: blank row (--strict refuses it; without --strict it is "
                    "skipped with a warning)"
                )
            continue
        t, c = _cell(row, tc, line), _cell(row, cc, line)
        if math.isnan(t) or math.isnan(c):
            col = tc if math.isnan(t) else cc
            cell = row[col.number - 1].strip() if col.number <= len(row) else None
            shown = "no cell" if cell is None else repr(cell)
            if strict:
                raise ValueError(
                    f"{col.where(line)}: missing value ({shown}; --strict refuses it, without "
                    "--strict the row is skipped with a warning)"
                )
            missing.append((line, col, shown))
            continue
        if values and not t > values[-1][0]:
            raise ValueError(
                f"{tc.where(line)}: time {t:g} is not after {values[-1][0]:g} on line "
                f"{lines[-1]} (rows must be in increasing time, without duplicates)"
            )
        values.append((t, c))
        lines.append(line)
    warnings = []
    if blank:
        warnings.append(f"skipped {len(blank)} blank row(s): line(s) {_lines(blank)}")
    if missing:
        shown = "; ".join(
            f"line {line} column {col.number} ({col.header or col.name}): {cell}"
            for line, col, cell in missing
        )
        warnings.append(f"skipped {len(missing)} row(s) with a missing value (NaN): {shown}")
    return np.array(values, dtype=float).reshape(-1, 2), lines, warnings


def load_csv(
    path: str | Path,
    time_unit: str | None = None,
    conc_unit: str | None = None,
    time_col: str | int | None = None,
    conc_col: str | int | None = None,
    strict: bool = False,
) -> Profile:
    """Load a tracer profile from a lab export (CSV, semicolon or tab separated; # comments).

    Columns are chosen by name (case-insensitive, with or without the unit) or number (from
    1); by default the time column is the one named ``time`` (else the first) and the
    concentration column the only other one (else the one named ``concentration...``). Units
    come from the header, ``name [unit]``, ``name (unit)`` (e.g. ``Time (min),API (%w/w)``) or
    a unit suffix as the wire contract writes field names (``time_s``, ``time_min``,
    ``concentration_pct_w_w``, ``..._mg_g``, ``..._fraction``; ``UNIT_SUFFIXES``), or from the
    arguments; a header unit that contradicts an argument is an error, and so is a unit that
    is neither declared nor given. Times are converted to s (s, ms, min, h) and
    concentrations to % w/w (% w/w, %, mg/g x 0.1, fraction x 100; '%' is read as % w/w).

    Blank rows and rows whose time or concentration is missing (empty, NaN, NA, ...:
    ``MISSING_CELLS``) are skipped, each line named in ``meta["warnings"]``; with ``strict``
    they are refused. Every error names the line and column. ``meta`` records the columns,
    the source units, the factors, the warnings and the skipped lines.
    """
    p = Path(path)
    rows = _read_rows(p)
    cols, hline, data_rows = _header(rows)
    tc = _pick(cols, time_col, "time", hline)
    cc = _pick(cols, conc_col, "concentration", hline, exclude=tc.number)
    if cc.number == tc.number:
        raise ValueError(
            f"{tc.where(hline)}: time and concentration columns must differ, got {tc.name!r} twice"
        )
    tu = _unit("time_unit", tc, hline, time_unit, canonical_time_unit)
    cu = _unit("conc_unit", cc, hline, conc_unit, canonical_conc_unit)
    data, lines, warnings = _data(data_rows, tc, cc, strict)
    if len(lines) < MIN_POINTS:
        span = f" (lines {lines[0]}-{lines[-1]})" if lines else ""
        raise ValueError(
            f"path {str(p)!r}: profile must have at least {MIN_POINTS} points, got "
            f"{len(lines)}{span}"
        )
    factor = CONC_UNITS[cu]
    prof = from_arrays(data[:, 0], data[:, 1] * factor, tu, "% w/w", name=p.stem)
    skipped = sorted({i for i, r in data_rows if not _blank(r)} - set(lines))
    prof.meta.update(
        {
            "time_column": tc.name,
            "conc_column": cc.name,
            "source_time_unit": tu,
            "source_conc_unit": cu,
            "conc_factor_to_pct_w_w": factor,
            "warnings": warnings,
            "skipped_lines": skipped,
        }
    )
    return prof


def _unit(
    name: str, col: _Column, line: int | None, given: str | None, canon: Callable[[str], str]
) -> str:
    """The canonical unit of a column: declared in the header or given (they must agree)."""
    where = col.where(line)
    if col.unit is None and given is None:
        raise ValueError(
            f"{where}: {name} is not declared in the header (name [unit], name (unit) or a unit "
            "suffix such as time_s) nor given, got None"
        )
    try:
        d = canon(col.unit) if col.unit is not None else None
        g = canon(given) if given is not None else None
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    if d is not None and g is not None and d != g:
        raise ValueError(f"{where}: {name} given as {given!r} but the header declares {col.unit!r}")
    return d if d is not None else g  # type: ignore[return-value]


#: a step within this share of a whole multiple of the record's step is that multiple
GAP_TOLERANCE = 0.01


def fill_gaps(profile: Profile) -> tuple[Profile, NDArray[np.bool_]]:
    """(profile on its uniform grid, mask of the measured samples). Where a step is a whole
    multiple m >= 2 of the record's step (the median step; rows that ``load_csv`` skipped),
    the m - 1 missing samples are put back with values interpolated linearly between their
    neighbours: for the filters that need a uniform grid and for presentation; the fit leaves
    them out of its likelihood (``pipeline.fit_profile``). A profile without gaps, or whose
    steps are not whole multiples of one step, is returned as it is (all measured)."""
    t = profile.t
    d = np.diff(t)
    step = float(np.median(d))
    m = np.rint(d / step)
    if np.all(m == 1) or np.any(m < 1) or np.any(np.abs(d / step - m) > GAP_TOLERANCE):
        return profile, np.ones(t.size, bool)
    index = np.concatenate([[0], np.cumsum(m)]).astype(int)
    grid = t[0] + step * np.arange(index[-1] + 1)
    grid[index] = t
    measured = np.zeros(grid.size, bool)
    measured[index] = True
    c = np.interp(grid, t, profile.c)
    out = Profile(grid, c, profile.conc_unit, profile.name, dict(profile.meta))
    return out, measured


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
