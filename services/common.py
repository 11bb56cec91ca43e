"""Shared machinery of the live services: history-keeping publishers, history-fetching
subscribers, a single-threaded inbox, run-scoped state and an idempotent output log.

Delivery guarantees. Publishers are zenoh *advanced* publishers with a sample cache
(``LineSpec.history_samples`` per key) and ``CongestionControl.BLOCK``; subscribers
(:class:`HistoryFeed`) are advanced subscribers (live samples, recovery of missed ones) that
query every matching publisher's cache themselves when they (re)start and deliver each payload
once. A service restarted after a crash therefore receives everything its upstream published,
recomputes its state deterministically, and suppresses the outputs it had already published
(their ids are in an append-only log in the run's state directory): no output lost, none
duplicated.

Why not zenoh-ext's own ``HistoryConfig``: with eclipse-zenoh 1.10.2 an advanced subscriber on
a wildcard key that joins while several advanced publishers are live receives the history of
only some of them (measured: in 10 of 10 joins, 3-4 of 5 publishers delivered live samples
only), although a plain query of their caches returns every sample
(``tests/test_history_feed.py``).

Processing is serialised: zenoh callbacks validate (``services.bus.MessageValidator``: bad
JSON / schema counted and skipped) and, after the catch-up, handle the message right there under
one lock (no thread hand-off on the latency path); during the catch-up they queue.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh
import zenoh.ext as zext

from schemas import keys as keys_mod
from schemas.base import Message
from schemas.line import LineSpec
from services.bus import JSON, MessageValidator, Service

log = logging.getLogger(__name__)

#: environment variable naming the run's state directory (set by the supervisor)
STATE_ENV = "TWIN_STATE_DIR"


class HistoryPublisher:
    """Publishes messages of one model on one key with a history cache (zenoh advanced publisher)."""

    def __init__(
        self,
        svc: Service,
        key: str,
        model: type[Message] | None,
        cache_samples: int,
        express: bool = False,
    ) -> None:
        keys_mod.parse_key(key)
        self.key = key
        self.model = model
        self.counters = svc.counters
        self.seq = 0
        self._pub = zext.declare_advanced_publisher(
            svc.session,
            key,
            encoding=JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
            cache=zext.CacheConfig(max_samples=cache_samples),
            sample_miss_detection=zext.MissDetectionConfig(heartbeat=0.5),
            publisher_detection=True,
            express=express,
        )

    def publish(self, msg: Message | dict[str, Any]) -> Message:
        """Validate (dicts) and send; ``seq`` defaults to the publisher's counter."""
        if isinstance(msg, dict):
            if self.model is None:
                raise TypeError(f"publisher {self.key} has no model: pass a Message")
            data = dict(msg)
            data.setdefault("seq", self.seq)
            msg = self.model.model_validate(data)
        elif self.model is not None and not isinstance(msg, self.model):
            raise TypeError(
                f"message for {self.key} must be a {self.model.__name__}, got {type(msg).__name__}"
            )
        self._pub.put(msg.to_json_bytes())
        self.seq = msg.seq + 1
        self.counters.inc("published")
        return msg

    def put_raw(self, payload: bytes) -> None:
        """Send a pre-encoded JSON payload (replay of recorded bytes)."""
        self._pub.put(payload)
        self.counters.inc("published")

    def undeclare(self) -> None:
        self._pub.undeclare()


#: the advanced publishers' cache queryables live under ``<key>/@adv/pub/<zid>/<eid>/<meta>``
#: (zenoh-ext's advanced pub/sub wire protocol, shared by zenoh-c, -pico and -python)
CACHE_SUFFIX = "@adv/pub/**"


