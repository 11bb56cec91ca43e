"""The twin's bus: zenoh sessions from :class:`schemas.bus_config.BusConfig`, typed publish and
subscribe, and the :class:`Service` helper every service process builds on.

Typed publishing validates (a message must be an instance of the key's model; a dict is validated
into one) and uses ``CongestionControl.BLOCK`` so that data is never dropped silently. A typed
subscriber never raises on bad input: bad JSON, a schema violation and time going backwards
(per key expression, i.e. per publisher) are logged with their reason, counted
(``rejected_json``, ``rejected_schema``, ``rejected_time``, ``rejected_unknown``) and skipped; the
counters are published in the service's health.

Topology. Two processes on one host: one listens, the other connects (peer to peer). More
processes: one session in ``router`` mode (``twin router``) listens and the others connect to it
as ``client`` (zenoh 1.x peers with gossip off do not forward between the peers connected to
them; clients of a router or of a peer are routed).

Minimal service::

    from schemas import keys
    from schemas.messages import FeederFlow, MeasuredConcentration
    from services.bus import Service

    with Service("doubler", BusConfig.loopback(7447, listen=False)) as svc:
        pub = svc.publisher(keys.key("line1", "x", "out", id="y"), MeasuredConcentration)
        svc.subscribe("twin/line1/feeder/*/flow", lambda key, msg: ..., model=FeederFlow)
        svc.run()  # until SIGINT/SIGTERM or svc.stop()
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh
from pydantic import ValidationError

from schemas import keys as keys_mod
from schemas.base import Message
from schemas.bus_config import BusConfig
from schemas.messages import ServiceHealth

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON
#: rejection reasons (counter names)
REJECT_REASONS = ("rejected_json", "rejected_schema", "rejected_time", "rejected_unknown")


def zenoh_config(config: BusConfig | None = None) -> zenoh.Config:
    """The zenoh ``Config`` of a :class:`BusConfig` (default: loopback peer, scouting off)."""
    config = config or BusConfig()
    return zenoh.Config.from_json5(json.dumps(config.to_zenoh_dict()))


def free_port() -> int:
    """A free TCP port on the loopback interface (for a router of tests, demos, benchmarks)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def open_session(config: BusConfig | None = None) -> zenoh.Session:
    """Open a zenoh session. Close it (``with`` or ``close()``): a session with Python callback
    subscribers otherwise keeps its process alive."""
    return zenoh.open(zenoh_config(config))


class Counters:
    """Thread-safe named counters (exposed in :class:`ServiceHealth`)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._values: dict[str, int] = {}
        self.last_error: str | None = None

    def inc(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._values[name] = self._values.get(name, 0) + n

    def get(self, name: str) -> int:
        with self._lock:
            return self._values.get(name, 0)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._values)

    def rejected(self) -> int:
        """Total rejected messages, all reasons."""
        snap = self.snapshot()
        return sum(snap.get(r, 0) for r in REJECT_REASONS)


class TypedPublisher:
    """Publishes validated messages of one model on one key expression.

    ``publish(msg)`` takes a model instance or a dict of its fields (``seq`` is filled in from
    the publisher's counter when missing) and returns the message sent. A message whose ``t`` is
    earlier than the previous one raises ValueError (subscribers would reject it), unless
    ``check_time=False``.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        model: type[Message],
        *,
        counters: Counters | None = None,
        congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.BLOCK,
        express: bool = False,
        check_time: bool = True,
    ) -> None:
        keys_mod.parse_key(key)
        self.key = key
        self.model = model
        self.counters = counters or Counters()
        self.check_time = check_time
        self.last_t: float | None = None
        self.seq = 0
        self._pub = session.declare_publisher(
            key, encoding=JSON, congestion_control=congestion_control, express=express
        )

    def publish(self, msg: Message | dict[str, Any]) -> Message:
        if isinstance(msg, dict):
            data = dict(msg)
            data.setdefault("seq", self.seq)
            msg = self.model.model_validate(data)
        elif not isinstance(msg, self.model):
            raise TypeError(
                f"message for {self.key} must be a {self.model.__name__}, got {type(msg).__name__}"
            )
        if self.check_time and self.last_t is not None and msg.t < self.last_t:
            raise ValueError(
                f"t must not go backwards on {self.key}: got t={msg.t} after {self.last_t}"
            )
        self._pub.put(msg.to_json_bytes())
        self.last_t = msg.t
        self.seq = msg.seq + 1
        self.counters.inc("published")
        return msg

    def has_subscribers(self) -> bool:
        """Whether a matching subscriber is known (zenoh matching status)."""
        return bool(self._pub.matching_status.matching)

    def undeclare(self) -> None:
        self._pub.undeclare()


