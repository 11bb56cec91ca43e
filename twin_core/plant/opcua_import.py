"""``twin import``: a historian or PAT-software export turned into the twin's messages with the
bridge's own mapping (``schemas.opcua.BridgeConfig``; a node's ``tag``, else its node id,
names its column or file).

Formats (CSV):

- *wide*: one file, a time column and one column per tag;
- *one file per tag*: a folder of ``<tag>.csv`` files, each with a time column and a value
  column.

A column header may declare its unit as ``<tag> [<unit>]`` (a value column ``value [<unit>]``
in a per-tag file). Times are ISO 8601 wall-clock stamps with their time zone (``...+01:00``,
``...Z``); stamps without one are refused unless a time zone is given (``timezone``, e.g.
``Europe/Berlin``). Plant time is the stamp minus the mapping's ``epoch_utc``.

Nothing is guessed; everything is reported (:class:`ImportReport`): a unit declared in the
export that differs from the mapping's, or is not a known unit, refuses the import
(ValueError naming tag and units); a repeated stamp of a tag is a duplicate: with the same
value one is kept, with different values the stamp is dropped (both counted); a gap (stamps of
a tag more than 1.5 of its unit's sample periods apart) is reported with its stretch and left
as it is (the messages' sequence numbers skip the missed samples, as the bridge's do); an
empty cell or bad value is counted by reason (``twin_core.plant.opcua_map.convert``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from schemas.base import Message
from schemas.opcua import UNITS, BridgeConfig, NodeMap
from twin_core.plant.opcua_map import GAP_PERIODS, MessageAssembler

__all__ = ["ImportReport", "import_export", "read_tag_series"]

_UNIT_HEADER = re.compile(r"^(?P<name>.*?)\s*\[(?P<unit>[^\]]+)\]\s*$")


@dataclass
class ImportReport:
    """What the import found: per tag rows, duplicates and gaps; the assembler's counters."""

    rows: dict[str, int] = field(default_factory=dict)
    duplicates: dict[str, int] = field(default_factory=dict)
    conflicting: dict[str, int] = field(default_factory=dict)
    gaps: list[dict[str, Any]] = field(default_factory=list)
    counters: dict[str, int] = field(default_factory=dict)
    messages: int = 0

    def lines(self) -> list[str]:
        """The report as text lines."""
        out = [
            f"{self.messages} messages from {sum(self.rows.values())} samples of "
            f"{len(self.rows)} tags"
        ]
        for tag, n in self.duplicates.items():
            if n:
                out.append(
                    f"duplicates: {tag}: {n} repeated stamps "
                    f"({self.conflicting.get(tag, 0)} with different values, dropped)"
                )
        for g in self.gaps:
            out.append(
                f"gap: {g['tag']}: {g['n_missed']} samples missing between "
                f"{g['t_before_s']:.3f} s and {g['t_after_s']:.3f} s"
            )
        bad = {k: v for k, v in self.counters.items() if k.startswith("rejected") or k == "dropped"}
        if bad:
            out.append(f"rejected: {bad}")
        return out


def _split_unit(header: str) -> tuple[str, str | None]:
    m = _UNIT_HEADER.match(header)
    return (m["name"].strip(), m["unit"].strip()) if m else (header.strip(), None)


def _check_unit(tag: str, declared: str | None, node: NodeMap) -> None:
    if declared is None:
        return
    if declared not in UNITS:
        raise ValueError(
            f"unknown unit in the export, {tag!r}: {declared!r} (known: {sorted(UNITS)})"
        )
    if declared != node.unit:
        raise ValueError(
            f"unit mismatch, {tag!r}: the export declares {declared!r}, the mapping {node.unit!r}"
        )


def _stamps(values: pd.Series, timezone: str | None, tag: str) -> pd.Series:
    parsed = pd.to_datetime(values, format="ISO8601", utc=False, errors="coerce")
    if parsed.isna().any():
        bad = values[parsed.isna()].iloc[0]
        raise ValueError(f"time stamp not ISO 8601, {tag!r}: {bad!r}")
    if getattr(parsed.dt, "tz", None) is None:
        if timezone is None:
            raise ValueError(
                f"time stamps without time zone, {tag!r}: {values.iloc[0]!r} (give --timezone)"
            )
        parsed = parsed.dt.tz_localize(timezone)
    return parsed.dt.tz_convert("UTC")