class HistoryFeed:
    """Live samples on ``key_expr`` plus the cached history of every matching advanced publisher,
    each payload delivered once to ``sink(key, payload)``.

    The live side is an advanced subscriber (sample-miss recovery on the publishers' heartbeat);
    the history side is one query of the publishers' caches (all queryables, no consolidation,
    replies on the samples' own keys). A payload seen on both sides (published while the
    query ran) is delivered once: payloads are remembered until ``dedup_s`` after the query has
    completed, then forgotten (bounded memory on long runs). History and live samples may
    interleave, so consumers that care order by plant time (the services' catch-up does).
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        sink: Callable[[str, bytes], None],
        *,
        timeout_s: float = 10.0,
        dedup_s: float = 5.0,
    ) -> None:
        self._sink = sink
        self._lock = threading.Lock()
        self._seen: set[tuple[str, bytes]] | None = set()
        self._done_at: float | None = None
        self.dedup_s = dedup_s
        self.history_complete = threading.Event()
        self.n_history = 0
        self.n_duplicates = 0
        self._sub = zext.declare_advanced_subscriber(
            session,
            key_expr,
            zenoh.handlers.Callback(self._on_live, lambda: None),
            recovery=zext.RecoveryConfig(heartbeat=True),
            subscriber_detection=True,
        )
        session.get(
            f"{key_expr}/{CACHE_SUFFIX}",
            zenoh.handlers.Callback(self._on_reply, self._on_history_done),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            accept_replies=zenoh.ReplyKeyExpr.ANY,
            timeout=timeout_s,
        )

    def _on_live(self, sample: zenoh.Sample) -> None:
        self._deliver(str(sample.key_expr), sample.payload.to_bytes(), history=False)

    def _on_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            s = reply.ok
            self._deliver(str(s.key_expr), s.payload.to_bytes(), history=True)

    def _on_history_done(self) -> None:
        with self._lock:
            self._done_at = time.monotonic()
        self.history_complete.set()

    def _deliver(self, key: str, payload: bytes, *, history: bool) -> None:
        with self._lock:
            if self._seen is not None:
                if (key, payload) in self._seen:
                    self.n_duplicates += 1
                    return
                self._seen.add((key, payload))
                if self._done_at is not None and time.monotonic() - self._done_at > self.dedup_s:
                    self._seen = None
            if history:
                self.n_history += 1
        self._sink(key, payload)

    def undeclare(self) -> None:
        self._sub.undeclare()


class HistorySubscriber:
    """Validating :class:`HistoryFeed` of one key expression into a service."""

    def __init__(
        self,
        svc: Service,
        key_expr: str,
        sink: Callable[[str, Any], None],
        *,
        model: type[Message] | None = None,
    ) -> None:
        # time order is restored by the service's catch-up sort and per-stream de-duplication:
        # history may arrive after the first live samples
        self.validator = MessageValidator(
            svc.counters, model=model, name=svc.name, check_time=False
        )
        self.counters = svc.counters
        self._sink = sink
        self.feed = HistoryFeed(svc.session, key_expr, self._on_payload)

    def _on_payload(self, key: str, payload: bytes) -> None:
        msg = self.validator.check(key, payload)
        if msg is None:
            return
        self.counters.inc("received")
        self._sink(key, msg)

    def undeclare(self) -> None:
        self.feed.undeclare()


class OutputLog:
    """Append-only log of output ids already published (idempotence across restarts)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self.done: set[str] = set()
        if path.exists():
            # a torn last line (crash mid-write) is ignored: that output is sent again
            lines = path.read_text().split("\n")
            self.done = {ln for ln in lines[:-1] if ln}
        self._f = path.open("a")

    def __contains__(self, output_id: str) -> bool:
        return output_id in self.done

    def add(self, output_id: str) -> None:
        self.done.add(output_id)
        self._f.write(output_id + "\n")
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def state_dir(spec: LineSpec) -> Path:
    """The run's state directory: ``$TWIN_STATE_DIR`` (set by ``twin up``) or ``spec.state_dir``."""
    return Path(os.environ.get(STATE_ENV) or spec.state_dir)