class RawPublisher:
    """Publishes pre-encoded JSON payloads on one key (replay: bytes sent as recorded)."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        *,
        congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.BLOCK,
    ) -> None:
        self.key = key
        self._pub = session.declare_publisher(
            key, encoding=JSON, congestion_control=congestion_control
        )

    def put(self, payload: bytes) -> None:
        self._pub.put(payload)

    def has_subscribers(self) -> bool:
        """Whether a matching subscriber is known (zenoh matching status)."""
        return bool(self._pub.matching_status.matching)

    def undeclare(self) -> None:
        self._pub.undeclare()


class MessageValidator:
    """Decode and check payloads: JSON, schema (by key or fixed model), time order per key.

    ``check(key, payload)`` returns the message, or None after counting and logging the reason.
    With ``model=None`` the model is looked up from the key's signal; an unknown signal is
    rejected (``rejected_unknown``) unless ``allow_unknown`` is set, in which case any JSON
    object passes and is returned as a dict.
    """

    def __init__(
        self,
        counters: Counters,
        *,
        model: type[Message] | None = None,
        check_time: bool = True,
        allow_unknown: bool = False,
        name: str = "subscriber",
        log_first: int = 20,
    ) -> None:
        self.counters = counters
        self.model = model
        self.check_time = check_time
        self.allow_unknown = allow_unknown
        self.name = name
        self.log_first = log_first
        self.last_t: dict[str, float] = {}
        self._lock = threading.Lock()
        self._logged = 0

    def _reject(self, reason: str, key: str, detail: str) -> None:
        self.counters.inc(reason)
        text = f"{self.name}: {reason} on {key}: {detail}"
        self.counters.last_error = text[:500]
        if self._logged < self.log_first:
            log.warning("%s", text)
            self._logged += 1
            if self._logged == self.log_first:
                log.warning("%s: further rejections are counted, not logged", self.name)

    def check(self, key: str, payload: bytes) -> Message | dict[str, Any] | None:
        model = self.model or keys_mod.model_for_key(key)
        if model is None:
            if not self.allow_unknown:
                self._reject("rejected_unknown", key, "no message model for this key")
                return None
            try:
                data = json.loads(payload)
            except (ValueError, UnicodeDecodeError) as exc:
                self._reject("rejected_json", key, f"bad JSON: {exc}")
                return None
            if not isinstance(data, dict):
                self._reject("rejected_schema", key, f"payload must be a JSON object, got {data!r}")
                return None
            return data
        try:
            msg = model.model_validate_json(payload)
        except ValidationError as exc:
            errors = exc.errors(include_url=False)
            reason = (
                "rejected_json"
                if any(e["type"] == "json_invalid" for e in errors)
                else "rejected_schema"
            )
            detail = "; ".join(
                f"{'.'.join(str(p) for p in e['loc']) or '<payload>'}: {e['msg']} "
                f"(got {e.get('input')!r:.80})"
                for e in errors[:5]
            )
            self._reject(reason, key, f"{model.__name__}: {detail}")
            return None
        if self.check_time:
            with self._lock:
                last = self.last_t.get(key)
                if last is not None and msg.t < last:
                    self._reject(
                        "rejected_time", key, f"t went backwards: t={msg.t} < previous {last}"
                    )
                    return None
                self.last_t[key] = msg.t
        return msg


Callback = Callable[..., None]


class TypedSubscriber:
    """Subscribes to a key expression, validates every sample and calls ``callback(key, msg)``
    for the valid ones (zenoh's callback thread; ``callback(key, msg, payload_bytes)`` with
    ``with_payload=True``). Invalid samples are counted, logged, skipped;
    an exception in ``callback`` is counted (``callback_errors``) and logged, never propagated."""

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        callback: Callback,
        *,
        model: type[Message] | None = None,
        counters: Counters | None = None,
        check_time: bool = True,
        allow_unknown: bool = False,
        name: str = "subscriber",
        with_payload: bool = False,
        key_counts: Counters | None = None,
    ) -> None:
        self.key_expr = key_expr
        self.with_payload = with_payload
        self.key_counts = key_counts if key_counts is not None else Counters()
        self.counters = counters or Counters()
        self.validator = MessageValidator(
            self.counters,
            model=model,
            check_time=check_time,
            allow_unknown=allow_unknown,
            name=name,
        )
        self._callback = callback
        self._sub = session.declare_subscriber(
            key_expr, zenoh.handlers.Callback(self._on_sample, self._on_drop)
        )

    def _on_drop(self) -> None:
        pass

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        self.key_counts.inc(key)
        payload = sample.payload.to_bytes()
        msg = self.validator.check(key, payload)
        if msg is None:
            return
        self.counters.inc("received")
        try:
            if self.with_payload:
                self._callback(key, msg, payload)
            else:
                self._callback(key, msg)
        except Exception:  # noqa: BLE001 - a consumer bug must not kill the zenoh thread
            self.counters.inc("callback_errors")
            log.exception("callback for %s failed", key)

    def undeclare(self) -> None:
        self._sub.undeclare()


def live_services(session: zenoh.Session, line: str = "*", timeout_s: float = 1.0) -> list[str]:
    """Names of the services whose liveliness token is alive (``twin/<line>/service/<name>/alive``)."""
    names = []
    for reply in session.liveliness().get(f"twin/{line}/service/*/alive", timeout=timeout_s):
        if reply.ok is not None:
            names.append(keys_mod.parse_key(str(reply.ok.key_expr)).id)
    return sorted(set(names))


@dataclass
class PingReply:
    """A service's answer to a ping: its health and how many samples it got per key."""

    health: ServiceHealth
    key_counts: dict[str, int]


