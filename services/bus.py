"""The twin's bus: zenoh sessions from :class:`schemas.bus_config.BusConfig`, the one publisher
class, typed and history-fetching subscribers, pings and the drain barrier.

:class:`Publisher` validates (a message must be an instance of the key's model; a dict is
validated into one) or sends pre-encoded payloads (replay), with ``CongestionControl.BLOCK`` so
that data is never dropped silently, and optionally keeps a history cache for late or restarted
subscribers. A subscriber never raises on bad input: bad JSON, a schema violation and time going
backwards (per key expression, i.e. per publisher) are logged with their reason, counted
(``rejected_json``, ``rejected_schema``, ``rejected_time``, ``rejected_unknown``) and skipped;
the counters are published in the service's health (``services.service.Service``).

Delivery guarantees of the history. Publishers with a history are zenoh *advanced* publishers
with a sample cache; :class:`HistoryFeed` subscribers are advanced subscribers (live samples,
recovery of missed ones) that query every matching publisher's cache themselves when they
(re)start and deliver each payload once. Why not zenoh-ext's own ``HistoryConfig``: with
eclipse-zenoh 1.10.2 an advanced subscriber on a wildcard key that joins while several advanced
publishers are live receives the history of only some of them (measured: in 10 of 10 joins, 3-4
of 5 publishers delivered live samples only), although a plain query of their caches returns
every sample (``tests/services/test_history_feed.py``).

Topology. Two processes on one host: one listens, the other connects (peer to peer). More
processes: one session in ``router`` mode (``twin router``) listens and the others connect to it
as ``client`` (zenoh 1.x peers with gossip off do not forward between the peers connected to
them; clients of a router or of a peer are routed).
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import zenoh
import zenoh.ext as zext
from pydantic import ValidationError

from schemas import keys as keys_mod
from schemas.base import Message
from schemas.bus_config import BusConfig
from schemas.messages import ServiceHealth

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON
#: rejection reasons (counter names): bad JSON, schema violation, time going backwards on a key,
#: a key without a model, a feed that does not match the line's configuration
REJECT_REASONS = (
    "rejected_json",
    "rejected_schema",
    "rejected_time",
    "rejected_unknown",
    "rejected_mismatch",
)


def read_password(config: BusConfig) -> str | None:
    """The password of ``config.usrpwd``'s user: from its ``password_file`` (which must be
    readable by its owner only) or its ``password_env`` variable; None without a user."""
    up = config.usrpwd
    if up is None or up.user is None:
        return None
    if up.password_env is not None:
        value = os.environ.get(up.password_env)
        if not value:
            raise ValueError(
                f"usrpwd.password_env names an unset environment variable, got {up.password_env!r}"
            )
        return value
    path = up.password_file
    try:
        mode = path.stat().st_mode
        text = path.read_text().strip()
    except OSError as exc:
        raise ValueError(f"usrpwd.password_file cannot be read, got {str(path)!r}: {exc}") from None
    if mode & 0o077:
        raise ValueError(
            f"usrpwd.password_file must be readable by its owner only (chmod 600), got mode "
            f"{oct(mode & 0o777)} for {str(path)!r}"
        )
    if not text:
        raise ValueError(f"usrpwd.password_file is empty, got {str(path)!r}")
    return text


def zenoh_config(config: BusConfig | None = None) -> zenoh.Config:
    """The zenoh ``Config`` of a :class:`BusConfig` (default: loopback peer, scouting off); the
    password comes from its file or variable (:func:`read_password`). A listener on another
    interface than loopback with neither TLS nor authentication is refused unless
    ``allow_insecure_listen``."""
    config = config or BusConfig()
    exposed = config.insecure_listeners()
    if exposed and not config.allow_insecure_listen:
        raise ValueError(
            "a listener beyond loopback needs TLS or user/password authentication (or "
            f"allow_insecure_listen: true), bus.listen: {', '.join(exposed)}"
        )
    if exposed:
        log.warning("listening without TLS or authentication on %s", ", ".join(exposed))
    cfg = config.to_zenoh_dict(password=read_password(config))
    return zenoh.Config.from_json5(json.dumps(cfg))


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

    def raise_to(self, name: str, value: int) -> None:
        """Set counter ``name`` to ``value`` if that is larger (a running maximum)."""
        with self._lock:
            self._values[name] = max(self._values.get(name, 0), value)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._values)

    def rejected(self) -> int:
        """Total rejected messages, all reasons."""
        snap = self.snapshot()
        return sum(snap.get(r, 0) for r in REJECT_REASONS)


class RateLimitedLog:
    """Warnings of one kind, rate-limited per reason: the first ``burst`` of a reason are logged,
    then at most one every ``period_s`` saying how many were not logged since (the counters
    hold every one)."""

    def __init__(
        self, logger: logging.Logger = log, *, burst: int = 5, period_s: float = 10.0
    ) -> None:
        self.logger = logger
        self.burst = burst
        self.period_s = period_s
        self._lock = threading.Lock()
        self._seen: dict[str, int] = {}
        self._quiet: dict[str, int] = {}
        self._last: dict[str, float] = {}

    def warn(self, reason: str, text: str) -> bool:
        """Log ``text`` for ``reason`` unless rate-limited; returns whether it was logged."""
        now = time.monotonic()
        with self._lock:
            n = self._seen.get(reason, 0) + 1
            self._seen[reason] = n
            if n > self.burst and now - self._last.get(reason, -math.inf) < self.period_s:
                self._quiet[reason] = self._quiet.get(reason, 0) + 1
                return False
            quiet = self._quiet.pop(reason, 0)
            self._last[reason] = now
        more = f" ({quiet} more {reason} not logged since the last one)" if quiet else ""
        self.logger.warning("%s%s", text, more)
        return True


class StreamOrder:
    """Per-key order of a stream of messages: each key's messages must come in increasing
    ``(t, seq)`` (one publisher per key). :meth:`check` says whether a message is ``new``, a
    ``duplicate`` (a position seen recently on its key: history delivered again, a restarted
    publisher sending again what it had sent) or ``backwards`` (older than the newest seen on
    its key and not a recent one: a clock reset, a second plant session on the same keys, a
    second publisher)."""

    def __init__(self, recent: int = 4096) -> None:
        self.recent = recent
        self._lock = threading.Lock()
        self.last: dict[str, tuple[float, int]] = {}
        self._seen: dict[str, set[tuple[float, int]]] = {}
        self._order: dict[str, deque[tuple[float, int]]] = {}

    def check(self, key: str, t: float, seq: int) -> Literal["new", "duplicate", "backwards"]:
        pos = (float(t), int(seq))
        with self._lock:
            seen = self._seen.setdefault(key, set())
            if pos in seen:
                return "duplicate"
            last = self.last.get(key)
            if last is not None and pos < last:
                return "backwards"
            self.last[key] = pos
            order = self._order.setdefault(key, deque())
            order.append(pos)
            seen.add(pos)
            if len(order) > self.recent:
                seen.discard(order.popleft())
            return "new"


class Publisher:
    """Publishes on one key: validated messages of one model, or pre-encoded JSON payloads.

    ``publish(msg)`` takes a model instance or a dict of its fields (``seq`` is filled in from
    the publisher's counter when missing) and returns the message sent; with ``check_time`` a
    message whose ``t`` is earlier than the previous one raises ValueError (subscribers would
    reject it). ``put_raw(payload)`` sends bytes as they are (replay of recorded bytes).

    With ``history`` (a number of samples) it is a zenoh advanced publisher keeping that many
    samples per key for late or restarted subscribers (:class:`HistoryFeed`), with publisher
    detection and sample-miss heartbeats; otherwise a plain publisher, whose matching
    subscribers :meth:`has_subscribers` reports.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        model: type[Message] | None = None,
        *,
        counters: Counters | None = None,
        history: int | None = None,
        express: bool = False,
        check_time: bool = True,
        congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.BLOCK,
    ) -> None:
        if model is not None:
            keys_mod.parse_key(key)
        self.key = key
        self.model = model
        self.counters = counters or Counters()
        self.check_time = check_time
        self.last_t: float | None = None
        self.seq = 0
        self.history = history
        if history is None:
            self._pub = session.declare_publisher(
                key, encoding=JSON, congestion_control=congestion_control, express=express
            )
        else:
            self._pub = zext.declare_advanced_publisher(
                session,
                key,
                encoding=JSON,
                congestion_control=congestion_control,
                cache=zext.CacheConfig(max_samples=history),
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
        if self.check_time and self.last_t is not None and msg.t < self.last_t:
            raise ValueError(
                f"t must not go backwards on {self.key}: got t={msg.t} after {self.last_t}"
            )
        self._pub.put(msg.to_json_bytes())
        self.last_t = msg.t
        self.seq = msg.seq + 1
        self.counters.inc("published")
        return msg

    def put_raw(self, payload: bytes) -> None:
        """Send a pre-encoded JSON payload (replay of recorded bytes)."""
        self._pub.put(payload)
        self.counters.inc("published")

    def has_subscribers(self) -> bool:
        """Whether a matching subscriber is known (zenoh matching status; plain publishers)."""
        if self.history is not None:
            raise TypeError(f"publisher {self.key} keeps a history: no matching status")
        return bool(self._pub.matching_status.matching)

    def undeclare(self) -> None:
        self._pub.undeclare()


def reject(counters: Counters, warnings: RateLimitedLog, reason: str, text: str) -> None:
    """Count a rejected message under ``reason``, keep ``text`` as the last error and log it
    (rate-limited per reason)."""
    counters.inc(reason)
    counters.last_error = text[:500]
    warnings.warn(reason, text)


class MessageValidator:
    """Decode and check payloads: JSON, schema (by key or fixed model), time order per key.

    ``check(key, payload)`` returns the message, or None after counting and logging (rate-limited,
    :class:`RateLimitedLog`) the reason.
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
        warnings: RateLimitedLog | None = None,
    ) -> None:
        self.counters = counters
        self.model = model
        self.check_time = check_time
        self.allow_unknown = allow_unknown
        self.name = name
        self.warnings = warnings or RateLimitedLog()
        self.order = StreamOrder()

    def _reject(self, reason: str, key: str, detail: str) -> None:
        reject(self.counters, self.warnings, reason, f"{self.name}: {reason} on {key}: {detail}")

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
        if self.check_time and not self.in_order(key, msg):
            return None
        return msg

    def in_order(self, key: str, msg: Message) -> bool:
        """Whether ``msg`` is new on its key (:class:`StreamOrder`): a duplicate is counted
        (``duplicates``) and dropped, a message going back in time is rejected
        (``rejected_time``)."""
        verdict = self.order.check(key, msg.t, msg.seq)
        if verdict == "new":
            return True
        if verdict == "duplicate":
            self.counters.inc("duplicates")
            return False
        t_last, seq_last = self.order.last[key]
        self._reject(
            "rejected_time",
            key,
            f"t went backwards: t={msg.t} seq={msg.seq} after t={t_last} seq={seq_last}",
        )
        return False


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
        warnings: RateLimitedLog | None = None,
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
            warnings=warnings,
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
            keys_mod.advanced_caches(key_expr),
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
    """Validating :class:`HistoryFeed` of one key expression: valid messages to
    ``sink(key, msg)`` (counted ``received``), the others counted and skipped."""

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        sink: Callable[[str, Any], None],
        *,
        counters: Counters,
        model: type[Message] | None = None,
        name: str = "subscriber",
        key_counts: Counters | None = None,
        warnings: RateLimitedLog | None = None,
    ) -> None:
        # time order is restored by the service's catch-up sort and checked after it
        # (``services.service.Service``): history may arrive after the first live samples
        self.validator = MessageValidator(
            counters, model=model, name=name, check_time=False, warnings=warnings
        )
        self.counters = counters
        self.key_counts = key_counts if key_counts is not None else Counters()
        self._sink = sink
        self.feed = HistoryFeed(session, key_expr, self._on_payload)

    def _on_payload(self, key: str, payload: bytes) -> None:
        self.key_counts.inc(key)
        msg = self.validator.check(key, payload)
        if msg is None:
            return
        self.counters.inc("received")
        self._sink(key, msg)

    def undeclare(self) -> None:
        self.feed.undeclare()


def live_services(session: zenoh.Session, line: str = "*", timeout_s: float = 1.0) -> list[str]:
    """Names of the services whose liveliness token is alive (``twin/<line>/service/<name>/alive``)."""
    names = []
    for reply in session.liveliness().get(keys_mod.services_alive(line), timeout=timeout_s):
        if reply.ok is not None:
            names.append(keys_mod.parse_key(str(reply.ok.key_expr)).id)
    return sorted(set(names))


def collect_health(
    session: zenoh.Session, line: str = "*", wait_s: float = 1.5
) -> tuple[list[str], dict[str, ServiceHealth]]:
    """The services whose liveliness token is alive, and the latest health each published
    within ``wait_s`` (health that does not validate is skipped)."""
    health: dict[str, ServiceHealth] = {}

    def on_health(sample: zenoh.Sample) -> None:
        try:
            h = ServiceHealth.model_validate_json(sample.payload.to_bytes())
        except ValueError:
            return
        health[h.service] = h

    sub = session.declare_subscriber(
        keys_mod.services_health(line), zenoh.handlers.Callback(on_health, lambda: None)
    )
    alive = live_services(session, line, timeout_s=wait_s)
    time.sleep(wait_s)
    sub.undeclare()
    return alive, health


class AlertFeed:
    """Every OOS alert of a line, and with ``divert`` every divert command, once each (history
    included, ``HistoryFeed``) to ``emit(key, message)``; :attr:`done` is set after ``count``
    alerts (0: never). :meth:`attach` moves the feed to another session (a tool reconnected to
    a restarted twin, :class:`TwinLink`): the new session's history is fetched and what was
    already emitted (by alert or command id) is not emitted again."""

    def __init__(
        self,
        session: zenoh.Session | None,
        line: str,
        emit: Callable[[str, Any], None],
        *,
        divert: bool = False,
        count: int = 0,
    ) -> None:
        self._emit = emit
        self._count = count
        self._line = line
        self._divert = divert
        self._seen: set[tuple[str, str]] = set()
        self._lock = threading.Lock()
        self.alerts = 0
        self.done = threading.Event()
        self._feeds: list[HistoryFeed] = []
        if session is not None:
            self.attach(session)

    def attach(self, session: zenoh.Session) -> None:
        """Follow the alerts (and divert commands) on ``session``, history included."""
        from schemas.messages import DivertCommand, OosAlert

        self.undeclare()
        feeds = [HistoryFeed(session, keys_mod.oos_alert(self._line), self._on(OosAlert, True))]
        if self._divert:
            key = keys_mod.divert_command(self._line)
            feeds.append(HistoryFeed(session, key, self._on(DivertCommand, False)))
        self._feeds = feeds

    def _on(self, model: type[Message], is_alert: bool) -> Callable[[str, bytes], None]:
        def cb(key: str, payload: bytes) -> None:
            try:
                msg = model.model_validate_json(payload)
            except ValueError as exc:
                log.warning("bad message on %s: %s", key, exc)
                return
            ident = msg.alert_id if is_alert else msg.command_id
            with self._lock:
                if (key, ident) in self._seen:
                    return
                self._seen.add((key, ident))
                self._emit(key, msg)
                if is_alert:
                    self.alerts += 1
                    if self._count and self.alerts >= self._count:
                        self.done.set()

        return cb

    def undeclare(self) -> None:
        feeds, self._feeds = self._feeds, []
        for f in feeds:
            try:
                f.undeclare()
            except zenoh.ZError as exc:  # a session already closed
                log.debug("undeclare: %s", exc)


class TwinLink:
    """A tool's link to the running twin of a line that survives restarts of the twin
    (``twin alerts``, ``twin record``, the dashboard).

    ``connect(config, again)`` opens the tool's session on ``config``, declares its
    subscriptions and returns the session and what closes it; ``again`` is true on a
    reconnection: fetch what was missed from the publishers' history (:class:`HistoryFeed`).
    ``config`` is ``services.security.tool_bus(spec, identity)``, read again at each connection:
    a new run of the twin has its own endpoints and credentials, found through the run's lock
    file. The link watches the twin: the supervisor's liveliness token
    (``twin/<line>/service/supervisor/alive``) and the run's lock file
    (``services.common.running_twin``). When the token goes, the lock is released or another
    run holds it, it says so at once in one line (``say``, stderr by default), closes the
    session and connects again as soon as a twin of the line answers, saying so too.
    """

    def __init__(
        self,
        spec: Any,
        identity: str,
        connect: Callable[[BusConfig, bool], tuple[zenoh.Session, Callable[[], None]]],
        *,
        name: str,
        say: Callable[[str], None] | None = None,
        poll_s: float = 0.5,
    ) -> None:
        self.spec = spec
        self.identity = identity
        self.name = name
        self.poll_s = poll_s
        self._connect_cb = connect
        self._say = say or (lambda text: print(text, file=sys.stderr, flush=True))
        self.session: zenoh.Session | None = None
        self._close: Callable[[], None] | None = None
        self._watch: Any = None
        #: run directory of the twin connected to (None: no lock file here, a twin elsewhere)
        self.run: str | None = None
        self.reconnects = 0
        self.lost = 0
        self._gone = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _config(self) -> tuple[BusConfig, str | None]:
        from services.common import running_twin
        from services.security import tool_bus

        info = running_twin(self.spec)
        return tool_bus(self.spec, self.identity), (info.run_dir if info else None)

    def _open(self, again: bool) -> None:
        config, run = self._config()
        session, close = self._connect_cb(config, again)
        try:
            self._gone.clear()
            self._watch = session.liveliness().declare_subscriber(
                keys_mod.service_alive(self.spec.name, "supervisor"),
                zenoh.handlers.Callback(self._on_token, lambda: None),
            )
        except BaseException:
            close()
            raise
        self.session, self._close, self.run = session, close, run

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self._gone.set()

    def open(self) -> TwinLink:
        """Connect (a RuntimeError naming the endpoints when no twin answers) and start
        watching the twin."""
        try:
            self._open(again=False)
        except zenoh.ZError:
            raise RuntimeError(
                f"no twin of line {self.spec.name} answers (is `twin up` running?), bus.connect: "
                f"{', '.join(self._config()[0].connect)}"
            ) from None
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-link", daemon=True)
        self._thread.start()
        return self

    def _disconnect(self) -> None:
        close, self._close, self.session = self._close, None, None
        if self._watch is not None:
            try:
                self._watch.undeclare()
            except zenoh.ZError as exc:
                log.debug("undeclare: %s", exc)
            self._watch = None
        if close is not None:
            close()

    def _lost_why(self, run: str | None) -> str | None:
        if self._gone.is_set():
            return "the supervisor's liveliness token is gone"
        if self.run is not None and run != self.run:
            return "its run ended" if run is None else f"another run holds the line: {run}"
        return None

    def _run(self) -> None:
        from services.common import running_twin

        line = self.spec.name
        while not self._stop.wait(self.poll_s):
            info = running_twin(self.spec)
            run = info.run_dir if info else None
            if self.session is not None:
                why = self._lost_why(run)
                if why is not None:
                    self.lost += 1
                    self._say(
                        f"{self.name}: lost the twin of line {line} ({why}); reconnecting when "
                        "it is back"
                    )
                    self._disconnect()
                continue
            if self.run is not None and run is None:
                continue  # the twin of this directory is down: wait for its lock
            try:
                self._open(again=True)
            except (zenoh.ZError, ValueError, OSError) as exc:
                log.debug("%s: reconnection failed: %s", self.name, exc)
                continue
            self.reconnects += 1
            where = f"run dir {self.run}" if self.run else ", ".join(self._config()[0].connect)
            self._say(
                f"{self.name}: reconnected to the twin of line {line} ({where}); what was "
                "missed comes from its history"
            )

    def close(self) -> None:
        """Stop watching and close the session."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._disconnect()


@dataclass
class PingReply:
    """A service's answer to a ping: its health and how many samples it got per key."""

    health: ServiceHealth
    key_counts: dict[str, int]


def ping(session: zenoh.Session, line: str = "*", timeout_s: float = 2.0) -> dict[str, PingReply]:
    """Ask every service (``twin/<line>/service/*/ping``) for its health and per-key
    sample counts; returns replies by service name."""
    replies = session.get(
        keys_mod.services_ping(line),
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
    """Wait until every service on the bus has processed what this session sent.

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
