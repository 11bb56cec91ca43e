"""Event-time merge of several time-ordered streams (a watermark, as in stream processors).

Items are released in (t, stream order, arrival) order once every stream has reached at least
that time (the watermark is the minimum over the streams of their latest time; a stream that has
delivered nothing yet holds everything back): the result does not depend on how the streams
interleaved in transit (after a restart, history arrives stream by stream). A stream that knows
it will deliver nothing before some time says so with :meth:`WatermarkMerger.advance` (a
punctuation, as in stream processors), so that the others are not held back by its silence.
:meth:`WatermarkMerger.release_all` drains everything (end of stream, or a stream known to be
silent).
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Sequence
from typing import Any

__all__ = ["WatermarkMerger"]


class WatermarkMerger:
    """Merge time-ordered streams by plant time.

    Args:
        streams: names of the streams, in tie-break order (equal times release in this order).
    """

    def __init__(self, streams: Sequence[str]) -> None:
        if not streams:
            raise ValueError("streams must not be empty, got []")
        self.order = {s: i for i, s in enumerate(streams)}
        self.last: dict[str, float] = {}
        self._heap: list[tuple[float, int, int, str, Any]] = []
        self._n = 0

    def push(self, stream: str, t: float, item: Any) -> list[tuple[str, float, Any]]:
        """Add one item of ``stream`` at time t; return the items now releasable, in order."""
        if stream not in self.order:
            raise ValueError(f"stream must be one of {list(self.order)}, got {stream!r}")
        if not math.isfinite(t):
            raise ValueError(f"t must be finite, got {t!r}")
        prev = self.last.get(stream, -math.inf)
        if t < prev:
            raise ValueError(f"t must not decrease within stream {stream!r}: {t} < {prev}")
        self.last[stream] = t
        heapq.heappush(self._heap, (t, self.order[stream], self._n, stream, item))
        self._n += 1
        if len(self.last) < len(self.order):
            return []
        return self._release(min(self.last.values()))

    def advance(self, stream: str, t: float) -> list[tuple[str, float, Any]]:
        """``stream`` will deliver nothing before time ``t`` (its watermark moves to ``t`` if
        later); return the items now releasable, in order."""
        if stream not in self.order:
            raise ValueError(f"stream must be one of {list(self.order)}, got {stream!r}")
        if not math.isfinite(t):
            raise ValueError(f"t must be finite, got {t!r}")
        self.last[stream] = max(self.last.get(stream, -math.inf), t)
        if len(self.last) < len(self.order):
            return []
        return self._release(min(self.last.values()))

    def _release(self, watermark: float) -> list[tuple[str, float, Any]]:
        out = []
        heap = self._heap
        while heap and heap[0][0] <= watermark:
            t, _, _, s, item = heapq.heappop(heap)
            out.append((s, t, item))
        return out

    def release_all(self, until: float = math.inf) -> list[tuple[str, float, Any]]:
        """Release every buffered item up to time ``until`` (default: all), in order, whatever
        the streams' watermarks (end of stream, or a stream known to be silent)."""
        return self._release(until)

    def __len__(self) -> int:
        return len(self._heap)