def _values(column: pd.Series) -> list[Any]:
    """Cells as Python values: numbers as float, true/false as bool, empty as None."""
    out: list[Any] = []
    for v in column.tolist():
        if v is None or (isinstance(v, float) and np.isnan(v) and not isinstance(v, bool)):
            out.append(None)
        elif isinstance(v, str):
            s = v.strip().lower()
            if s in ("true", "false"):
                out.append(s == "true")
            else:
                try:
                    out.append(float(s))
                except ValueError:
                    out.append(v)
        elif isinstance(v, (bool, np.bool_)):
            out.append(bool(v))
        else:
            out.append(float(v))
    return out


def read_tag_series(
    path: Path, config: BridgeConfig, *, time_column: str = "timestamp", timezone: str | None = None
) -> dict[str, tuple[pd.Series, list[Any]]]:
    """``tag -> (UTC stamps, raw values)`` of a wide CSV file or a folder of per-tag CSV files
    (module docstring); units declared in headers checked against the mapping."""
    by_tag = {n.column: n for n in config.nodes()}
    out: dict[str, tuple[pd.Series, list[Any]]] = {}
    if path.is_dir():
        for tag, node in by_tag.items():
            f = path / f"{tag}.csv"
            if not f.exists():
                continue
            df = pd.read_csv(f, dtype=str, keep_default_na=False, na_values=[""])
            if time_column not in df.columns or len(df.columns) != 2:
                raise ValueError(
                    f"a per-tag file must hold {time_column!r} and one value column, "
                    f"{f.name}: {list(df.columns)}"
                )
            value_col = next(c for c in df.columns if c != time_column)
            _check_unit(tag, _split_unit(value_col)[1], node)
            out[tag] = (_stamps(df[time_column], timezone, tag), _values(df[value_col]))
    else:
        df = pd.read_csv(path, dtype=str, keep_default_na=False, na_values=[""])
        if time_column not in df.columns:
            raise ValueError(f"time column missing, {time_column!r} (columns: {list(df.columns)})")
        stamps = _stamps(df[time_column], timezone, time_column)
        for col in df.columns:
            if col == time_column:
                continue
            tag, unit = _split_unit(col)
            if tag not in by_tag:
                continue
            _check_unit(tag, unit, by_tag[tag])
            out[tag] = (stamps, _values(df[col]))
    if not out:
        raise ValueError(f"no mapped tag in the export, {path} (mapped: {sorted(by_tag)})")
    return out


def _period_of(config: BridgeConfig) -> dict[str, float | None]:
    periods: dict[str, float | None] = {}
    for f in config.feeders:
        for n in f.nodes.values():
            periods[n.column] = f.sample_period_s
    periods[config.sensor.node.column] = config.sensor.sample_period_s
    if config.tracer is not None:
        periods[config.tracer.node.column] = None
    return periods


def import_export(
    path: str | Path,
    config: BridgeConfig,
    *,
    time_column: str = "timestamp",
    timezone: str | None = None,
) -> tuple[list[tuple[str, Message]], ImportReport]:
    """The messages of an export (time order) and what was found (module docstring)."""
    series = read_tag_series(Path(path), config, time_column=time_column, timezone=timezone)
    report = ImportReport()
    periods = _period_of(config)
    ids = {n.column: n.node_id for n in config.nodes()}
    epoch = pd.Timestamp(config.epoch_utc).tz_convert("UTC")
    samples: list[tuple[float, str, Any]] = []
    for tag, (stamps, values) in series.items():
        t = ((stamps - epoch).dt.total_seconds()).to_numpy()
        report.rows[tag] = len(values)
        by_t: dict[float, list[Any]] = {}
        for ti, v in zip(t, values):
            if v is None:  # an empty cell: no sample at this stamp for this tag
                continue
            by_t.setdefault(float(ti), []).append(v)
        dup = sum(len(v) - 1 for v in by_t.values())
        conflict = [ti for ti, v in by_t.items() if len(set(map(repr, v))) > 1]
        report.duplicates[tag] = dup
        report.conflicting[tag] = len(conflict)
        for ti in conflict:
            del by_t[ti]
        times = sorted(by_t)
        period = periods.get(tag)
        if period is not None:
            for a, b in zip(times, times[1:]):
                if b - a > GAP_PERIODS * period:
                    report.gaps.append(
                        {
                            "tag": tag,
                            "t_before_s": a,
                            "t_after_s": b,
                            "n_missed": max(1, round((b - a) / period) - 1),
                        }
                    )
        samples += [(ti, ids[tag], by_t[ti][0]) for ti in times]
    samples.sort(key=lambda s: s[0])
    assembler = MessageAssembler(config)
    messages: list[tuple[str, Message]] = []
    for t, node, raw in samples:
        messages += assembler.add(node, t, raw)[0]
    messages += assembler.flush()[0]
    messages.sort(key=lambda km: km[1].t)
    report.counters = dict(assembler.counters)
    report.messages = len(messages)
    return messages, report