class LiveService(Service):
    """A service of the live twin: a :class:`services.bus.Service` plus an inbox processed in
    the main thread, history publishers/subscribers and the run's state directory.

    Subclasses implement :meth:`setup` (declare publishers/subscriptions), :meth:`handle`
    (one validated message) and optionally :meth:`idle` (called when the inbox has been empty
    for ``idle_s``) and :meth:`finish` (at shutdown).
    """

    idle_s: float = 0.2
    #: catch-up of a (re)started service: inputs (history and live) are collected for at least
    #: ``catchup_s``, until ``catchup_quiet_s`` without input or ``catchup_max_s``, then handled
    #: in plant-time order
    catchup_s: float = 1.0
    catchup_quiet_s: float = 0.3
    catchup_max_s: float = 10.0

    def __init__(self, name: str, spec: LineSpec, *, install_signal_handlers: bool = True):
        super().__init__(
            name,
            spec.client_bus(),
            health_period_s=1.0,
            install_signal_handlers=install_signal_handlers,
        )
        self.spec = spec
        self.inbox: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._hlock = threading.RLock()
        self._direct = False
        self._active = False
        self.state_path = state_dir(spec)

    # -- declarations ------------------------------------------------------------------------
    def history_publisher(self, key: str, model: type[Message] | None) -> HistoryPublisher:
        pub = HistoryPublisher(
            self, key, model, self.spec.history_samples, express=self.spec.express
        )
        self._entities.append(pub)
        return pub

    def history_subscribe(self, key_expr: str, model: type[Message] | None = None) -> None:
        sub = HistorySubscriber(self, key_expr, self._enqueue, model=model)
        self._entities.append(sub)

    def _enqueue(self, key: str, msg: Any) -> None:
        t = getattr(msg, "t", None)
        if t is not None and t > self.plant_time_s:
            self.plant_time_s = t
        if self._direct:
            with self._hlock:
                self._safe_handle(key, msg)
            return
        with self._hlock:
            if self._direct:
                self._safe_handle(key, msg)
            else:
                self.inbox.put((key, msg))

    def _safe_handle(self, key: str, msg: Any) -> None:
        self._active = True
        try:
            self.handle(key, msg)
        except Exception as exc:  # noqa: BLE001 - one bad message must not kill the service
            self.counters.inc("handler_errors")
            self.counters.last_error = f"{type(exc).__name__}: {exc}"[:500]
            log.exception("%s: handling %s failed", self.name, key)

    # -- lifecycle ---------------------------------------------------------------------------
    def setup(self) -> None:
        """Declare publishers and subscriptions (session open)."""

    def handle(self, key: str, msg: Any) -> None:
        """Process one validated message."""

    def idle(self) -> None:
        """Called when no message arrived for ``idle_s``."""

    def finish(self) -> None:
        """Called once at shutdown, before the session closes."""

    def run(self, timeout_s: float | None = None) -> int:
        """Catch up, then handle each message as it arrives, in the subscriber's callback under
        a lock (no thread hand-off on the latency path); call :meth:`idle` after ``idle_s``
        without input."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        self._catch_up()
        with self._hlock:
            while True:  # what arrived during the catch-up, then switch to direct handling
                try:
                    key, msg = self.inbox.get_nowait()
                except queue.Empty:
                    break
                self._safe_handle(key, msg)
            self._direct = True
        while not self.stop_flag.wait(self.idle_s):
            with self._hlock:
                if not self._active:
                    self.idle()
                self._active = False
            if deadline is not None and time.monotonic() >= deadline:
                break
        return 0

    def _catch_up(self) -> None:
        """Collect inputs (history and live) for at least ``catchup_s``, until the inbox has been
        quiet for ``catchup_quiet_s`` (history delivered) or ``catchup_max_s`` has passed, then
        handle them sorted by plant time."""
        t0 = time.monotonic()
        batch: list[tuple[float, int, str, Any]] = []
        while not self.stopping:
            now = time.monotonic()
            if now - t0 >= self.catchup_max_s:
                break
            wait = self.catchup_quiet_s
            if now - t0 < self.catchup_s:
                wait = max(wait, self.catchup_s - (now - t0))
            try:
                key, msg = self.inbox.get(timeout=wait)
            except queue.Empty:
                if time.monotonic() - t0 >= self.catchup_s:
                    break
                continue
            batch.append((float(getattr(msg, "t", 0.0)), len(batch), key, msg))
        batch.sort(key=lambda x: (x[0], x[1]))
        self.counters.inc("caught_up", len(batch))
        with self._hlock:
            for _, _, key, msg in batch:
                self._safe_handle(key, msg)

    def serve(self) -> int:
        """Open, set up, run until SIGINT/SIGTERM, finish and close."""
        with self:
            self.setup()
            try:
                return self.run()
            finally:
                self.finish()
