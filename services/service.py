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
a time: a (re)started service first collects its inputs (history and live) for at least
``catchup_s``, until ``catchup_quiet_s`` without input or ``catchup_max_s``, handles them in
plant-time order, then handles each message in the subscriber's callback under one lock (no
thread hand-off on the latency path). A service restarted after a crash therefore receives
everything its upstream published, recomputes its state deterministically, and suppresses the
outputs it had already published (``services.common.OutputLog``).

Subclasses implement :meth:`Service.setup` (declare publishers and subscriptions),
:meth:`Service.handle` (one validated message), and optionally :meth:`Service.idle` (no input
for ``idle_s``) and :meth:`Service.finish` (at shutdown).
"""

from __future__ import annotations

import json
import logging
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
    Publisher,
    StopFlag,
    TypedSubscriber,
    barrier,
    open_session,
)
from services.common import state_dir

log = logging.getLogger(__name__)


class Service:
    """A process on the twin's bus (see the module docstring).

    Args:
        name: the service's name (key segment of its health, token and ping).
        config: the bus session (default: loopback peer); ignored with ``spec``.
        spec: the line of a live-twin service: its client bus, history cache size, zenoh
            express, state directory.
        health_period_s: seconds between health reports (0: only at start and stop).
        install_signal_handlers: stop on SIGINT/SIGTERM (main thread only).
    """

    idle_s: float = 0.2
    #: catch-up of a (re)started service: inputs (history and live) are collected for at least
    #: ``catchup_s``, until ``catchup_quiet_s`` without input or ``catchup_max_s``, then handled
    #: in plant-time order
    catchup_s: float = 1.0
    catchup_quiet_s: float = 0.3
    catchup_max_s: float = 10.0

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
        self.config = spec.client_bus() if spec is not None else (config or BusConfig())
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
        self._hlock = threading.RLock()
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
            self.state = "running"
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

    def finish(self) -> None:
        """Called once at shutdown, before the session closes."""

    def run(self, timeout_s: float | None = None) -> int:
        """Catch up, then handle each message as it arrives, in the subscriber's callback under
        a lock; call :meth:`idle` after ``idle_s`` without input; return at stop or timeout."""
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
        )
        self._entities.append(sub)

    def _advance(self, msg: Any) -> None:
        t = getattr(msg, "t", None)
        if t is not None and t > self.plant_time_s:
            self.plant_time_s = t

    def _enqueue(self, key: str, msg: Any) -> None:
        self._advance(msg)
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

    # -- health ----------------------------------------------------------------------------
    def health(self) -> ServiceHealth:
        assert self._health_pub is not None
        return ServiceHealth(
            t=self.plant_time_s,
            seq=self._health_pub.seq,
            service=self.name,
            state=self.state,
            pid=os.getpid(),
            uptime_s=time.monotonic() - self._t0,
            wall_time_unix_s=time.time(),
            counters=self.counters.snapshot(),
            last_error=self.counters.last_error,
        )

    def drain(self, timeout_s: float = 10.0, **kwargs: Any) -> list[ServiceHealth]:
        """Wait until every service on the bus processed what this one sent (see
        ``services.bus.barrier``); call before closing after a burst of publications."""
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
        return self._health_pub.publish(self.health())

    def _health_loop(self) -> None:
        while not self.stop_flag.wait(self.health_period_s):
            try:
                self.publish_health()
            except Exception as exc:  # noqa: BLE001 - health must not kill the service
                log.warning("health publish failed: %s", exc)
