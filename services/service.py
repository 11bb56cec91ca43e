"""The one base of every process on the twin's bus: :class:`Service`.

A service opens its zenoh session, declares a liveliness token
``twin/<line>/service/<name>/alive``, answers pings (health and per-key sample counts,
``services.bus.ping``), publishes :class:`~schemas.messages.ServiceHealth` every
``health_period_s`` on ``twin/<line>/service/<name>/health`` (its counters), and shuts down
cleanly on SIGINT/SIGTERM or :meth:`Service.stop` (health ``stopping``, token undeclared,
session closed). Use it as a context manager, or :meth:`Service.serve`.

A service of the live twin (built with ``spec=``, a :class:`~schemas.line.LineSpec`) declares
history publishers and subscribers (``services.bus``; the cache size and zenoh express from the
line) and keeps its restart state in the run's state directory. Its inputs are processed one at
a time: a (re)started service first collects its inputs (history and live) until the history
query of every subscription has completed (at most ``catchup_max_s``; health state
``starting`` meanwhile), handles them in plant-time order, then handles each message in the
subscriber's callback under one lock (no thread hand-off on the latency path). A service
restarted after a crash therefore receives everything its upstream published, recomputes its
state deterministically, and suppresses the outputs it had already published
(``services.common.OutputLog``).

Each input key's messages must come in increasing ``(t, seq)`` (``services.bus.StreamOrder``):
a message seen again (history, a restarted publisher) is counted in ``duplicates`` and dropped;
one going back in time on its key (a clock reset, a second plant session replayed into a running
twin, a second publisher) is rejected (``rejected_time``), logged (rate-limited) and puts the
service in the health state ``degraded`` for ``degraded_s``.

Subclasses implement :meth:`Service.setup` (declare publishers and subscriptions),
:meth:`Service.handle` (one validated message), and optionally :meth:`Service.idle` (no input
for ``idle_s``) and :meth:`Service.finish` (at shutdown).
"""

from __future__ import annotations

import gc
import heapq
import json
import logging
import math
import os
import queue
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from schemas import keys as keys_mod
from schemas.base import Message
from schemas.bus_config import BusConfig
from schemas.line import LineSpec
from schemas.messages import ServiceHealth
from services.bus import (
    JSON,
    Callback,
    Counters,
    HistorySubscriber,
    MessageValidator,
    Publisher,
    RateLimitedLog,
    StopFlag,
    TypedSubscriber,
    barrier,
    open_session,
)
from services.common import state_dir
from services.security import service_bus

log = logging.getLogger(__name__)


