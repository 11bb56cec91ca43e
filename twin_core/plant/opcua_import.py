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

Nothing is guessed; everything is reported (:class:`ImportReport`):

- a unit declared in the export that differs from the mapping's, or is not a known unit,
  refuses the import (ValueError naming tag and units);
- a *bad row* (a stamp that is no ISO 8601 time or lacks the time zone the other rows carry,
  a row with more or fewer fields than the header, a cell refused by
  ``twin_core.plant.opcua_map.convert`` or outside the message contract, e.g. a negative
  mass) is named by :class:`BadCell` (file, row = the file's line number, the header being
  line 1, tag, value, reason): the import raises :class:`BadRows` naming every one, or, with
  ``skip_bad_rows``, leaves those rows out (counted and named);
- an empty cell is no sample of that tag at that stamp; a repeated stamp of a tag is a
  duplicate: with the same value one is kept, with different values the stamp is dropped (both
  counted, each conflict named with its rows);
- a unit (feeder, sensor, blender drive) writes no message at a stamp where a tag it takes at
  every sample is empty, conflicting, skipped or absent: never an earlier value in its place
  (``twin_core.plant.opcua_map.MessageAssembler``); the message's sequence numbers skip that
  sample slot, as the bridge's do, and the stamp is named with the tags and why
  (``ImportReport.missing``);