def ping(session: zenoh.Session, line: str = "*", timeout_s: float = 2.0) -> dict[str, PingReply]:
    """Ask every :class:`Service` (``twin/<line>/service/*/ping``) for its health and per-key
    sample counts; returns replies by service name."""
    replies = session.get(
        f"twin/{line}/service/*/ping",
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        congestion_control=zenoh.CongestionControl.BLOCK,
        priority=zenoh.Priority.DATA,
        timeout=timeout_s,
    )
    out: dict[str, PingReply] = {}
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            data = json.loads(reply.ok.payload.to_bytes())
            health = ServiceHealth.model_validate(data["health"])
            counts = {str(k): int(v) for k, v in data["key_counts"].items()}
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("bad ping reply from %s: %s", reply.ok.key_expr, exc)
            continue
        out[health.service] = PingReply(health, counts)
    return out


def barrier(
    session: zenoh.Session,
    line: str = "*",
    timeout_s: float = 10.0,
    *,
    sent: dict[str, int] | None = None,
    baseline: dict[str, PingReply] | None = None,
    quiet_s: float = 0.1,
) -> list[ServiceHealth]:
    """Wait until every :class:`Service` on the bus has processed what this session sent.

    A closing zenoh session drops what is still queued, so a burst must be drained first.
    The services are pinged repeatedly (``quiet_s`` apart); the barrier returns when two
    successive replies show the same per-key sample counts (quiescence) and, if ``sent``
    (key -> messages sent since ``baseline``, a :func:`ping` taken before sending) is given,
    every service that got any message of a sent key since the baseline got all of them, and
    every service that answered the baseline answers again (or has stopped: its liveliness
    token is gone).
    Returns the services' health; on timeout, logs a warning and returns the last replies.
    """
    deadline = time.monotonic() + timeout_s
    prev: dict[str, dict[str, int]] | None = None
    base = baseline or {}
    replies: dict[str, PingReply] = {}
    while True:
        remaining = deadline - time.monotonic()
        replies = ping(session, line, max(0.5, min(5.0, remaining)))
        snapshot = {name: r.key_counts for name, r in replies.items()}
        complete = True
        for name, r in replies.items():
            got_before = base[name].key_counts if name in base else {}
            for key, n in (sent or {}).items():
                got = r.key_counts.get(key, 0) - got_before.get(key, 0)
                if 0 < got < n:
                    complete = False
        missing = set(base) - set(replies)
        if complete and missing:
            # a service of the baseline that did not answer must have stopped (token gone)
            alive = set(live_services(session, line, timeout_s=min(2.0, max(0.2, remaining))))
            complete = not (missing & alive)
        if complete and snapshot == prev:
            return [r.health for r in replies.values()]
        if time.monotonic() >= deadline:
            log.warning("barrier: timed out after %.1f s; last counts %s", timeout_s, snapshot)
            return [r.health for r in replies.values()]
        prev = snapshot
        time.sleep(quiet_s)