class Service:
    """A process on the twin's bus (see the module docstring).

    Args:
        name: the service's name (key segment of its health, token and ping).
        config: the bus session (default: with ``spec``, the line's client bus as the identity
            of the environment, ``services.security.service_bus``; else a loopback peer).
        spec: the line of a live-twin service: its client bus, history cache size, zenoh
            express, state directory.
        health_period_s: seconds between health reports (0: only at start and stop).
        install_signal_handlers: stop on SIGINT/SIGTERM (main thread only).
    """

    idle_s: float = 0.2
    #: catch-up of a (re)started service: inputs (history and live) are collected until every
    #: history query has completed, at most ``catchup_max_s``, then handled in plant-time order
    catchup_max_s: float = 10.0
    #: how long the health state stays ``degraded`` after a rejected message, s (wall)
    degraded_s: float = 10.0
    #: wall seconds each input is held before it is handled, in (plant time, key, seq) order, so
    #: that a message arriving up to that late behind messages of later plant time on other keys
    #: (another route, a sample recovered on a heartbeat) is still handled in plant-time order:
    #: the outputs do not depend on arrival order or machine load. 0: handled on arrival (the
    #: services on the diverter's latency path)
    reorder_s: float = 0.0

    def __init__(
        self,
        name: str,
        config: BusConfig | None = None,
        *,
        spec: LineSpec | None = None,
        health_period_s: float = 1.0,
        install_signal_handlers: bool = True,
    ) -> None:
        self.name = name
        self.spec = spec
        if config is None:
            config = service_bus(spec) if spec is not None else BusConfig()
        self.config = config
        self.line = self.config.line
        self.health_period_s = health_period_s
        self.counters = Counters()
        #: samples received per key (valid or not), reported to pings (see ``bus.barrier``)
        self.key_counts = Counters()
        self.stop_flag = StopFlag(install=install_signal_handlers)
        self.session: zenoh.Session | None = None
        self.plant_time_s = 0.0
        self.state = "starting"
        self.state_path = state_dir(spec) if spec is not None else Path.cwd()
        self.inbox: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self.warnings = RateLimitedLog(log)
        #: order of the history subscriptions' messages, per key (checked after the catch-up)
        self.order = MessageValidator(self.counters, name=name, warnings=self.warnings)
        self._feeds: list[HistorySubscriber] = []
        self._held: list[tuple[float, str, int, int, float, Any]] = []
        self._n_held = 0
        self._degraded_until = -math.inf
        #: why the service refuses its input (None: it does not), see :meth:`refuse`
        self.refusal: str | None = None
        self._hlock = threading.RLock()
        self._health_lock = threading.Lock()
        self._direct = False
        self._active = False
        self._t0 = time.monotonic()
        self._token: zenoh.LivelinessToken | None = None
        self._ping: zenoh.Queryable | None = None
        self._health_pub: Publisher | None = None
        self._health_thread: threading.Thread | None = None
        self._entities: list[Any] = []
        self._closed = False

    # -- lifecycle -------------------------------------------------------------------------
    def open(self) -> Service:
        self.session = open_session(self.config)
        try:
            self._token = self.session.liveliness().declare_token(
                keys_mod.service_alive(self.line, self.name)
            )
            self._ping = self.session.declare_queryable(
                keys_mod.service_ping(self.line, self.name), self._on_ping
            )
            self._health_pub = Publisher(
                self.session,
                keys_mod.service_health(self.line, self.name),
                ServiceHealth,
                counters=Counters(),
            )
            # a live-twin service is ``starting`` until its catch-up is done (:meth:`run`)
            self.state = "starting" if self.spec is not None else "running"
            self.publish_health()
            if self.health_period_s > 0:
                self._health_thread = threading.Thread(
                    target=self._health_loop, name=f"{self.name}-health", daemon=True
                )
                self._health_thread.start()
        except BaseException:
            self.session.close()
            raise
        return self

    def __enter__(self) -> Service:
        return self.open()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def stop(self) -> None:
        """Ask :meth:`run` to return (thread-safe; also what SIGINT/SIGTERM do)."""
        self.stop_flag.set()

    @property
    def stopping(self) -> bool:
        return self.stop_flag.is_set()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.stop_flag.set()
        self.state = "stopping"
        try:
            if self._health_thread is not None:
                self._health_thread.join(timeout=2.0)
            if self.session is not None and not self.session.is_closed():
                try:
                    self.publish_health()
                except Exception as exc:  # noqa: BLE001 - best effort at shutdown
                    log.debug("final health not sent: %s", exc)
                for entity in reversed(self._entities):
                    try:
                        entity.undeclare()
                    except Exception as exc:  # noqa: BLE001
                        log.debug("undeclare failed: %s", exc)
                if self._ping is not None:
                    self._ping.undeclare()
                if self._token is not None:
                    self._token.undeclare()
        finally:
            if self.session is not None:
                self.session.close()
            self.stop_flag.restore()

    def setup(self) -> None:
        """Declare publishers and subscriptions (session open)."""

    def handle(self, key: str, msg: Any) -> None:
        """Process one validated message of a history subscription."""

    def idle(self) -> None:
        """Called when no message arrived for ``idle_s``."""

    def caught_up(self) -> None:
        """Called once the catch-up's messages have been admitted (handled, unless
        ``reorder_s`` holds them), before the service reports ``running``, under the handling
        lock: what the history held is complete."""

    def finish(self) -> None:
        """Called once at shutdown, before the session closes."""

    def run(self, timeout_s: float | None = None) -> int:
        """Catch up, then handle each message as it arrives, in the subscriber's callback under
        a lock; call :meth:`idle` after ``idle_s`` without input; return at stop or timeout."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        self._catch_up()
        while not self.stop_flag.wait(self.idle_s):
            with self._hlock:
                self._release(time.monotonic())
                if not self._active:
                    self.idle()
                self._active = False
            if deadline is not None and time.monotonic() >= deadline:
                break
        return 0

    def serve(self) -> int:
        """Open, set up, run until SIGINT/SIGTERM, finish and close."""
        with self:
            self.setup()
            try:
                return self.run()
            finally:
                self.finish()

    # -- publishers and subscribers ----------------------------------------------------------
    def _require_session(self) -> zenoh.Session:
        if self.session is None:
            raise RuntimeError(f"service {self.name!r} is not open")
        return self.session

    def publisher(
        self, key: str, model: type[Message] | None = None, *, history: bool = False, **kwargs: Any
    ) -> Publisher:
        """A :class:`~services.bus.Publisher` counted in this service's health. ``history``:
        keep the line's ``history_samples`` per key for late or restarted subscribers (zenoh
        express as the line says; no time check: a history publisher may send out of order)."""
        if history:
            if self.spec is None:
                raise ValueError(f"service {self.name!r} has no line spec: no history publisher")
            kwargs = {
                "history": self.spec.history_samples,
                "express": self.spec.express,
                "check_time": False,
                **kwargs,
            }
        pub = Publisher(self._require_session(), key, model, counters=self.counters, **kwargs)
        self._entities.append(pub)
        return pub

    def subscribe(
        self,
        key_expr: str,
        callback: Callback,
        *,
        model: type[Message] | None = None,
        check_time: bool = True,
        allow_unknown: bool = False,
        with_payload: bool = False,
    ) -> TypedSubscriber:
        """Live typed subscription, ``callback`` in zenoh's thread (see
        :class:`~services.bus.TypedSubscriber`). Time order is checked per key. The callback
        also advances :attr:`plant_time_s` (reported in health)."""

        def wrapped(key: str, msg: Any, *payload: bytes) -> None:
            self._advance(msg)
            callback(key, msg, *payload)

        sub = TypedSubscriber(
            self._require_session(),
            key_expr,
            wrapped,
            model=model,
            counters=self.counters,
            check_time=check_time,
            allow_unknown=allow_unknown,
            name=self.name,
            with_payload=with_payload,
            key_counts=self.key_counts,
            warnings=self.warnings,
        )
        self._entities.append(sub)
        return sub

    def history_subscribe(self, key_expr: str, model: type[Message] | None = None) -> None:
        """Subscribe with history (:class:`~services.bus.HistorySubscriber`): every message goes
        through :meth:`handle`, in plant-time order after the catch-up."""
        sub = HistorySubscriber(
            self._require_session(),
            key_expr,
            self._enqueue,
            counters=self.counters,
            model=model,
            name=self.name,
            key_counts=self.key_counts,
            warnings=self.warnings,
        )
        self._entities.append(sub)
        self._feeds.append(sub)

    def _advance(self, msg: Any) -> None:
        t = getattr(msg, "t", None)
        if t is not None and t > self.plant_time_s:
            self.plant_time_s = t

    def _enqueue(self, key: str, msg: Any) -> None:
        self._advance(msg)
        if self._direct:
            with self._hlock:
                self._admit(key, msg)
            return
        with self._hlock:
            if self._direct:
                self._admit(key, msg)
            else:
                self.inbox.put((key, msg))

    def _admit(self, key: str, msg: Any) -> None:
        """Handle a message that is new on its key (duplicates dropped, time going backwards
        rejected: ``services.bus.MessageValidator.in_order``), after ``reorder_s``."""
        if not self.order.in_order(key, msg):
            if self.counters.get("rejected_time"):
                self._degraded_until = time.monotonic() + self.degraded_s
            return
        if self.reorder_s <= 0:
            self._safe_handle(key, msg)
            return
        now = time.monotonic()
        self._n_held += 1
        heapq.heappush(self._held, (float(msg.t), key, int(msg.seq), self._n_held, now, msg))
        self._release(now)

    def _release(self, now: float) -> None:
        """Handle the held messages that have waited ``reorder_s``, in plant-time order (one
        that has not waited long enough holds back those of later plant time)."""
        held = self._held
        while held and now - held[0][4] >= self.reorder_s:
            _, key, _, _, _, msg = heapq.heappop(held)
            self._safe_handle(key, msg)

    def _safe_handle(self, key: str, msg: Any) -> None:
        self._active = True
        try:
            self.handle(key, msg)
        except Exception as exc:  # noqa: BLE001 - one bad message must not kill the service
            self.counters.inc("handler_errors")
            self.counters.last_error = f"{type(exc).__name__}: {exc}"[:500]
            log.exception("%s: handling %s failed", self.name, key)

    def _history_complete(self, deadline: float) -> bool:
        """Wait until every history query has completed (or the deadline, or a stop)."""
        for sub in self._feeds:
            while not sub.feed.history_complete.wait(0.05):
                if self.stopping or time.monotonic() >= deadline:
                    return False
        return True

    def _catch_up(self) -> None:
        """Collect inputs (history and live) until every history query has completed (at most
        ``catchup_max_s``), then handle them sorted by plant time (key and ``seq`` break ties,
        so the order does not depend on arrival) and switch to direct handling."""
        self.state = "starting"
        if not self._history_complete(time.monotonic() + self.catchup_max_s):
            if not self.stopping:
                self.counters.inc("catchup_timeouts")
                log.warning(
                    "%s: history incomplete after %.0f s; going on with what came",
                    self.name,
                    self.catchup_max_s,
                )
        with self._hlock:
            batch: list[tuple[float, str, int, Any]] = []
            while True:
                try:
                    key, msg = self.inbox.get_nowait()
                except queue.Empty:
                    break
                batch.append((float(getattr(msg, "t", 0.0)), key, int(getattr(msg, "seq", 0)), msg))
            batch.sort(key=lambda x: x[:3])
            self.counters.inc("caught_up", len(batch))
            for _, key, _, msg in batch:
                self._admit(key, msg)
            self.caught_up()
            self._freeze_heap()
            self._direct = True
            self.state = "running"
        self.publish_health()  # the end of the catch-up, at once

    #: the cyclic garbage collector's generation-0 threshold once running (CPython's default is
    #: 700 allocations: with a large heap of long-lived objects a collection every few
    #: messages; the older generations are rare and, after :meth:`_freeze_heap`, small)
    gc_threshold0: int = 20_000

    def _freeze_heap(self) -> None:
        """After the start-up and catch-up: collect once, then move every object alive (modules,
        numba and pydantic machinery, the recomputed state) to the collector's permanent
        generation and raise the generation-0 threshold, so that later collections scan only
        what the running service allocates (a full collection of the diverter's start-up heap,
        ~84 000 objects, took 160-460 ms on the loaded 2-core machine, after the freeze
        < 0.01 ms)."""
        gc.collect()
        gc.freeze()
        _, g1, g2 = gc.get_threshold()
        gc.set_threshold(self.gc_threshold0, g1, g2)

    def refuse(self, reason: str) -> None:
        """The service refuses its input for ``reason``: logged as an error, its health is
        ``degraded`` with the reason as its last error from now on."""
        if self.refusal is None:
            self.refusal = reason
            log.error("%s: %s", self.name, reason)

    # -- health ----------------------------------------------------------------------------
    def health(self) -> ServiceHealth:
        assert self._health_pub is not None
        state = self.state
        if state == "running" and (self.refusal or time.monotonic() < self._degraded_until):
            state = "degraded"
        return ServiceHealth(
            t=self.plant_time_s,
            seq=self._health_pub.seq,
            service=self.name,
            state=state,
            pid=os.getpid(),
            uptime_s=time.monotonic() - self._t0,
            wall_time_unix_s=time.time(),
            counters=self.counters.snapshot(),
            last_error=(self.refusal or self.counters.last_error or "")[:500] or None,
        )

    def drain(self, timeout_s: float = 10.0, **kwargs: Any) -> list[ServiceHealth]:
        """Wait until every service on the bus processed what this one sent (see
        ``services.bus.barrier``); call before closing after a burst of publications."""
        kwargs.setdefault("line", self.line if self.spec is not None else "*")
        return barrier(self._require_session(), timeout_s=timeout_s, **kwargs)

    def _on_ping(self, query: zenoh.Query) -> None:
        try:
            payload = {
                "health": self.health().model_dump(mode="json"),
                "key_counts": self.key_counts.snapshot(),
            }
            query.reply(
                keys_mod.service_ping(self.line, self.name),
                json.dumps(payload).encode(),
                encoding=JSON,
            )
        except Exception as exc:  # noqa: BLE001 - a ping must not kill the receive path
            log.warning("ping reply failed: %s", exc)

    def publish_health(self) -> ServiceHealth:
        assert self._health_pub is not None
        with self._health_lock:  # the health thread and the catch-up's end
            return self._health_pub.publish(self.health())

    def _health_loop(self) -> None:
        while not self.stop_flag.wait(self.health_period_s):
            try:
                self.publish_health()
            except Exception as exc:  # noqa: BLE001 - health must not kill the service
                log.warning("health publish failed: %s", exc)
