"""Recorded line data on arrays, and the training / held-out windows.

A :class:`RunData` is what the close-loop needs of a recording: the uniform time grid, the
NIR reading of the measured component, the twin's inputs (reported feeder flows, refill flags,
tracer pulses; a ``twin_core.plant.LineInputs``) and the events (refills, pulses, disturbances,
set-point changes) as dicts ``{"t_s", "kind", "source", ...}``
(``twin_core.online.inlet.event_record`` of a ``schemas.messages.Event``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twin_core.online.inlet import event_record
from twin_core.plant.model import LineInputs


@dataclass
class StreamStamps:
    """The raw time stamps of one stream's messages in arrival order (``t_s``, s) and their
    per-publisher sequence numbers (``seq``, or None): what the data-quality check reads time
    jumps, duplicate stamps and dropouts from (``twin_core.closeloop.quality``).

    ``arrival``: each message's position in the arrival order of the whole record (all
    streams; None: unknown), what a clock offset between sources is estimated from
    (``twin_core.closeloop.quality.estimate_clock_offsets``); ``resent``: stamps of the
    messages received twice (same stamp, sequence number and values) whose copies the record
    dropped."""

    t_s: np.ndarray
    seq: np.ndarray | None = None
    arrival: np.ndarray | None = None
    resent: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self.t_s = np.asarray(self.t_s, dtype=float)
        self.resent = np.asarray(self.resent, dtype=float)
        for name in ("seq", "arrival"):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=np.int64)
                if v.shape != self.t_s.shape:
                    raise ValueError(
                        f"{name} must have the shape of t_s {self.t_s.shape}, got {v.shape}"
                    )
                setattr(self, name, v)

    def between(self, t0: float, t1: float) -> StreamStamps:
        """The stamps with t0 <= t <= t1."""
        m = (self.t_s >= t0) & (self.t_s <= t1)
        r = self.resent
        return StreamStamps(
            self.t_s[m],
            None if self.seq is None else self.seq[m],
            None if self.arrival is None else self.arrival[m],
            r[(r >= t0) & (r <= t1)],
        )


@dataclass(frozen=True)
class ClockOffset:
    """A source whose clock is off the record's common clock: its stamps minus the true times,
    ``offset_s`` (s), and the interval [``low_s``, ``high_s``] the arrival order allows
    (``twin_core.closeloop.quality.estimate_clock_offsets``), from ``n_messages`` messages
    against the ``reference`` stream; ``applied``: the record put the source back on the
    common clock."""

    series: str
    offset_s: float
    low_s: float
    high_s: float
    n_messages: int
    reference: str
    applied: bool = True

    def to_dict(self) -> dict[str, Any]:
        return {
            "series": self.series,
            "offset_s": float(self.offset_s),
            "low_s": float(self.low_s),
            "high_s": float(self.high_s),
            "n_messages": int(self.n_messages),
            "reference": self.reference,
            "applied": bool(self.applied),
        }


@dataclass
class RunData:
    """Arrays of one recording (see module docstring). NaN in ``measured`` = no sample.

    ``stamps``: the raw message stamps per stream (``nir``, ``<feeder>:flow``) when the record
    has them (a recording, the live twin), for the data-quality check.

    ``clock_offsets``: the sources whose clock the record found off the common clock and
    corrected (``twin_core.closeloop.record.LineRecord``), for the report.

    ``noise_span_s``: plant time over which the probe's 1/f noise has its declared standard
    deviation (``schemas.line.NIRNoise.pink_sd``) when this record is a segment of a longer run
    (a live window); None: the record is the whole run. The 1/f power at frequencies below
    1 / (record length) shows in a short window as a slow offset or trend: it is noise, and
    the tests must know it (:meth:`noise_record_n`).
    """

    t_s: np.ndarray
    measured: np.ndarray
    inputs: LineInputs
    events: list[dict[str, Any]] = field(default_factory=list)
    name: str = "run"
    stamps: dict[str, StreamStamps] = field(default_factory=dict)
    noise_span_s: float | None = None
    clock_offsets: list[ClockOffset] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.noise_span_s is not None and not self.noise_span_s > 0:
            raise ValueError(f"noise_span_s must be > 0 or None, got {self.noise_span_s!r}")
        self.t_s = np.asarray(self.t_s, dtype=float)
        self.measured = np.asarray(self.measured, dtype=float)
        if self.measured.shape != self.t_s.shape:
            raise ValueError(
                f"measured must have the shape of t_s {self.t_s.shape}, got {self.measured.shape}"
            )
        if not np.array_equal(self.inputs.t_s, self.t_s):
            raise ValueError("inputs.t_s must equal t_s")
        if np.sum(np.isfinite(self.measured)) < 10:
            raise ValueError("measured must hold at least 10 finite samples")

    def noise_record_n(self) -> int:
        """Samples of the 1/f process this record is a segment of: the record itself, or
        ``noise_span_s`` of plant time when longer (``twin_core.closeloop.noise.NoiseWhitener``'s
        ``n_record``: its autocorrelation c(k) = g(k) / g(0), g the Wiener-Khinchin sum over
        the bins of that span)."""
        n = int(self.t_s.size)
        if self.noise_span_s is None or n < 2:
            return n
        dt = float(np.median(np.diff(self.t_s)))
        return max(n, int(round(self.noise_span_s / dt)))

    @classmethod
    def from_line_run(cls, run: Any, name: str = "run") -> RunData:
        """From a ``twin_core.plant.LineRun`` (the simulator's output)."""
        return cls(
            t_s=run.t_s,
            measured=run.measured_pct_w_w,
            inputs=run.inputs(),
            events=[event_record(e) for e in run.events],
            name=name,
        )

    def slice(self, t0: float, t1: float) -> RunData:
        """The samples with t0 <= t < t1 (tracer pulses and events of that span)."""
        m = (self.t_s >= t0) & (self.t_s < t1)
        if m.sum() < 2:
            raise ValueError(f"window [{t0}, {t1}) must hold >= 2 samples, got {int(m.sum())}")
        inp = self.inputs
        sub = LineInputs(
            t_s=self.t_s[m],
            flows_kg_h={k: v[m] for k, v in inp.flows_kg_h.items()},
            components=dict(inp.components),
            refilling={k: v[m] for k, v in inp.refilling.items()},
            tracers=[p for p in inp.tracers if t0 <= p.t_s < t1],
            screw_speed_rpm={k: v[m] for k, v in inp.screw_speed_rpm.items()},
        )
        ev = [e for e in self.events if t0 <= float(e["t_s"]) < t1]
        t_last = float(self.t_s[m][-1])
        stamps = {k: v.between(t0, t_last) for k, v in self.stamps.items()}
        return RunData(
            self.t_s[m],
            self.measured[m],
            sub,
            ev,
            self.name,
            stamps,
            self.noise_span_s,
            list(self.clock_offsets),
        )


@dataclass
class Split:
    """Boolean masks over the run: ``train`` and ``heldout`` (disjoint)."""

    train: np.ndarray
    heldout: np.ndarray
    kind: str
    description: str


def make_split(
    t_s: np.ndarray,
    kind: str = "tail",
    train_fraction: float = 0.6,
    block_s: float = 120.0,
    skip_s: float = 0.0,
) -> Split:
    """Training / held-out masks.

    ``"tail"``: the first ``train_fraction`` of the record trains, the rest is held out (the
    fix must predict the future: forward validation). ``"blocks"``: alternating blocks of
    ``block_s`` (even blocks train, odd held out; blocked cross-validation, Bergmeir & Benitez
    2012, Inf. Sci. 191:192). ``skip_s``: samples before t_s[0] + skip_s are in neither
    (start-up transient).
    """
    t = np.asarray(t_s, dtype=float)
    if not 0.1 <= train_fraction <= 0.9:
        raise ValueError(f"train_fraction must be in [0.1, 0.9], got {train_fraction!r}")
    if not (math.isfinite(skip_s) and skip_s >= 0):
        raise ValueError(f"skip_s must be >= 0, got {skip_s!r}")
    valid = t >= t[0] + skip_s
    if kind == "tail":
        t_cut = t[0] + skip_s + train_fraction * (t[-1] - t[0] - skip_s)
        train = valid & (t < t_cut)
        held = valid & (t >= t_cut)
        desc = f"train t < {t_cut:.1f} s, held out t >= {t_cut:.1f} s"
    elif kind == "blocks":
        if not block_s > 0:
            raise ValueError(f"block_s must be > 0, got {block_s!r}")
        b = np.floor((t - t[0]) / block_s).astype(int)
        train = valid & (b % 2 == 0)
        held = valid & (b % 2 == 1)
        desc = f"alternating {block_s:.0f} s blocks (even train, odd held out)"
    else:
        raise ValueError(f"split kind must be 'tail' or 'blocks', got {kind!r}")
    if train.sum() < 10 or held.sum() < 10:
        raise ValueError("split leaves fewer than 10 samples in a window")
    return Split(train, held, kind, desc)


def split_kept(
    t_s: np.ndarray,
    keep: np.ndarray,
    kind: str = "tail",
    train_fraction: float = 0.6,
    block_s: float = 120.0,
    skip_s: float = 0.0,
) -> Split:
    """:func:`make_split` over the samples in ``keep`` only, as masks over the whole run.

    Used when the data-quality check leaves out the end of a record (after a clock jump the
    rest is misaligned): the windows are then laid over the usable part, so the usable data
    are still checked instead of the check failing for want of a held-out window."""
    keep = np.asarray(keep, dtype=bool)
    t = np.asarray(t_s, dtype=float)
    if keep.sum() < 20:
        raise ValueError(f"usable samples must be >= 20 to split, got {int(keep.sum())}")
    inner = make_split(t[keep], kind, train_fraction, block_s, skip_s)
    train = np.zeros(t.size, dtype=bool)
    held = np.zeros(t.size, dtype=bool)
    train[keep] = inner.train
    held[keep] = inner.heldout
    return Split(train, held, kind, inner.description + " (over the usable samples)")
