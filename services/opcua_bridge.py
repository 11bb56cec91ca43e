"""``twin bridge opcua``: the twin's way in from a line's OPC UA server (PLC, SCADA, PAT
manager), and its diverter's way out to the gate.

:class:`OpcuaBridge` opens an asyncua client session (security from ``BRIDGE.yaml``) and one
subscription with a monitored item per mapped node (data-change trigger status/value/timestamp:
every stamped update is reported, not polled), and hands each notification ``(node, source
timestamp, value)`` to ``twin_core.plant.opcua_map.MessageAssembler``, which converts units,
refuses NaN / wrong types / out-of-range values (counted by reason), assembles one message per
unit and plant time and finds gaps. Messages go on the twin's bus as the ``plant`` identity
(history publishers: late or restarted services fetch them); a gap is marked by a ``note``
``Event`` on ``keys.event(line, "plant", "opcua")`` and by the unit's sequence number skipping
the missed samples (what the close-loop's data-quality step reads as missing data).

Reconnection: a session that fails (server restart, network cut: no keep-alive answer, a
failed publish) is closed and opened again every ``reconnect_s`` until it succeeds, the
subscription made anew; samples the server stamped in between and no longer holds are missed,
counted (``samples_missed``) and marked as above; ``reconnects`` counts the sessions reopened.

Writes: with a ``diverter`` node, the bridge subscribes to ``twin/<line>/divert/command`` and
writes the JSON of each ``DivertCommand`` to the node, once per command id. Only commands of
the twin's diverter are written: the bridge writes only on a secured twin bus (the router's
access control lets the ``oos`` identity alone publish there, ``services.security``; a forged
command is dropped by the router and never reaches the bridge) and over a signed and encrypted
OPC UA session; either missing refuses to start unless ``insecure`` (``--insecure``, logged as
a warning).

Time: each notification is handed over with its receive time; a value stamped ahead of the
plant clock (the other units' latest stamps, advanced at real time) by more than
``future_tolerance_s`` is held and refused as soon as its node reports an earlier stamp
(``future``, ``twin_core.plant.opcua_map``), logged rate-limited (``services.bus.RateLimitedLog``).

Logging: nothing per update at INFO. asyncua logs each publish answer (every notification in
it) at INFO, 10.8 MB per 30 min of plant time: its loggers are set to WARNING unless the
process logs at DEBUG (:func:`quiet_opcua_stack`); the bridge logs a summary of its counters
every :data:`SUMMARY_PERIOD_S` while they change.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from schemas import keys
from schemas.bus_config import BusConfig
from schemas.messages import DivertCommand
from schemas.opcua import BridgeConfig
from services.bus import Counters, RateLimitedLog
from services.service import Service
from twin_core.plant.opcua_map import Gap, MessageAssembler, gap_event, plant_time_s

log = logging.getLogger(__name__)

#: history samples a bridge's publishers keep for late or restarted services
HISTORY = 20000
#: the server state is read this often; no answer within the timeout is a lost session (a
#: closed connection fails at once; a busy client must not be taken for a dead server)
LIVENESS_PERIOD_S = 0.5
LIVENESS_TIMEOUT_S = 10.0
#: an OPC UA request's timeout (a publish answer of many notifications on a loaded machine
#: took more than asyncua's default 4 s)
REQUEST_TIMEOUT_S = 30.0
#: queue of one monitored item on the server between two publishes
QUEUE_SIZE = 1000
#: wall seconds between two summaries of the counters in the log (INFO)
SUMMARY_PERIOD_S = 60.0
#: the counters a summary names, in this order
SUMMARY_COUNTERS = (
    "samples",
    "published",
    "future",
    "future_held",
    "late",
    "dropped",
    "samples_missed",
    "rejected_nan",
    "rejected_type",
    "rejected_range",
    "rejected_status",
    "divert_written",
    "divert_failed",
)


def quiet_opcua_stack() -> None:
    """asyncua logs every publish answer, every notification in it, and each server write at
    INFO: its loggers log WARNING and above unless this process logs at DEBUG (``twin -v``)."""
    if not logging.getLogger().isEnabledFor(logging.DEBUG):
        logging.getLogger("asyncua").setLevel(logging.WARNING)


def refusal(config: BridgeConfig, bus: BusConfig, insecure: bool) -> str | None:
    """Why the bridge must not write to the gate, or None: writing needs a secured twin bus
    (user/password: the router's access control) and a signed and encrypted OPC UA session."""
    if config.diverter is None or insecure:
        return None
    if bus.usrpwd is None or bus.usrpwd.user is None:
        return (
            "the twin's bus is not secured (no user/password), so divert commands could be forged"
        )
    if not config.security.secured:
        return (
            f"the OPC UA session is not signed and encrypted (security.policy "
            f"{config.security.policy!r}, mode {config.security.mode!r})"
        )
    return None


def _password(config: BridgeConfig) -> str | None:
    sec = config.security
    if sec.password_file is not None:
        return Path(sec.password_file).read_text().strip()
    if sec.password_env is not None:
        value = os.environ.get(sec.password_env)
        if value is None:
            raise ValueError(f"security.password_env {sec.password_env!r} is not set")
        return value
    return None


class OpcuaBridge:
    """One OPC UA session feeding one twin's bus (module docstring). Use as a context manager
    (opens the bus, starts the OPC UA loop in its own thread) or :meth:`serve`."""

    def __init__(
        self,
        config: BridgeConfig,
        bus: BusConfig | None,
        *,
        spec: Any = None,
        insecure: bool = False,
        name: str = "plant",
        install_signal_handlers: bool = False,
    ) -> None:
        # bus None: a supervised service's bus, from its environment (services.service)
        self.svc = Service(name, bus, spec=spec, install_signal_handlers=install_signal_handlers)
        why = refusal(config, self.svc.config, insecure)
        if why is not None:
            self.svc.stop_flag.restore()
            raise ValueError(f"refusing to write divert commands, {why} (--insecure writes anyway)")
        if insecure and config.diverter is not None:
            log.warning("bridge: writing divert commands without security (--insecure)")
        quiet_opcua_stack()
        self.config = config
        self.assembler = MessageAssembler(config)
        self.counters: Counters = self.svc.counters
        self.warnings = RateLimitedLog(log)
        self._summary_at = time.monotonic()
        self._summary_last: dict[str, int] = {}
        self._lock = threading.Lock()
        self._pubs: dict[str, Any] = {}
        self._gap_pub: Any = None
        self._gap_seq = 0
        self._eos_pub: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._client: Client | None = None
        self._written: set[str] = set()
        self.connected = threading.Event()
        self.on_publish: Any = None

    # -- bus side --------------------------------------------------------------------------------
    def __enter__(self) -> OpcuaBridge:
        svc = self.svc.open()
        svc.state = "running"
        history = self.svc.spec is not None
        try:
            for unit in self.assembler.units:
                self._pubs[unit.key] = svc.publisher(unit.key, history=history)
            self._gap_pub = svc.publisher(
                keys.event(self.config.line, "plant", "opcua"), history=history
            )
            if self.config.diverter is not None:
                # commands are not in plant-time order (an alert's final command can follow a
                # later window's early one): deduplicated by command id, not ordered by t
                svc.subscribe(
                    keys.divert_command(self.config.line),
                    self._on_divert,
                    model=DivertCommand,
                    check_time=False,
                )
        except BaseException:
            svc.close()
            raise
        self._thread = threading.Thread(target=self._run_loop, name="opcua", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        self.svc.stop()
        if self._loop is not None:
            self._loop.call_soon_threadsafe(lambda: None)
        if self._thread is not None:
            self._thread.join(timeout=10)
        with self._lock:
            self._account(self.assembler.flush)
        self.svc.close()

    def serve(self) -> int:
        """Run until SIGINT/SIGTERM (or :meth:`Service.stop`)."""
        with self:
            while not self.svc.stop_flag.wait(1.0):
                pass
        return 0

    def _emit(self, messages: list, gaps: list[Gap]) -> None:
        for gap in gaps:
            log.warning(
                "bridge: %s missed %d samples (%.3f-%.3f s)",
                gap.unit,
                gap.n_missed,
                gap.t_before_s,
                gap.t_after_s,
            )
            self._gap_pub.publish(gap_event(gap, self._gap_seq))
            self._gap_seq += 1
            self.counters.inc("gaps")
        for key, msg in messages:
            self._pubs[key].publish(msg)
            self.svc._advance(msg)
            if self.on_publish is not None:
                self.on_publish(key, msg)

    def end_of_stream(self) -> None:
        """The plant's end of stream (``END_OF_STREAM`` on ``keys.replay_event``) at the last
        plant time published: the twin's diverter then closes what is open (a demo or test
        that serves a finite recording)."""
        from schemas.messages import END_OF_STREAM, Event

        if self._eos_pub is None:
            self._eos_pub = self.svc.publisher(
                keys.replay_event(self.config.line), history=self.svc.spec is not None
            )
        self._eos_pub.publish(
            Event(
                t=self.svc.plant_time_s, seq=0, kind="note", source="replay", detail=END_OF_STREAM
            )
        )

    def sample(self, node_id: str, source: Any, value: Any) -> None:
        """One OPC UA notification (also the entry point of tests), received now."""
        t = plant_time_s(source, self.config.epoch_utc) if source is not None else float("nan")
        with self._lock:
            self._account(self.assembler.add, node_id, t, value, time.monotonic())

    def tick(self) -> None:
        """Time passes: release what the plant clock has reached; a summary when it is due."""
        with self._lock:
            self._account(self.assembler.tick, time.monotonic())
        self._summary()

    def _account(self, step: Any, *args: Any) -> None:
        """One assembler step: its counters into the service's, its refusals logged, its
        messages published (under the lock)."""
        before = dict(self.assembler.counters)
        out = step(*args)
        for name, n in self.assembler.counters.items():
            if n > before.get(name, 0):
                self.counters.inc(name, n - before.get(name, 0))
        for f in self.assembler.refused:
            self.warnings.warn(
                "future",
                f"bridge: {f.unit} value of {f.node_id} stamped {f.t_s:.3f} s refused: ahead "
                f"of the plant clock by more than {self.config.future_tolerance_s:g} s ({f.why})",
            )
        self.assembler.refused.clear()
        self._emit(*out)

    def _summary(self) -> None:
        """Every :data:`SUMMARY_PERIOD_S`, one INFO line of the counters, if they changed."""
        now = time.monotonic()
        if now - self._summary_at < SUMMARY_PERIOD_S:
            return
        self._summary_at = now
        snap = self.counters.snapshot()
        if snap == self._summary_last:
            return
        self._summary_last = snap
        text = ", ".join(f"{k} {snap[k]}" for k in SUMMARY_COUNTERS if snap.get(k))
        log.info("bridge: %s (totals)", text or "no samples")

    def _on_divert(self, key: str, cmd: DivertCommand) -> None:
        if cmd.command_id in self._written or self._loop is None:
            self.counters.inc("divert_repeated")
            return
        self._written.add(cmd.command_id)
        asyncio.run_coroutine_threadsafe(self._write(cmd), self._loop)

    async def _write(self, cmd: DivertCommand) -> None:
        try:
            node = self._client.get_node(self.config.diverter.node_id)
            await node.write_value(
                ua.DataValue(ua.Variant(cmd.model_dump_json(), ua.VariantType.String))
            )
            self.counters.inc("divert_written")
        except Exception as exc:  # noqa: BLE001 - counted and logged; the next command retries
            self.counters.inc("divert_failed")
            self._written.discard(cmd.command_id)
            log.error("bridge: divert command %s not written: %s", cmd.command_id, exc)

    # -- OPC UA side -----------------------------------------------------------------------------
    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        dv = data.monitored_item.Value
        if not dv.StatusCode.is_good():
            self.counters.inc("rejected_status")
            return
        self.sample(node.nodeid.to_string(), dv.SourceTimestamp, val)

    def status_change_notification(self, status: Any) -> None:
        log.warning("bridge: subscription status %s", status)

    def _run_loop(self) -> None:
        self._loop = asyncio.new_event_loop()
        try:
            self._loop.run_until_complete(self._sessions())
        finally:
            self._loop.close()

    async def _client_session(self) -> Client:
        cfg = self.config
        # asyncua's own watchdog probes the server with min(session timeout / 2, interval): 1 s
        # by default, which a loaded machine missed (a needless reconnect, samples lost)
        client = Client(
            cfg.endpoint, timeout=REQUEST_TIMEOUT_S, watchdog_intervall=LIVENESS_TIMEOUT_S
        )
        client.session_timeout = 60000
        sec = cfg.security
        if sec.policy == "Basic256Sha256":
            mode = getattr(ua.MessageSecurityMode, sec.mode)
            await client.set_security(
                SecurityPolicyBasic256Sha256,
                str(sec.certificate),
                str(sec.private_key),
                server_certificate=None
                if sec.server_certificate is None
                else str(sec.server_certificate),
                mode=mode,
            )
        if sec.user is not None:
            client.set_user(sec.user)
            client.set_password(_password(cfg))
        await client.connect()
        return client

    async def _subscribe(self, client: Client) -> None:
        sub = await client.create_subscription(self.config.publishing_interval_ms, self)
        nodes = [client.get_node(n) for n in self.assembler.node_ids()]
        flt = ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValueTimestamp)
        handles = await sub._subscribe(nodes, mfilter=flt, queuesize=QUEUE_SIZE)
        bad = [
            n for n, h in zip(self.assembler.node_ids(), handles) if isinstance(h, ua.StatusCode)
        ]
        if bad:
            raise ValueError(f"the OPC UA server refused to monitor nodes {bad}")

    async def _sessions(self) -> None:
        first = True
        while not self.svc.stopping:
            try:
                self._client = await self._client_session()
                await self._subscribe(self._client)
                if not first:
                    self.counters.inc("reconnects")
                    log.warning("bridge: reconnected to %s", self.config.endpoint)
                first = False
                self.counters.inc("sessions")
                self.connected.set()
                while not self.svc.stopping:
                    await asyncio.sleep(LIVENESS_PERIOD_S)
                    await asyncio.wait_for(
                        self._client.nodes.server_state.read_value(), LIVENESS_TIMEOUT_S
                    )
                    self.tick()
            except ValueError:
                raise
            except Exception as exc:  # noqa: BLE001 - any failure of the session: reconnect
                self.connected.clear()
                self.counters.inc("connection_lost" if not first else "connect_failed")
                log.warning(
                    "bridge: OPC UA session to %s lost or refused: %s", self.config.endpoint, exc
                )
            finally:
                if self._client is not None:
                    try:
                        await asyncio.wait_for(self._client.disconnect(), 2)
                    except Exception:  # noqa: BLE001 - the connection is gone already
                        pass
            if not self.svc.stopping:
                await asyncio.sleep(self.config.reconnect_s)

    def health(self) -> dict[str, int]:
        return self.counters.snapshot()


def bridge_service(spec: Any, **kwargs: Any) -> OpcuaBridge:
    """The bridge as a service of ``twin up`` (``services: [bridge]``, ``opcua_bridge:
    BRIDGE.yaml``): identity ``bridge`` (the router lets it publish what the plant may), its
    bus from the supervisor's environment, divert commands written under the same rules."""
    config = BridgeConfig.from_file(spec.opcua_bridge)
    if config.line != spec.name:
        raise ValueError(f"line must be the twin's, got {config.line!r} for {spec.name!r}")
    return OpcuaBridge(
        config, None, spec=spec, name="bridge", install_signal_handlers=True, **kwargs
    )


def wait_for(predicate: Any, timeout_s: float, step_s: float = 0.02) -> bool:
    """Poll ``predicate`` until true or ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step_s)
    return bool(predicate())
