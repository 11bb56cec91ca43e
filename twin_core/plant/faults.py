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
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from schemas import keys
from schemas.line import LineConfig

__all__ = ["FAULT_KINDS", "DataFault", "apply_faults"]

FAULT_KINDS = ("stuck", "gap", "clip", "spike_burst", "time_jump", "duplicate_stamps")

#: message field of each value a fault can change
_FIELDS = {
    "nir": "concentration_pct_w_w",
    "flow": "mass_flow_kg_h",
    "screw_speed": "screw_speed_rpm",
}


@dataclass(frozen=True)
class DataFault:
    """One data fault (module docstring). ``size``: spike size (value units) or time jump (s);
    ``low``/``high``: instrument range of ``clip``; ``seed``: spike positions and signs."""

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
        if self.stream != "nir" and self.field not in ("flow", "screw_speed"):
            raise ValueError(f"fault field must be 'flow' or 'screw_speed', got {self.field!r}")
        if not (math.isfinite(self.t_s) and self.t_s >= 0):
            raise ValueError(f"fault t_s must be >= 0, got {self.t_s!r}")
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise ValueError(f"fault duration_s must be > 0, got {self.duration_s!r}")
        if self.kind == "clip" and not self.low < self.high:
            raise ValueError(f"fault low must be < high, got {self.low!r} >= {self.high!r}")
        if not 0 < self.fraction <= 1:
            raise ValueError(f"fault fraction must be in (0, 1], got {self.fraction!r}")
        if self.kind in ("spike_burst", "time_jump") and not (
            math.isfinite(self.size) and self.size != 0
        ):
            raise ValueError(f"fault size must be finite and non-zero, got {self.size!r}")

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
        pos = [i for i, item in enumerate(out) if item is not None and item[0] == key]
        if not pos:
            raise ValueError(f"fault stream {fault.stream!r} has no messages (key {key!r})")
        changed, truth = _apply_one(fault, [out[i][1] for i in pos])
        for i, msg in zip(pos, changed):
            out[i] = None if msg is None else (key, msg)
        truths.extend(truth)
    return [m for m in out if m is not None], truths
