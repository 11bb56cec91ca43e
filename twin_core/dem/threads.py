"""Thread count chosen at run time from measured throughput (``twin dem run --threads auto``).

On an idle two-core machine two numba threads run the engine faster than one; on a loaded machine
every parallel region waits for a descheduled thread and two threads are slower than one
(docs/dem_engine.md). The pair forces are summed in an order fixed by the chunks of the scatter
(``Simulation.pair_chunks``), not by the threads, so the thread count can change between chunks
of steps without changing the results. :class:`ThreadChooser` alternates one thread and the maximum for a probe
(each until it has ``probe_s`` of wall time), keeps the one with the higher particle-steps per
wall second (median of its chunks) for ``hold_s`` of wall time, and probes again, so a machine
whose load changes is followed.

``adaptive_threads()`` is a context manager under which :meth:`Simulation.run
<twin_core.dem.simulation.Simulation.run>` uses a chooser (the CLI wraps a scene's runs in it);
``Simulation.thread_policy = "adaptive"`` does the same for one simulation.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
from collections.abc import Iterator

import numpy as np

__all__ = ["OPENMP_FIRST", "ThreadChooser", "adaptive_threads", "current_policy", "prefer_openmp"]

#: numba threading layers in the order a DEM process asks for them
OPENMP_FIRST: tuple[str, ...] = ("omp", "tbb", "workqueue")

_POLICY: contextvars.ContextVar[str] = contextvars.ContextVar("dem_thread_policy", default="fixed")


@contextlib.contextmanager
def adaptive_threads() -> Iterator[None]:
    """Within the block, simulations choose their thread count at run time."""
    token = _POLICY.set("adaptive")
    try:
        yield
    finally:
        _POLICY.reset(token)


def prefer_openmp() -> tuple[str, ...] | None:
    """Ask numba for its OpenMP threading layer first (then TBB, then workqueue) in this
    process and the processes it starts (``NUMBA_THREADING_LAYER_PRIORITY``); returns the order
    set, or None where it is left alone: the environment chooses (``NUMBA_THREADING_LAYER`` or
    ``NUMBA_THREADING_LAYER_PRIORITY``) or a layer has started.

    Why: on two idle cores the engine's two threads run 2.0x one thread under OpenMP and 1.5x
    under TBB (``benchmarks/dem_threading_layers.py``, docs/dem_engine.md): OpenMP's static schedule
    keeps each half of the particles on the same core from step to step. For processes whose
    work is the DEM (``twin dem``, the campaign and benchmark scripts), called at their start
    (not the live twin's dem service: there it stopped the service answering,
    docs/dem_engine.md). GNU OpenMP is not fork-safe: a process that has run a parallel region
    under it must not fork a child that runs one (the calibration campaign's process pool
    starts its workers with ``forkserver``).
    """
    import numba
    from numba.np.ufunc import parallel

    if "NUMBA_THREADING_LAYER" in os.environ or "NUMBA_THREADING_LAYER_PRIORITY" in os.environ:
        return None
    if parallel._is_initialized:
        return None
    numba.config.THREADING_LAYER_PRIORITY = list(OPENMP_FIRST)
    # child interpreters (campaign workers, subprocesses) read it from the environment
    os.environ["NUMBA_THREADING_LAYER_PRIORITY"] = " ".join(OPENMP_FIRST)
    return OPENMP_FIRST


def current_policy() -> str:
    """``"adaptive"`` inside :func:`adaptive_threads`, else ``"fixed"``."""
    return _POLICY.get()


class ThreadChooser:
    """Choose 1 or ``max_threads`` threads for each chunk of steps (module docstring).

    Args:
        max_threads: the most threads to use (> 1, else the chooser always answers 1).
        probe_s: wall time each candidate runs during a probe.
        hold_s: wall time the faster candidate is kept between probes.
    """

    def __init__(self, max_threads: int, probe_s: float = 0.6, hold_s: float = 20.0) -> None:
        self.candidates = (1, int(max_threads)) if max_threads > 1 else (1,)
        self.probe_s = probe_s
        self.hold_s = hold_s
        self.chosen = self.candidates[-1]
        self._rates: dict[int, list[float]] = {c: [] for c in self.candidates}
        self._wall: dict[int, float] = {c: 0.0 for c in self.candidates}
        self._held = 0.0
        self._probing = len(self.candidates) > 1
        #: (threads chosen, median rate of each candidate) after each probe
        self.history: list[tuple[int, dict[int, float]]] = []

    def next_threads(self) -> int:
        """Thread count for the next chunk."""
        if not self._probing:
            return self.chosen
        # alternate the candidates until each has probe_s of wall time
        return min(self.candidates, key=lambda c: self._wall[c])

    def record(self, threads: int, particle_steps: float, wall_s: float) -> None:
        """A chunk ran ``particle_steps`` in ``wall_s`` with ``threads``."""
        if wall_s <= 0 or threads not in self._rates:
            return
        if not self._probing:
            self._held += wall_s
            if self._held >= self.hold_s:
                self._start_probe()
            return
        self._rates[threads].append(particle_steps / wall_s)
        self._wall[threads] += wall_s
        if all(self._rates.values()) and min(self._wall.values()) >= self.probe_s:
            medians = {c: float(np.median(r)) for c, r in self._rates.items()}
            self.chosen = max(self.candidates, key=lambda c: (medians[c], -c))
            self.history.append((self.chosen, medians))
            self._probing = False
            self._held = 0.0

    def _start_probe(self) -> None:
        self._probing = True
        self._rates = {c: [] for c in self.candidates}
        self._wall = {c: 0.0 for c in self.candidates}