- a gap (stamps of a tag more than 1.5 of its unit's sample periods apart) is reported with
  its stretch and left as it is.
"""

from __future__ import annotations

import csv
import functools
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any

import pandas as pd
from pydantic import BaseModel, TypeAdapter, ValidationError

from schemas.base import Message
from schemas.messages import BlenderDrive, Event, FeederFlow, MeasuredConcentration
from schemas.opcua import UNITS, BridgeConfig, NodeMap
from twin_core.plant.opcua_map import GAP_PERIODS, BadValue, MessageAssembler, convert

__all__ = ["BadCell", "BadRows", "ImportReport", "import_export", "read_tag_series"]

_UNIT_HEADER = re.compile(r"^(?P<name>.*?)\s*\[(?P<unit>[^\]]+)\]\s*$")

#: a row of an export: (file name, line number; the header is line 1)
Row = tuple[str, int]
#: a cell left out because its row is bad (``skip_bad_rows``)
SKIPPED = "skipped"


@dataclass(frozen=True)
class BadCell:
    """A bad row of an export: its file, row (the file's line number), the tag (None: the row
    as a whole, e.g. its field count), the value as written and why it is refused."""

    file: str
    row: int
    tag: str | None
    value: str
    reason: str

    def describe(self) -> str:
        """``wide.csv row 14, 'api_MassFlow': 'abc' (rejected_type: ...)``."""
        where = f"{self.file} row {self.row}"
        if self.tag is not None:
            where += f", {self.tag!r}"
        value = self.value if len(self.value) <= 80 else self.value[:77] + "..."
        return f"{where}: {value!r} ({self.reason})"


class BadRows(ValueError):
    """Rows of an export the import refuses (``skip_bad_rows`` leaves them out): ``bad``
    names each one; the message names the first and the count."""

    def __init__(self, bad: list[BadCell]) -> None:
        n = len({(b.file, b.row) for b in bad})
        more = f", and {len(bad) - 1} more bad cells (each named)" if len(bad) > 1 else ""
        super().__init__(
            f"{n} bad {'row' if n == 1 else 'rows'} in the export, {bad[0].describe()}{more}; "
            "--skip-bad-rows leaves them out"
        )
        self.bad = bad


@dataclass
class ImportReport:
    """What the import found: per tag rows, duplicates and gaps; bad rows (named, skipped when
    asked); the stamps where a unit wrote no message and why; the assembler's counters."""

    rows: dict[str, int] = field(default_factory=dict)
    duplicates: dict[str, int] = field(default_factory=dict)
    conflicting: dict[str, int] = field(default_factory=dict)
    conflicts: list[dict[str, Any]] = field(default_factory=list)
    gaps: list[dict[str, Any]] = field(default_factory=list)
    bad: list[BadCell] = field(default_factory=list)
    skipped_rows: int = 0
    missing: list[dict[str, Any]] = field(default_factory=list)
    counters: dict[str, int] = field(default_factory=dict)
    messages: int = 0

    def lines(self) -> list[str]:
        """The report as text lines: the summary first, then what was found (each a line)."""
        out = [
            f"{self.messages} messages from {sum(self.rows.values())} samples of "
            f"{len(self.rows)} tags"
        ]
        if self.skipped_rows:
            n = self.skipped_rows
            out.append(f"skipped {n} bad {'row' if n == 1 else 'rows'} (--skip-bad-rows):")
        out += [f"bad row: {b.describe()}" for b in self.bad]
        for tag, n in self.duplicates.items():
            if n:
                out.append(
                    f"duplicates: {tag}: {n} repeated stamps "
                    f"({self.conflicting.get(tag, 0)} with different values, dropped)"
                )
        for c in self.conflicts:
            out.append(
                f"conflict: {c['tag']} at {c['t_s']:.3f} s: "
                + ", ".join(f"{f} row {r}: {v!r}" for (f, r), v in zip(c["rows"], c["values"]))
            )
        for g in self.gaps:
            out.append(
                f"gap: {g['tag']}: {g['n_missed']} samples missing between "
                f"{g['t_before_s']:.3f} s and {g['t_after_s']:.3f} s"
            )
        for m in self.missing:
            span = (
                f"at {m['t_start_s']:.3f} s"
                if m["n_stamps"] == 1
                else f"at {m['t_start_s']:.3f}-{m['t_end_s']:.3f} s ({m['n_stamps']} stamps)"
            )
            out.append(f"no message: {m['unit']} {span}: {m['reason']}")
        bad = {
            k: v
            for k, v in self.counters.items()
            if k.startswith("rejected") or k in ("dropped", "missing")
        }
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


def _read_csv(path: Path) -> tuple[list[str], list[tuple[int, list[str]]], list[BadCell]]:
    """Header and ``(line, fields)`` rows of a CSV file; a row with another field count than
    the header is a :class:`BadCell` of the row."""
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            raise ValueError(f"the export is empty, {path.name}")
        rows: list[tuple[int, list[str]]] = []
        bad: list[BadCell] = []
        for fields in reader:
            line = reader.line_num
            if not fields or all(not x.strip() for x in fields):
                continue
            if len(fields) != len(header):
                bad.append(
                    BadCell(
                        path.name,
                        line,
                        None,
                        ",".join(fields),
                        f"{len(fields)} fields, the header has {len(header)}",
                    )
                )
                continue
            rows.append((line, fields))
    return header, rows, bad


def _plant_times(
    texts: list[str],
    lines: list[int],
    *,
    file: str,
    column: str,
    timezone: str | None,
    epoch: pd.Timestamp,
) -> tuple[list[float | None], list[BadCell]]:
    """Plant time of each stamp (None where the row is bad, named in the list returned)."""
    parsed: list[datetime | None] = []
    bad: list[BadCell] = []
    for text, line in zip(texts, lines):
        try:
            parsed.append(datetime.fromisoformat(text.strip()))
        except ValueError:
            parsed.append(None)
            bad.append(BadCell(file, line, column, text, "not an ISO 8601 stamp"))
    naive = [i for i, d in enumerate(parsed) if d is not None and d.tzinfo is None]
    aware = sum(1 for d in parsed if d is not None and d.tzinfo is not None)
    out: list[float | None] = [None] * len(parsed)
    if naive and timezone is None:
        if not aware:
            raise ValueError(
                f"time stamps without time zone, {column!r}: {texts[naive[0]]!r} (give --timezone)"
            )
        for i in naive:  # the other rows carry one: these are bad rows, not a guess
            bad.append(BadCell(file, lines[i], column, texts[i], "no time zone"))
            parsed[i] = None
    elif naive:
        local = pd.DatetimeIndex([parsed[i] for i in naive]).tz_localize(
            timezone, ambiguous="NaT", nonexistent="NaT"
        )
        for i, ts in zip(naive, local):
            if pd.isna(ts):
                bad.append(
                    BadCell(
                        file,
                        lines[i],
                        column,
                        texts[i],
                        f"ambiguous or nonexistent local time in {timezone}",
                    )
                )
            else:
                out[i] = (ts - epoch).total_seconds()
            parsed[i] = None
    for i, d in enumerate(parsed):
        if d is not None and d.tzinfo is not None:
            out[i] = (pd.Timestamp(d).tz_convert("UTC") - epoch).total_seconds()
    return out, bad


def _value(text: str) -> Any:
    """A cell as a Python value: a number as float, true/false as bool, empty as None, other
    text as it is (refused by ``convert``)."""
    s = text.strip()
    if not s:
        return None
    if s.lower() in ("true", "false"):
        return s.lower() == "true"
    try:
        return float(s)
    except ValueError:
        return text


@functools.cache
def _contract(model: type[BaseModel], name: str) -> TypeAdapter:
    """The validator of one field of a message model (its type and constraints)."""
    info = model.model_fields[name]
    if not info.metadata:
        return TypeAdapter(info.annotation)
    return TypeAdapter(Annotated[info.annotation, *info.metadata])


def _fields_of(config: BridgeConfig) -> dict[str, tuple[NodeMap, type[BaseModel], str]]:
    """``tag -> (node, message model, field)`` of every mapped node."""
    out: dict[str, tuple[NodeMap, type[BaseModel], str]] = {}
    for f in config.feeders:
        for name, node in f.nodes.items():
            out[node.column] = (node, FeederFlow, name)
    s = config.sensor.node
    out[s.column] = (s, MeasuredConcentration, "concentration_pct_w_w")
    if config.tracer is not None:
        out[config.tracer.node.column] = (config.tracer.node, Event, "mass_kg")
    if config.blender is not None:
        out[config.blender.node.column] = (config.blender.node, BlenderDrive, "blade_speed_rpm")
    return out


def _refusal(node: NodeMap, model: type[BaseModel], name: str, raw: Any) -> str | None:
    """Why a cell's value cannot be used (``convert``'s reason, or the message contract's),
    None when it can."""
    try:
        value = convert(node, raw)
    except BadValue as exc:
        return f"{exc.reason}: {exc}"
    try:
        _contract(model, name).validate_python(value)
    except ValidationError as exc:
        return (
            f"outside the contract, {model.__name__}.{name} = {value!r}: {exc.errors()[0]['msg']}"
        )
    return None


#: one cell of a tag: its row, plant time and value (None: empty; SKIPPED: its row is bad)
Cell = tuple[Row, float, Any]


def read_tag_series(
    path: Path, config: BridgeConfig, *, time_column: str = "timestamp", timezone: str | None = None
) -> tuple[dict[str, list[Cell]], list[BadCell]]:
    """``tag -> cells`` (row, plant time, value: None for an empty cell) of a wide CSV file or
    a folder of per-tag CSV files (module docstring), and the bad rows found (a row with a bad
    stamp has no cell; a bad cell's row keeps its other cells, the bad one as ``SKIPPED``).
    Units declared in headers are checked against the mapping."""
    fields = _fields_of(config)
    epoch = pd.Timestamp(config.epoch_utc).tz_convert("UTC")
    out: dict[str, list[Cell]] = {}
    bad: list[BadCell] = []

    def take(file: str, header: list[str], rows: list[tuple[int, list[str]]], tags: dict) -> None:
        i_time = header.index(time_column)
        lines = [line for line, _ in rows]
        times, bad_t = _plant_times(
            [r[i_time] for _, r in rows],
            lines,
            file=file,
            column=time_column,
            timezone=timezone,
            epoch=epoch,
        )
        bad.extend(bad_t)
        for col, tag in tags.items():
            node, model, name = fields[tag]
            cells = out.setdefault(tag, [])
            for (line, r), t in zip(rows, times):
                if t is None:
                    continue
                raw = _value(r[col])
                why = None if raw is None else _refusal(node, model, name, raw)
                if why is not None:
                    bad.append(BadCell(file, line, tag, r[col], why))
                    raw = SKIPPED
                cells.append(((file, line), t, raw))

    if path.is_dir():
        for tag, (node, _, _) in fields.items():
            f = path / f"{tag}.csv"
            if not f.exists():
                continue
            header, rows, bad_rows = _read_csv(f)
            bad.extend(bad_rows)
            if time_column not in header or len(header) != 2:
                raise ValueError(
                    f"a per-tag file must hold {time_column!r} and one value column, "
                    f"{f.name}: {header}"
                )
            i_value = 1 - header.index(time_column)
            _check_unit(tag, _split_unit(header[i_value])[1], node)
            take(f.name, header, rows, {i_value: tag})
    else:
        header, rows, bad_rows = _read_csv(path)
        bad.extend(bad_rows)
        if time_column not in header:
            raise ValueError(f"time column missing, {time_column!r} (columns: {header})")
        tags: dict[int, str] = {}
        for i, col in enumerate(header):
            tag, unit = _split_unit(col)
            if col == time_column or tag not in fields:
                continue
            _check_unit(tag, unit, fields[tag][0])
            tags[i] = tag
        take(path.name, header, rows, tags)
    if not out:
        raise ValueError(f"no mapped tag in the export, {path} (mapped: {sorted(fields)})")
    bad.sort(key=lambda b: (b.file, b.row))
    return out, bad


def _stretches(
    times: list[float], why: dict[float, str], period: float | None
) -> Iterable[tuple[float, float, int, str]]:
    """Consecutive stamps (at most 1.5 periods apart) with the same reason, as
    ``(first, last, n, reason)``."""
    run: list[float] = []
    for t in sorted(times):
        if run and (why[t] != why[run[-1]] or period is None or t - run[-1] > GAP_PERIODS * period):
            yield run[0], run[-1], len(run), why[run[0]]
            run = []
        run.append(t)
    if run:
        yield run[0], run[-1], len(run), why[run[0]]


def import_export(
    path: str | Path,
    config: BridgeConfig,
    *,
    time_column: str = "timestamp",
    timezone: str | None = None,
    skip_bad_rows: bool = False,
) -> tuple[list[tuple[str, Message]], ImportReport]:
    """The messages of an export (time order) and what was found (module docstring). Raises
    :class:`BadRows` naming every bad row unless ``skip_bad_rows``, which leaves them out."""
    series, bad = read_tag_series(Path(path), config, time_column=time_column, timezone=timezone)
    report = ImportReport(bad=bad)
    if bad and not skip_bad_rows:
        raise BadRows(bad)
    bad_rows = {(b.file, b.row) for b in bad}
    report.skipped_rows = len(bad_rows)
    periods = {n.column: None for n in config.nodes()}
    assembler = MessageAssembler(config)
    for unit in assembler.units:
        for node in unit.fields.values():
            periods[node.column] = unit.period_s if node.stamped == "every_sample" else None
    ids = {n.column: n.node_id for n in config.nodes()}
    samples: list[tuple[float, str, Any]] = []
    # tag -> stamp -> why it has no value there (empty, conflicting, bad row skipped)
    lacking: dict[str, dict[float, str]] = {}
    for tag, cells in series.items():
        report.rows[tag] = len(cells)
        by_t: dict[float, list[tuple[Row, Any]]] = {}
        for row, t, v in cells:
            by_t.setdefault(t, []).append((row, SKIPPED if row in bad_rows else v))
        why: dict[float, str] = {}
        good: dict[float, list[tuple[Row, Any]]] = {}
        for t, vs in by_t.items():
            kept = [(r, v) for r, v in vs if v is not None and v is not SKIPPED]
            if not kept:
                skipped = any(v is SKIPPED for _, v in vs)
                why[t] = "bad row skipped" if skipped else "empty"
            else:
                good[t] = kept
        report.duplicates[tag] = sum(len(v) - 1 for v in good.values())
        conflict = [t for t, v in good.items() if len({repr(x) for _, x in v}) > 1]
        report.conflicting[tag] = len(conflict)
        for t in sorted(conflict):
            report.conflicts.append(
                {
                    "tag": tag,
                    "t_s": t,
                    "rows": [r for r, _ in good[t]],
                    "values": [x for _, x in good[t]],
                }
            )
            del good[t]
            why[t] = "conflicting"
        lacking[tag] = why
        times = sorted(good)
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
        samples += [(t, ids[tag], good[t][0][1]) for t in times]
    samples.sort(key=lambda s: s[0])
    messages: list[tuple[str, Message]] = []
    for t, node, raw in samples:
        messages += assembler.add(node, t, raw)[0]
    messages += assembler.flush()[0]
    messages.sort(key=lambda km: km[1].t)
    report.counters = dict(assembler.counters)
    report.messages = len(messages)
    report.missing = _missing(assembler, series, lacking, messages)
    return messages, report


def _missing(
    assembler: MessageAssembler,
    series: dict[str, list[Cell]],
    lacking: dict[str, dict[float, str]],
    messages: list[tuple[str, Message]],
) -> list[dict[str, Any]]:
    """The stamps of the export at which a unit sampled each period wrote no message, in
    stretches, with the tags that lacked a value there and why."""
    written: dict[str, set[float]] = {}
    for key, msg in messages:
        written.setdefault(key, set()).add(msg.t)
    out: list[dict[str, Any]] = []
    for unit in assembler.units:
        if unit.period_s is None:  # the tracer: a stamp without pulse is no message
            continue
        tags = [n.column for n in unit.fields.values() if n.stamped == "every_sample"]
        seen = {t for tag in tags for _, t, _ in series.get(tag, [])}
        stamps = {tag: {t for _, t, _ in series.get(tag, [])} for tag in tags}
        why: dict[float, str] = {}
        for t in seen - written.get(unit.key, set()):
            by_reason: dict[str, list[str]] = {}
            for tag in tags:
                if t in lacking.get(tag, {}):
                    by_reason.setdefault(lacking[tag][t], []).append(tag)
                elif t not in stamps[tag]:
                    by_reason.setdefault("absent", []).append(tag)
            why[t] = (
                "; ".join(f"{', '.join(ts)} {r}" for r, ts in by_reason.items())
                or "refused (see the counters)"
            )
        for first, last, n, reason in _stretches(list(why), why, unit.period_s):
            out.append(
                {
                    "unit": unit.name,
                    "key": unit.key,
                    "t_start_s": first,
                    "t_end_s": last,
                    "n_stamps": n,
                    "reason": reason,
                }
            )
    out.sort(key=lambda m: (m["t_start_s"], m["unit"]))
    return out