class StopFlag:
    """A stop event set by SIGINT/SIGTERM (handlers installed from the main thread only)."""

    def __init__(self, install: bool = True) -> None:
        self.event = threading.Event()
        self.signal: int | None = None
        self._previous: dict[int, Any] = {}
        if install and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handler)

    def _handler(self, signum: int, frame: Any) -> None:
        self.signal = signum
        self.event.set()

    def set(self) -> None:
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        return self.event.wait(timeout)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()


class Service:
    """Base/helper of a twin service process.

    Opens the session, declares a liveliness token ``twin/<line>/service/<name>/alive``,
    publishes :class:`ServiceHealth` every ``health_period_s`` on
    ``twin/<line>/service/<name>/health`` (counters of all its publishers and subscribers),
    and shuts down cleanly on SIGINT/SIGTERM or :meth:`stop` (health ``stopping``, token
    undeclared, session closed). Use as a context manager; :meth:`run` blocks until stopped.
    Subclasses may override :meth:`step` (called every ``step_period_s`` by :meth:`run`).
    """

    step_period_s: float = 0.1

    def __init__(
        self,
        name: str,
        config: BusConfig | None = None,
        *,
        health_period_s: float = 1.0,
        install_signal_handlers: bool = True,
    ) -> None:
        self.name = name
        self.config = config or BusConfig()
        self.line = self.config.line
        self.health_period_s = health_period_s
        self.counters = Counters()
        #: samples received per key (valid or not), reported to pings (see :func:`barrier`)
        self.key_counts = Counters()
        self.stop_flag = StopFlag(install=install_signal_handlers)
        self.session: zenoh.Session | None = None
        self.plant_time_s = 0.0
        self.state = "starting"
        self._t0 = time.monotonic()
        self._token: zenoh.LivelinessToken | None = None
        self._ping: zenoh.Queryable | None = None
        self._health_pub: TypedPublisher | None = None
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
                keys_mod.key(self.line, "service", "ping", self.name), self._on_ping
            )
            self._health_pub = TypedPublisher(
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

    def run(self, timeout_s: float | None = None) -> int:
        """Call :meth:`step` periodically until stopped (signal, :meth:`stop`, or timeout)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self.stop_flag.wait(self.step_period_s):
            self.step()
            if deadline is not None and time.monotonic() >= deadline:
                break
        return 0

    def step(self) -> None:
        """Periodic work of a subclass (default: nothing)."""

    # -- pub/sub ---------------------------------------------------------------------------
    def _require_session(self) -> zenoh.Session:
        if self.session is None:
            raise RuntimeError(f"service {self.name!r} is not open")
        return self.session

    def publisher(self, key: str, model: type[Message], **kwargs: Any) -> TypedPublisher:
        pub = TypedPublisher(self._require_session(), key, model, counters=self.counters, **kwargs)
        self._entities.append(pub)
        return pub

    def raw_publisher(self, key: str) -> RawPublisher:
        pub = RawPublisher(self._require_session(), key)
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
        """Typed subscription; see :class:`TypedSubscriber`. Time order is checked per key.

        The callback also advances :attr:`plant_time_s` (reported in health)."""

        def wrapped(key: str, msg: Any, *payload: bytes) -> None:
            t = getattr(msg, "t", None)
            if t is not None and t > self.plant_time_s:
                self.plant_time_s = t
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

    # -- health ----------------------------------------------------------------------------
    def health(self) -> ServiceHealth:
        assert self._health_pub is not None
        state = self.state
        return ServiceHealth(
            t=self.plant_time_s,
            seq=self._health_pub.seq,
            service=self.name,
            state=state,
            pid=os.getpid(),
            uptime_s=time.monotonic() - self._t0,
            wall_time_unix_s=time.time(),
            counters=self.counters.snapshot(),
            last_error=self.counters.last_error,
        )

    def drain(self, timeout_s: float = 10.0, **kwargs: Any) -> list[ServiceHealth]:
        """Wait until every service on the bus processed what this one sent (see
        :func:`barrier`); call before closing after a burst of publications."""
        return barrier(self._require_session(), timeout_s=timeout_s, **kwargs)

    def _on_ping(self, query: zenoh.Query) -> None:
        try:
            payload = {
                "health": self.health().model_dump(mode="json"),
                "key_counts": self.key_counts.snapshot(),
            }
            query.reply(
                keys_mod.key(self.line, "service", "ping", self.name),
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
