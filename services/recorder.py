"""Recorder service: everything on the line's bus (``twin/<line>/**``) to an MCAP file.

Thin shell over ``services.recording.McapRecorder``: each valid message is written with its
payload bytes as received, on the channel of its key, ``log_time`` = its plant time. Invalid
payloads are counted (``services.bus.MessageValidator``) and not written; a message already
recorded (its key, ``t`` and ``seq`` seen again: history delivered twice, a restarted publisher
sending a tick again) is counted (``duplicates``) and not written again; one going back in time
on its key is recorded (it was on the bus), counted (``out_of_order``) and logged (rate-limited).
The file is
``LineSpec.record_path`` (relative paths under the run directory), flushed periodically so a
crash loses at most the last unflushed chunk, and finalized on SIGINT/SIGTERM.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from schemas import keys
from schemas.line import LineSpec
from services.bus import HistoryFeed, MessageValidator
from services.service import Service


class RecorderService(Service):
    """See the module docstring."""

    def __init__(self, spec: LineSpec, path: str | Path | None = None, **kwargs: Any) -> None:
        super().__init__("recorder", spec=spec, **kwargs)
        p = Path(path or spec.record_path or "twin-live.mcap")
        self.path = p if p.is_absolute() else self.state_path / p
        self._lock = threading.Lock()
        self.rec: Any = None

    def setup(self) -> None:
        from services.recording import McapRecorder

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = McapRecorder(self.path, flush_every=2000, flush_period_s=1.0)
        self.validator = MessageValidator(
            self.counters, name=self.name, check_time=False, warnings=self.warnings
        )
        self._sub = HistoryFeed(self.session, keys.everything(self.spec.name), self._on_payload)
        self._entities.append(self._sub)

    def _on_payload(self, key: str, payload: bytes) -> None:
        if keys.is_service_key(key):
            return  # health and liveliness are not plant data
        msg = self.validator.check(key, payload)
        if msg is None:
            return
        verdict = self.validator.order.check(key, msg.t, msg.seq)
        if verdict == "duplicate":
            self.counters.inc("duplicates")
            return
        if verdict == "backwards":
            self.counters.inc("out_of_order")
            self.warnings.warn("out_of_order", f"recorder: t went backwards on {key}: t={msg.t}")
        with self._lock:
            if self.rec is not None:
                self.rec.write(key, payload, float(msg.t), model=type(msg))
                self.counters.inc("recorded")

    def idle(self) -> None:
        with self._lock:
            if self.rec is not None:
                self.rec.flush()

    def finish(self) -> None:
        with self._lock:
            if self.rec is not None:
                self.rec.close()
                self.rec = None
