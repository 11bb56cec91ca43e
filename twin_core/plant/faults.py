"""Data faults of a line's records: what the data path does to good measurements.

A real record is not the process seen through noise only: instruments flat-line, drop out,
saturate at their range, burst with spikes, and the PLC's clock jumps. These faults act on the
run's bus messages (``twin_core.plant.messages.run_messages``: ``FeederFlow`` per feeder and
tick, ``MeasuredConcentration`` per NIR sample) after the process has been simulated, so the
process truth is unchanged and the truth of each fault is known (:func:`apply_faults` returns
it: kind, stream, interval, number of samples touched).

Streams: ``"nir"`` (the probe's concentration) or a feeder id (its ``FeederFlow`` messages);
``field`` chooses the value a feeder fault changes: ``"flow"`` (``mass_flow_kg_h``) or
``"screw_speed"`` (``screw_speed_rpm``). Kinds:

- ``stuck``: every reading in [t_s, t_s + duration_s) repeats the first one (a frozen
  transmitter; identical values, e.g. 90-180 s);
- ``gap``: the messages in the interval are lost (dropouts);
- ``clip``: the readings are clipped to the instrument range [low, high] over the whole record
  (the seed's FT-NIR is calibrated 0-9 % w/w; a flow transmitter has its span); the truth lists
  every clipped stretch;
- ``spike_burst``: in the interval a fraction ``fraction`` of the readings get spikes of
  ``size`` (random sign, size x U(0.5, 1.5); readings kept >= 0 for feeder values): too dense
  for an isolated-outlier filter;
- ``time_jump``: from t_s on, the stream's time stamps are shifted by ``size`` seconds (a PLC
  clock reset; the messages keep their order);
- ``duplicate_stamps``: in the interval every second message carries the time stamp of the one
  before (the clock did not advance: two readings share a stamp, the next tick has none).

- ``refill_hold``: a feeder reports, while its refill flag is up, the flow of its last message
  before the refill (a loss-in-weight controller's flow estimate frozen while the load cell
  is disturbed by the refill; not a fault of the data, a way plants report: the check must
  not take it for one).

Timing faults (:data:`TIMING_KINDS`): the readings are right, the time they are given is not.
Each acts on the whole record unless an interval is given (``t_s``/``duration_s``, default the
whole record); the messages keep their arrival order (the order of the true times) unless the
fault is a sampling one (``irregular``):

- ``shift``: the value ``field`` of each message is the one of ``size`` messages before (a
  whole number, +-1..3; negative: after), the rest of the message as it was: a feeder's
  refill flag (``field="refilling"``) one sample before or after its held load-cell value, a
  flow or a screw speed a sample off its stamp, a NIR reading stamped a sample early or late;
- ``clock_offset``: every stamp of the stream is ``size`` s off (a source whose clock differs
  from the others', up to 5 s); the messages arrive when they did; a message stamped before
  0 is not kept;
- ``jitter``: each stamp moved by U(-``size``, ``size``) s (``size`` up to half a sample
  period), in the order of arrival;
- ``irregular``: the stream is sampled at irregular times, its intervals the period times
  U(1 - ``fraction``, 1 + ``fraction``): each message the one of the original sample nearest
  its time (the process as it was at that instant, with its own noise: interpolating between
  noisy readings would average the noise), stamped with that time, numbered anew, arriving in
  time order;
- ``drop_ticks``: a share ``fraction`` of the messages lost, isolated ones (a missing tick);
- ``duplicate_ticks``: a share ``fraction`` of the messages delivered twice (the same stamp,
  sequence number and values: a re-sent message).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from schemas import keys
from schemas.line import LineConfig

__all__ = ["FAULT_KINDS", "TIMING_KINDS", "DataFault", "apply_faults", "random_timing_fault"]

#: timing faults (module docstring)
TIMING_KINDS = ("shift", "clock_offset", "jitter", "irregular", "drop_ticks", "duplicate_ticks")
FAULT_KINDS = (
    "refill_hold",
    "stuck",
    "gap",
    "clip",
    "spike_burst",
    "time_jump",
    "duplicate_stamps",
    *TIMING_KINDS,
)

#: message field of each value a fault can change
_FIELDS = {
    "nir": "concentration_pct_w_w",
    "flow": "mass_flow_kg_h",
    "screw_speed": "screw_speed_rpm",
    "refilling": "refilling",
}


@dataclass(frozen=True)
class DataFault:
    """One data fault (module docstring). ``size``: spike size (value units) or time jump (s);
    ``low``/``high``: instrument range of ``clip``; ``seed``: spike positions and signs, the
    draws of the timing faults. A timing fault (:data:`TIMING_KINDS`) with the default interval
    acts on the whole record with ``duration_s=math.inf``."""

    kind: str
    stream: str = "nir"
    field: str = "flow"
    t_s: float = 0.0
    duration_s: float = 120.0
    low: float = -math.inf
    high: float = math.inf
    size: float = 0.0
    fraction: float = 0.3
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"fault kind must be one of {FAULT_KINDS}, got {self.kind!r}")
        if self.stream != "nir" and self.field not in ("flow", "screw_speed", "refilling"):
            raise ValueError(
                f"fault field must be 'flow', 'screw_speed' or 'refilling', got {self.field!r}"
            )
        if self.field == "refilling" and self.kind not in TIMING_KINDS:
            raise ValueError(f"field 'refilling' is for a timing fault, got kind {self.kind!r}")
        if not (math.isfinite(self.t_s) and self.t_s >= 0):
            raise ValueError(f"fault t_s must be >= 0, got {self.t_s!r}")
        whole = self.kind in TIMING_KINDS and self.duration_s == math.inf
        if not ((math.isfinite(self.duration_s) or whole) and self.duration_s > 0):
            raise ValueError(f"fault duration_s must be > 0, got {self.duration_s!r}")
        if self.kind == "refill_hold" and (self.stream == "nir" or self.field != "flow"):
            raise ValueError(f"refill_hold is a feeder's flow, got {self.label!r}")
        if self.kind == "clip" and not self.low < self.high:
            raise ValueError(f"fault low must be < high, got {self.low!r} >= {self.high!r}")
        if not 0 < self.fraction <= 1:
            raise ValueError(f"fault fraction must be in (0, 1], got {self.fraction!r}")
        if self.kind in ("spike_burst", "time_jump") and not (
            math.isfinite(self.size) and self.size != 0
        ):
            raise ValueError(f"fault size must be finite and non-zero, got {self.size!r}")
        if self.kind == "shift" and not (self.size == round(self.size) and self.size != 0):
            raise ValueError(f"shift size must be a non-zero whole number, got {self.size!r}")
        if self.kind == "clock_offset" and not (math.isfinite(self.size) and self.size != 0):
            raise ValueError(f"clock_offset size must be finite and non-zero, got {self.size!r}")
        if self.kind == "jitter" and not (math.isfinite(self.size) and self.size > 0):
            raise ValueError(f"jitter size must be > 0, got {self.size!r}")
        if self.kind == "irregular" and not self.fraction < 1:
            raise ValueError(f"irregular fraction must be < 1, got {self.fraction!r}")

    @property
    def value_field(self) -> str:
        """The message field the fault changes."""
        return _FIELDS["nir" if self.stream == "nir" else self.field]

    @property
    def label(self) -> str:
        return self.stream if self.stream == "nir" else f"{self.stream}:{self.field}"

    def to_dict(self) -> dict[str, Any]:
        return {
            k: (v if not isinstance(v, float) or math.isfinite(v) else None)
            for k, v in asdict(self).items()
        }


def _stream_key(config: LineConfig, stream: str) -> str:
    """Bus key of a stream: the NIR's concentration or a feeder's flow."""
    if stream == "nir":
        return keys.measured_concentration(config.name, config.sensor.id)
    ids = [f.id for f in config.feeders]
    if stream not in ids:
        raise ValueError(f"fault stream must be 'nir' or one of {ids}, got {stream!r}")
    return keys.feeder_flow(config.name, stream)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) indices of the True stretches of a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    d = np.diff(m.astype(int))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0] - 1))


def _truth(fault: DataFault, t: np.ndarray, first: int, last: int) -> dict[str, Any]:
    return {
        "kind": fault.kind,
        "stream": fault.label,
        "t_start_s": float(t[first]),
        "t_end_s": float(t[last]),
        "n_samples": int(last - first + 1),
    }


def _isolated(rng: np.random.Generator, n: int, fraction: float) -> np.ndarray:
    """Indices of about ``fraction`` x n isolated messages (no two adjacent; not the first)."""
    pick = rng.random(n) < fraction
    if n:
        pick[0] = False
    pick[1:] &= ~pick[:-1]  # the second of two adjacent picks is not taken
    return np.nonzero(pick)[0]


def _apply_timing(
    fault: DataFault, msgs: list[Any], arrival: np.ndarray, t_all: np.ndarray
) -> tuple[list[tuple[float, Any]], list[dict[str, Any]]]:
    """A timing fault on the messages of its stream (in order) at arrival positions
    ``arrival`` of the whole record, whose messages' stamps are ``t_all``: the new messages with
    the arrival position each takes (a fraction: between two original messages), and the
    truth."""
    t = np.array([m.t for m in msgs], dtype=float)
    inside = (t >= fault.t_s) & (t < fault.t_s + fault.duration_s)
    idx = np.nonzero(inside)[0]
    keep: list[tuple[float, Any]] = [(float(a), m) for a, m in zip(arrival, msgs)]
    if idx.size == 0:
        return keep, []
    rng = np.random.default_rng(fault.seed)
    truth = _truth(fault, t, int(idx[0]), int(idx[-1]))
    truth["size"] = float(fault.size)
    if fault.kind == "shift":
        f = fault.value_field
        vals = [getattr(m, f) for m in msgs]
        k = int(fault.size)
        for i in idx:
            j = min(max(int(i) - k, 0), len(msgs) - 1)
            keep[i] = (keep[i][0], msgs[i].model_copy(update={f: vals[j]}))
        truth["field"] = f
    elif fault.kind in ("clock_offset", "jitter"):
        e = np.full(idx.size, fault.size)
        if fault.kind == "jitter":
            e = rng.uniform(-fault.size, fault.size, idx.size)
        for i, d in zip(idx, e):
            keep[i] = (keep[i][0], msgs[i].model_copy(update={"t": max(float(t[i] + d), 0.0)}))
        lost = {int(i) for i, d in zip(idx, e) if fault.kind == "clock_offset" and t[i] + d < 0}
        keep = [x for i, x in enumerate(keep) if i not in lost]
        truth["n_lost"] = len(lost)
    elif fault.kind == "drop_ticks":
        lost = {int(i) for i in idx[_isolated(rng, idx.size, fault.fraction)]}
        keep = [x for i, x in enumerate(keep) if i not in lost]
        truth["n_samples"] = len(lost)
    elif fault.kind == "duplicate_ticks":
        twice = idx[_isolated(rng, idx.size, fault.fraction)]
        keep += [(float(arrival[i]) + 0.5, msgs[i]) for i in twice]
        truth["n_samples"] = int(twice.size)
    elif fault.kind == "irregular":
        period = float(np.median(np.diff(t))) if t.size > 1 else 1.0
        a, b = float(t[idx[0]]), float(t[idx[-1]])
        steps = period * rng.uniform(1 - fault.fraction, 1 + fault.fraction, idx.size * 2 + 2)
        tn = a + np.concatenate([[0.0], np.cumsum(steps)])
        tn = tn[tn <= b]
        nearest = np.clip(np.round(np.interp(tn, t, np.arange(t.size))), 0, len(msgs) - 1)
        order = np.argsort(t_all, kind="stable")
        # the arrival position of a new sample: just after the last message stamped before it
        at = np.searchsorted(t_all[order], tn, side="right") - 1
        pos = np.where(at >= 0, order[np.maximum(at, 0)] + 0.5, -0.5)
        seq0 = int(msgs[idx[0]].seq)
        made = []
        for n, (tt, j, p) in enumerate(zip(tn, nearest, pos)):
            upd = {"t": float(tt), "seq": seq0 + n}
            made.append((float(p), msgs[int(j)].model_copy(update=upd)))
        keep = [x for i, x in enumerate(keep) if not inside[i]] + made
        truth["n_samples"] = len(made)
    return keep, [truth]


def _apply_one(fault: DataFault, msgs: list[Any]) -> tuple[list[Any | None], list[dict[str, Any]]]:
    """One fault on the messages of its stream (in order). None marks a lost message."""
    t = np.array([m.t for m in msgs], dtype=float)
    f = fault.value_field
    vals = np.array([getattr(m, f) for m in msgs], dtype=float)
    inside = (t >= fault.t_s) & (t < fault.t_s + fault.duration_s)
    idx = np.nonzero(inside)[0]
    out: list[Any | None] = list(msgs)
    truths: list[dict[str, Any]] = []
    if fault.kind == "clip":
        clipped = (vals < fault.low) | (vals > fault.high)
        for i in np.nonzero(clipped)[0]:
            out[i] = msgs[i].model_copy(update={f: float(np.clip(vals[i], fault.low, fault.high))})
        truths = [_truth(fault, t, a, b) for a, b in _runs(clipped)]
        return out, truths
    if fault.kind == "time_jump":
        after = np.nonzero(t >= fault.t_s)[0]
        if after.size == 0:
            return out, []
        if t[after[0]] + fault.size < 0:
            raise ValueError(f"fault size {fault.size!r} moves stamps before 0 at {t[after[0]]!r}")
        for i in after:
            out[i] = msgs[i].model_copy(update={"t": float(t[i] + fault.size)})
        return out, [_truth(fault, t, int(after[0]), int(after[0]))]
    if fault.kind == "refill_hold":
        refill = np.array([bool(m.refilling) for m in msgs])
        truths = []
        for a, b in _runs(refill):
            held = float(vals[a - 1]) if a > 0 else float(vals[a])
            for i in range(a, b + 1):
                out[i] = msgs[i].model_copy(update={f: held})
            truths.append(_truth(fault, t, a, b))
        return out, truths
    if idx.size == 0:
        return out, []
    truth = _truth(fault, t, int(idx[0]), int(idx[-1]))
    if fault.kind == "stuck":
        for i in idx:
            out[i] = msgs[i].model_copy(update={f: float(vals[idx[0]])})
    elif fault.kind == "gap":
        for i in idx:
            out[i] = None
    elif fault.kind == "spike_burst":
        rng = np.random.default_rng(fault.seed)
        hit = idx[rng.random(idx.size) < fault.fraction]
        sign = rng.choice([-1.0, 1.0], hit.size)
        amp = fault.size * rng.uniform(0.5, 1.5, hit.size)
        for i, s, a in zip(hit, sign, amp):
            v = vals[i] + s * a
            out[i] = msgs[i].model_copy(update={f: max(v, 0.0) if fault.stream != "nir" else v})
        truth["n_samples"] = int(hit.size)
    elif fault.kind == "duplicate_stamps":
        for j in range(1, idx.size, 2):
            out[idx[j]] = msgs[idx[j]].model_copy(update={"t": float(t[idx[j - 1]])})
    return out, [truth]


def apply_faults(
    messages: Sequence[tuple[str, Any]], faults: Sequence[DataFault], config: LineConfig
) -> tuple[list[tuple[str, Any]], list[dict[str, Any]]]:
    """The messages with the faults applied, in their order (lost messages removed), and the
    faults' truth: one dict per affected stretch, {kind, stream, t_start_s, t_end_s,
    n_samples} (times are the original stamps)."""
    out: list[tuple[str, Any] | None] = list(messages)
    truths: list[dict[str, Any]] = []
    for fault in faults:
        key = _stream_key(config, fault.stream)
        if fault.kind in TIMING_KINDS:
            rows = [m for m in out if m is not None]
            pos = [i for i, item in enumerate(rows) if item[0] == key]
            if not pos:
                raise ValueError(f"fault stream {fault.stream!r} has no messages (key {key!r})")
            t_all = np.array([m[1].t for m in rows], dtype=float)
            made, truth = _apply_timing(fault, [rows[i][1] for i in pos], np.array(pos), t_all)
            others = [(float(i), m) for i, m in enumerate(rows) if m[0] != key]
            merged = sorted(others + [(a, (key, m)) for a, m in made], key=lambda x: x[0])
            out = [m for _, m in merged]
            truths.extend(truth)
            continue
        pos = [i for i, item in enumerate(out) if item is not None and item[0] == key]
        if not pos:
            raise ValueError(f"fault stream {fault.stream!r} has no messages (key {key!r})")
        changed, truth = _apply_one(fault, [out[i][1] for i in pos])
        for i, msg in zip(pos, changed):
            out[i] = None if msg is None else (key, msg)
        truths.extend(truth)
    return [m for m in out if m is not None], truths


def random_timing_fault(
    seed: int, feeders: Sequence[str], period_s: float = 1.0
) -> tuple[DataFault, ...]:
    """A timing fault of :data:`TIMING_KINDS` drawn with ``seed`` over the whole record: the kind
    uniform; a ``shift`` of +-1..3 samples of a feeder's refill flag (half the draws) or screw
    speed against the rest of its messages (a value shifted against its own stamp is a delay
    of that series, which no stamp shows: for the NIR it is the in-list ``extra_delay``); a ``clock_offset`` of +-(0.5..5) s, a ``jitter`` of 0.1..0.5 periods,
    ``irregular`` intervals of 1 +- 0.1..0.5 periods, 1..5 % of the ticks dropped or delivered
    twice, on the NIR or a feeder (``period_s``: the sampling period). A refill flag's shift
    comes after the feeder's ``refill_hold`` (its flow held over each refill, as the records
    of the issue: the held value and its flag a sample or more apart)."""
    rng = np.random.default_rng(seed)
    kind = str(rng.choice(TIMING_KINDS))
    streams = ["nir", *feeders]
    stream = str(rng.choice(streams))
    field = "flow"
    size, fraction = 0.0, 0.3
    if kind == "shift":  # a flag or value against the other fields of its feeder's message
        stream = str(rng.choice(list(feeders)))
        field = "refilling" if rng.random() < 0.5 else "screw_speed"
        size = float(rng.choice([-3, -2, -1, 1, 2, 3]))
    elif kind == "clock_offset":
        size = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 5.0))
    elif kind == "jitter":
        size = float(rng.uniform(0.1, 0.5) * period_s)
    elif kind == "irregular":
        fraction = float(rng.uniform(0.1, 0.5))
    else:
        fraction = float(rng.uniform(0.01, 0.05))
    fault = DataFault(
        kind,
        stream,
        field,
        duration_s=math.inf,
        size=size,
        fraction=fraction,
        seed=int(rng.integers(1 << 31)),
    )
    if field == "refilling":
        return (DataFault("refill_hold", stream), fault)
    return (fault,)
