"""Streaming (incremental) convolution of an inlet signal with a residence time distribution.

The outlet of a linear, time-invariant unit with residence time distribution E(t) is the
convolution (Danckwerts 1953; Fogler, *Elements of Chemical Reaction Engineering*, ch. 16)

    c_out(t) = integral_0^inf E(s) c_in(t - s) ds,

discretised on a uniform grid t_n = n dt as the rectangle rule

    y[n] = dt * sum_{k=0}^{K-1} e[k] u[n - k],                                  (1)

which is ``dt * numpy.convolve(u, e)[:N]`` for a stream that starts from zero. For live use the
stream starts from a steady state: samples before the first one are taken equal to ``initial``
(the steady-state inlet), so that a line at steady state predicts its own inlet, not a start-up
transient.

:class:`StreamingConvolver` keeps only the last K-1 inputs (a doubled ring buffer), so the cost of
a sample is one length-K dot product, independent of how long the stream has run (O(1) in the
stream length, O(K) arithmetic), and a block of M samples costs one ``numpy.convolve`` of
M + K - 1 points. Results equal the batch convolution to floating-point rounding.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["StreamingConvolver"]


class StreamingConvolver:
    """Incremental evaluation of Eq. (1) one sample (``push``) or one block (``push_many``) at a time.

    Args:
        e: E(t) sampled on the uniform grid k*dt, k = 0..K-1 (1/s), K >= 1.
        dt: sampling interval, s (> 0).
        initial: inlet value assumed for all samples before the first one (0 gives the
            plain ``numpy.convolve`` start-up; a steady-state value gives a steady start).
        normalize: rescale ``e`` so that ``dt * sum(e) == 1`` (unit gain: a truncated or coarsely
            sampled E(t) otherwise predicts a steady outlet slightly off its inlet).

    Attributes:
        n_: number of samples pushed so far.
        gain_: dt * sum(e) of the kernel in use (1 after normalisation).
    """

    def __init__(
        self, e: np.ndarray, dt: float, initial: float = 0.0, normalize: bool = False
    ) -> None:
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be > 0, got {dt!r}")
        if not np.isfinite(initial):
            raise ValueError(f"initial must be finite, got {initial!r}")
        self.dt = float(dt)
        self.normalize = bool(normalize)
        self.initial = float(initial)
        self.n_ = 0
        self._set_kernel(e)
        k = self._k
        # doubled ring buffer (both halves equal): the window _buf[_pos:_pos + K] is contiguous
        self._buf = np.full(2 * k, self.initial, dtype=float)
        self._pos = 0  # the window _buf[_pos:_pos + k] holds the last k inputs, oldest first

    # ------------------------------------------------------------------ kernel
    def _set_kernel(self, e: np.ndarray) -> None:
        e = np.asarray(e, dtype=float)
        if e.ndim != 1 or e.size == 0:
            raise ValueError(f"e must be a non-empty 1-D array, got shape {e.shape}")
        if not np.all(np.isfinite(e)):
            raise ValueError("e must be finite everywhere, got NaN or inf")
        gain = self.dt * float(e.sum())
        if self.normalize:
            if gain <= 0:
                raise ValueError(f"cannot normalise e with dt*sum(e) = {gain!r} <= 0")
            e = e / gain
            gain = 1.0
        self.gain_ = gain
        self._e = e
        self._k = e.size
        # reversed and scaled kernel so that y = window . _wrev with window oldest -> newest
        self._wrev = np.ascontiguousarray(e[::-1] * self.dt)

    @property
    def kernel(self) -> np.ndarray:
        """The E(t) samples in use (after normalisation), 1/s."""
        return self._e.copy()

    def history(self) -> np.ndarray:
        """The last K inputs, oldest first (``initial`` where the stream is shorter)."""
        return self._buf[self._pos : self._pos + self._k].copy()

    def set_kernel(self, e: np.ndarray) -> None:
        """Replace E(t) (e.g. an updated RTD estimate) keeping the input history.

        Inputs older than the kept history are taken as the oldest kept input (or ``initial``).
        The next outputs are those of the new kernel applied to the true past inputs as far as
        they are kept.
        """
        hist = self.history()
        self._set_kernel(e)
        k = self._k
        if hist.size >= k:
            window = hist[hist.size - k :]
        else:
            pad = hist[0] if hist.size else self.initial
            window = np.concatenate([np.full(k - hist.size, pad), hist])
        self._buf = np.concatenate([window, window])
        self._pos = 0

    # ------------------------------------------------------------------ streaming
    def push(self, u: float) -> float:
        """Append one inlet sample and return the outlet value y[n] of Eq. (1)."""
        u = float(u)
        if not np.isfinite(u):
            raise ValueError(f"u must be finite, got {u!r}")
        k = self._k
        buf = self._buf
        pos = self._pos
        # overwrite the oldest input (circular index pos) in both halves, advance the start
        buf[pos] = u
        buf[pos + k] = u
        pos += 1
        if pos == k:
            pos = 0
        self._pos = pos
        self.n_ += 1
        start = pos
        return float(np.dot(buf[start : start + k], self._wrev))

    @property
    def size(self) -> int:
        """K, the number of E(t) samples (and of inputs kept)."""
        return self._k

    def amend(self, lag: int, delta: float) -> None:
        """Add ``delta`` to the input pushed ``lag`` samples before the newest (0: the newest),
        e.g. a late contribution to a past inlet tick. The next outputs are those of the amended
        input history; outputs already returned are not revisited (they did not depend on it when
        e[0..lag] = 0)."""
        if not 0 <= lag < self._k:
            raise ValueError(f"lag must be in [0, {self._k}), got {lag!r}")
        if not np.isfinite(delta):
            raise ValueError(f"delta must be finite, got {delta!r}")
        i = (self._pos - 1 - lag) % self._k
        self._buf[i] += delta
        self._buf[i + self._k] += delta

    def push_many(self, u: np.ndarray) -> np.ndarray:
        """Append a block of inlet samples and return their outlet values (one ``numpy.convolve``)."""
        u = np.asarray(u, dtype=float)
        if u.ndim != 1:
            raise ValueError(f"u must be 1-D, got shape {u.shape}")
        if u.size == 0:
            return np.empty(0)
        if not np.all(np.isfinite(u)):
            raise ValueError("u must be finite, got NaN or inf")
        k = self._k
        hist = self.history()
        x = np.concatenate([hist[1:], u])  # the K-1 previous inputs then the block
        y = np.convolve(x, self._e, mode="valid") * self.dt
        window = x[x.size - k :]
        self._buf = np.concatenate([window, window])
        self._pos = 0
        self.n_ += u.size
        return y

    # ------------------------------------------------------------------ persistence
    def to_state(self) -> dict[str, Any]:
        """JSON-able state: enough to resume the stream exactly after a restart."""
        return {
            "e": self._e.tolist(),
            "dt": self.dt,
            "initial": self.initial,
            "history": self.history().tolist(),
            "n": self.n_,
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> StreamingConvolver:
        """Rebuild a convolver saved by :meth:`to_state` (the kernel is used as saved)."""
        obj = cls(np.asarray(state["e"]), float(state["dt"]), float(state["initial"]))
        hist = np.asarray(state["history"], dtype=float)
        if hist.size != obj._k:
            raise ValueError(f"history must have {obj._k} samples, got {hist.size}")
        obj._buf = np.concatenate([hist, hist])
        obj._pos = 0
        obj.n_ = int(state["n"])
        return obj
