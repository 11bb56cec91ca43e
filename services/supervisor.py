"""Supervisor of the live twin (``twin up``): router, service processes, restarts, clean stop.

:class:`Supervisor` hosts the zenoh router (``LineSpec.bus``, ``mode: router``) in its own
process, starts each configured service as a separate interpreter
(``python -m services.runner NAME``; no fork of a process with zenoh open), watches the
processes and their liveliness tokens (``twin/<line>/service/<name>/alive``), kills a service
whose token has been gone for ``liveliness_timeout_s`` while its process runs (hung, or cut off
from the router), restarts a service that exits with exponential backoff (``backoff_s``
doubling up to ``max_backoff_s``, reset after ``stable_s`` of uptime), and on :meth:`stop`
(SIGINT/SIGTERM in ``twin up``) sends SIGTERM to all, waits ``stop_timeout_s``, kills what
remains and closes the router.

Secure by default (``secure=True``, ``services.security``): per-run credentials for every
service and tool, the router accepting only them, and an access control where each identity
publishes only its own outputs (the diverter alone its alerts and divert commands, the plant
alone the plant inputs). ``secure=False`` (``twin up --insecure``) is the open bus.

One twin per line and state directory: the run lock ``<state_dir>/twin-<line>.lock``
(``services.common.RunLock``, released by the kernel if ``twin up`` dies) holds the run's
:class:`~services.common.RunInfo` for the tools. :meth:`start` refuses, with a one-line
RuntimeError, a second ``twin up`` of the line, a router endpoint already in use, and service
processes of an earlier run still running. No service outlives its supervisor: a service dies
with it (``services.runner``: Linux parent-death signal, and a watch of its parent process as a
fallback), and every service is started, and stopped, by the supervisor's watcher thread (the
parent-death signal follows the thread that started a process).

Each ``twin up`` gets a fresh run directory ``<state_dir>/run-<time>-<pid>`` (``$TWIN_STATE_DIR``
of the services: restart state and output logs; ``<name>.log``: each service's output;
``<name>.pid``: its process; ``line.json``: the configuration, no password).

The supervisor keeps the run's audit trail (``services.audit``, key ``<state_dir>/audit.key``):
the trail's start and the configuration loaded (its SHA-256), every service start, exit,
restart and kill, and from the bus every alert, divert command, close-loop finding (and its
data-quality findings), model switch of the blender and rise of a service's rejection
counters; on :meth:`stop` the services but the recorder stop first, then ``trail_end`` is
recorded and the recorder stopped, so a recording of a run that ended cleanly ends its trail.
"""

from __future__ import annotations

import hashlib
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from schemas import keys
from schemas.audit import AuditRecord
from schemas.bus_config import BusConfig
from schemas.closeloop import ModelFinding
from schemas.line import LineSpec
from schemas.messages import BlenderModelInUse, DivertCommand, OosAlert, ServiceHealth
from services.audit import AUDIT_KEY_FILE, AuditTrail, load_or_create_key
from services.bus import Publisher, open_session
from services.common import (
    STATE_ENV,
    RunInfo,
    RunLock,
    live_service_processes,
    lock_path,
    write_pid,
)
from services.runner import SUPERVISOR_PID_ENV
from services.security import (
    PASSWORD_ENV,
    PASSWORD_FILE_ENV,
    TOOL_IDENTITIES,
    USER_ENV,
    RouterDictionary,
    RunCredentials,
    as_identity,
    secured_router,
)

log = logging.getLogger(__name__)

SUPERVISED = (
    "feeder",
    "blender",
    "rtd",
    "oos",
    "recorder",
    "dem",
    "closeloop",
    "bridge",
    "trace",
)


@dataclass
class Child:
    """One supervised service process."""

    name: str
    proc: subprocess.Popen | None = None
    started_at: float = 0.0
    seen_alive: bool = False
    lost_since: float | None = None
    restarts: int = 0
    backoff_s: float = 0.0
    next_start: float = 0.0
    exit_codes: list[int] = field(default_factory=list)


def busy_endpoints(endpoints: list[str]) -> list[str]:
    """The TCP endpoints (``tcp/<host>:<port>``) on which a listener cannot bind now.

    Bound as the router binds (``SO_REUSEADDR``): a port that only has connections of a stopped
    run in TIME_WAIT is free; a port another process listens on is busy."""
    busy = []
    for ep in endpoints:
        proto, _, addr = ep.partition("/")
        if proto not in ("tcp", "tls"):
            continue
        host, _, port = addr.rpartition(":")
        host = host.strip("[]")
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((host, int(port)))
            except OSError:
                busy.append(ep)
    return busy


class Supervisor:
    """Starts, watches and stops the services of a line (see the module docstring)."""

    def __init__(
        self,
        spec: LineSpec,
        *,
        services: list[str] | None = None,
        run_dir: Path | None = None,
        secure: bool = True,
        backoff_s: float = 0.5,
        max_backoff_s: float = 10.0,
        stable_s: float = 30.0,
        liveliness_timeout_s: float = 15.0,
        stop_timeout_s: float = 5.0,
        log_level: str = "INFO",
    ) -> None:
        self.spec = spec
        names = [s for s in (services if services is not None else spec.services) if s != "plant"]
        for s in names:
            if s not in SUPERVISED:
                raise ValueError(f"services must be among {SUPERVISED}, got {s!r}")
        self.names = names
        stamp = time.strftime("%Y%m%dT%H%M%S")
        self.run_dir = run_dir or Path(spec.state_dir) / f"run-{stamp}-{os.getpid()}"
        self.secure = secure
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self.stable_s = stable_s
        self.liveliness_timeout_s = liveliness_timeout_s
        self.stop_timeout_s = stop_timeout_s
        self.log_level = log_level
        self.children = {n: Child(n) for n in names}
        self.alive: set[str] = set()
        #: held while the router's session is replaced (:meth:`restart_router`)
        self._router_lock = threading.Lock()
        self._recheck = False
        self.session: zenoh.Session | None = None
        self.creds: RunCredentials | None = None
        self._dictionary: RouterDictionary | None = None
        self._lock_file = RunLock(lock_path(spec))
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._liveliness: Any = None
        self.codes: dict[str, int | None] = {}
        self.config_path = self.run_dir / "line.json"
        self.trail: AuditTrail | None = None
        self._audit_pub: Publisher | None = None
        self._audit_subs: list[Any] = []
        #: rejection counters of each service last seen (their rises are recorded)
        self._rejected: dict[str, dict[str, int]] = {}

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> Supervisor:
        """Take the run lock, check the endpoints and earlier services, open the router and
        start the services; a one-line RuntimeError says why it cannot."""
        spec = self.spec
        info = RunInfo(
            os.getpid(), str(self.run_dir), spec.name, list(spec.bus.listen), self.secure
        )
        self._lock_file.acquire(info)
        try:
            self._check_free()
            self.run_dir.mkdir(parents=True, exist_ok=True)
            spec.to_file(self.config_path)
            key = load_or_create_key(Path(spec.state_dir) / AUDIT_KEY_FILE)
            self.trail = AuditTrail(
                key, self.run_dir.name, self._publish_audit, self.run_dir / "audit.jsonl"
            )
            self._open_router()
        except BaseException:
            self._close_security()
            self._lock_file.release()
            raise
        self.trail.append(
            "supervisor",
            "trail_start",
            self.run_dir.name,
            f"line {spec.name}, services {', '.join(self.names)}, "
            f"{'secured bus' if self.secure else 'insecure bus (--insecure)'}, pid {os.getpid()}",
        )
        digest = hashlib.sha256(self.config_path.read_bytes()).hexdigest()
        self.trail.append("supervisor", "config_loaded", "line.json", f"sha256 {digest}")
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._watch, name="supervisor", daemon=True)
        self._thread.start()
        return self

    def _check_free(self) -> None:
        old = live_service_processes(Path(self.spec.state_dir), self.spec.name)
        if old:
            pids = " ".join(str(p) for p in sorted(old))
            raise RuntimeError(
                f"services of an earlier run still run, pids {pids} ({sorted(old.values())[0]}"
                f"{' ...' if len(old) > 1 else ''}); stop them first (kill {pids})"
            )
        busy = busy_endpoints(list(self.spec.bus.listen))
        if busy:
            raise RuntimeError(
                f"the router's endpoint is in use (another twin or program), bus.listen: "
                f"{', '.join(busy)}"
            )

    def _open_router(self) -> None:
        if self.secure:
            identities = [*self.names, *TOOL_IDENTITIES]
            self.creds = RunCredentials.generate(identities)
            self.creds.write_tool_files(self.run_dir)
            self._dictionary = RouterDictionary(self.creds, self.run_dir)
        self._open_router_session()
        if self._dictionary is not None:
            self._dictionary.router_opened()

    def _open_router_session(self) -> None:
        """The router's session (with this run's credentials and access control), the
        supervisor's liveliness subscriber, token and health publisher on it."""
        spec = self.spec
        bus = spec.router_bus()
        if self.secure:
            identities = [*self.names, *TOOL_IDENTITIES]
            bus = secured_router(bus, spec, identities, self._dictionary.path)
        try:
            self.session = open_session(bus)
        except zenoh.ZError as exc:
            raise RuntimeError(
                f"cannot open the router, bus.listen: {', '.join(spec.bus.listen)}: {exc}"
            ) from None
        self._liveliness = self.session.liveliness().declare_subscriber(
            keys.services_alive(spec.name),
            zenoh.handlers.Callback(self._on_alive, lambda: None),
            history=True,
        )
        self._token = self.session.liveliness().declare_token(
            keys.service_alive(spec.name, "supervisor")
        )
        self._health = Publisher(
            self.session, keys.service_health(spec.name, "supervisor"), ServiceHealth
        )
        self._audit_pub = Publisher(
            self.session,
            keys.audit_record(spec.name),
            AuditRecord,
            history=spec.history_samples,
            check_time=False,
        )
        watched = {
            keys.oos_alert(spec.name): self._on_alert,
            keys.divert_command(spec.name): self._on_divert,
            keys.model_finding(spec.name): self._on_finding,
            keys.blender_model_in_use(spec.name): self._on_model,
            keys.services_health(spec.name): self._on_health,
        }
        self._audit_subs = [
            self.session.declare_subscriber(
                k, zenoh.handlers.Callback(self._audited(f), lambda: None)
            )
            for k, f in watched.items()
        ]

    def _close_router_session(self) -> None:
        if self.session is not None and not self.session.is_closed():
            for sub in self._audit_subs:
                sub.undeclare()
            self._audit_subs = []
            if self._liveliness is not None:
                self._liveliness.undeclare()
            self._token.undeclare()
            self.session.close()

    def restart_router(self, down_s: float = 1.0) -> None:
        """Close the router and open it again ``down_s`` later on the same endpoints, with the
        same credentials (a router restart: every link drops; the services, zenoh clients,
        reconnect by themselves and recover what they missed from the publishers' caches)."""
        with self._router_lock:
            self._close_router_session()
            time.sleep(down_s)
            self._open_router_session()

    def _close_security(self) -> None:
        if self._dictionary is not None:
            self._dictionary.close()
            self._dictionary = None

    def client_config(self, identity: str = "operator") -> BusConfig:
        """The bus of a tool of this run (``plant`` or ``operator``): a client of the router
        presenting that identity's credentials (none on an insecure bus)."""
        bus = self.spec.client_bus()
        if not self.secure:
            return bus
        if identity not in TOOL_IDENTITIES:
            raise ValueError(f"identity must be one of {TOOL_IDENTITIES}, got {identity!r}")
        return as_identity(bus, identity, password_file=self.run_dir / "credentials" / identity)

    def __enter__(self) -> Supervisor:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    def _on_alive(self, sample: zenoh.Sample) -> None:
        name = keys.parse_key(str(sample.key_expr)).id
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(name)
            else:
                # a restarted service declares the same key: the old token's deletion may come
                # after the new token; the watcher re-queries the live tokens
                self.alive.discard(name)
                self._recheck = True

    def refresh_alive(self, timeout_s: float = 1.0) -> set[str]:
        """Query the live tokens (the truth, whatever order the events came in)."""
        names = set()
        assert self.session is not None
        for reply in self.session.liveliness().get(
            keys.services_alive(self.spec.name), timeout=timeout_s
        ):
            if reply.ok is not None:
                names.add(keys.parse_key(str(reply.ok.key_expr)).id)
        with self._lock:
            self.alive = names
        return names

    def _child_env(self, name: str) -> dict[str, str]:
        env = dict(os.environ)
        env[STATE_ENV] = str(self.run_dir)
        env[SUPERVISOR_PID_ENV] = str(os.getpid())
        for var in (USER_ENV, PASSWORD_ENV, PASSWORD_FILE_ENV):
            env.pop(var, None)
        if self.creds is not None:
            env[USER_ENV] = name
            env[PASSWORD_ENV] = self.creds.passwords[name]
        return env

    def _spawn(self, child: Child) -> None:
        """Start a service (from the watcher thread only: see the module docstring)."""
        logf = (self.run_dir / f"{child.name}.log").open("ab")
        cmd = [
            sys.executable,
            "-m",
            "services.runner",
            child.name,
            "--config",
            str(self.config_path),
            "--log-level",
            self.log_level,
        ]
        child.proc = subprocess.Popen(
            cmd,
            stdout=logf,
            stderr=subprocess.STDOUT,
            env=self._child_env(child.name),
            start_new_session=True,
        )
        logf.close()
        write_pid(self.run_dir, child.name, child.proc.pid)
        child.started_at = time.monotonic()
        log.info("started %s (pid %d)", child.name, child.proc.pid)
        action = "service_restart" if child.restarts else "service_start"
        self._audit("supervisor", action, child.name, f"pid {child.proc.pid}")

    # -- audit trail ---------------------------------------------------------------------------
    def _publish_audit(self, rec: AuditRecord) -> None:
        pub = self._audit_pub
        if pub is None:
            return
        try:
            pub.publish(rec)
        except Exception as exc:  # noqa: BLE001 - the record is in audit.jsonl all the same
            log.warning("audit record %d not published: %s", rec.seq, exc)

    def _audit(self, actor: str, action: str, subject: str, detail: str = "") -> None:
        if self.trail is not None:
            self.trail.append(actor, action, subject, detail)

    def _audited(self, handler: Any) -> Any:
        """A bus callback that decodes nothing itself and never raises into zenoh."""

        def callback(sample: zenoh.Sample) -> None:
            try:
                handler(str(sample.key_expr), sample.payload.to_bytes())
            except Exception as exc:  # noqa: BLE001 - a bad message must not stop the trail
                log.debug("audit: message on %s not recorded: %s", sample.key_expr, exc)

        return callback

    def _on_alert(self, key: str, payload: bytes) -> None:
        a = OosAlert.model_validate_json(payload)
        self.trail.see(a.t)
        self._audit(
            "oos",
            "alert",
            a.alert_id,
            f"{a.t_start_s:.1f}-{a.t_end_s:.1f} s, model {a.model_version}: {a.cause}",
        )

    def _on_divert(self, key: str, payload: bytes) -> None:
        d = DivertCommand.model_validate_json(payload)
        self.trail.see(d.t)
        self._audit(
            "oos",
            "divert_command",
            d.command_id,
            f"{d.action} {d.t_start_s:.1f}-{d.t_end_s:.1f} s (alert {d.alert_id}, model "
            f"{d.model_version}): {d.reason}",
        )

    def _on_finding(self, key: str, payload: bytes) -> None:
        f = ModelFinding.model_validate_json(payload)
        self.trail.see(f.t)
        effects = ", ".join(e.label for e in f.effects) or "none"
        self._audit(
            "closeloop",
            "model_finding",
            f.finding_id,
            f"{f.status}; effects {effects}; product at risk {f.product_at_risk}",
        )
        if f.data_quality:
            kinds = ", ".join(
                f"{q.kind} {q.t_start_s:.0f}-{q.t_end_s:.0f} s" for q in f.data_quality[:20]
            )
            self._audit("closeloop", "data_quality", f.finding_id, kinds)

    def _on_model(self, key: str, payload: bytes) -> None:
        m = BlenderModelInUse.model_validate_json(payload)
        self.trail.see(m.t)
        self._audit(
            "blender",
            "model_adopted",
            m.name,
            f"{m.kind} model version {m.model_version} from {m.applies_from_s:.1f} s "
            f"({m.reason}), mean residence time {m.mean_residence_time_s:.2f} s",
        )

    def _on_health(self, key: str, payload: bytes) -> None:
        h = ServiceHealth.model_validate_json(payload)
        now = {k: int(v) for k, v in h.counters.items() if k.startswith("rejected_")}
        before = self._rejected.get(h.service, {})
        rises = {k: v - before.get(k, 0) for k, v in now.items() if v > before.get(k, 0)}
        self._rejected[h.service] = now
        if rises:
            text = ", ".join(f"{k} +{d} (total {now[k]})" for k, d in sorted(rises.items()))
            last = h.last_error or ""
            self._audit(h.service, "rejected_messages", h.service, f"{text}. {last}".strip())

    def publish_health(self) -> None:
        """Health of the supervisor: restarts and running state of every service."""
        counters = {f"restarts_{n}": c.restarts for n, c in self.children.items()}
        counters.update({f"running_{n}": int(c.proc is not None) for n, c in self.children.items()})
        self._health.publish(
            ServiceHealth(
                t=0.0,
                seq=self._health.seq,
                service="supervisor",
                state="stopping" if self._stop.is_set() else "running",
                pid=os.getpid(),
                uptime_s=time.monotonic() - self._t0,
                wall_time_unix_s=time.time(),
                counters=counters,
            )
        )

    def _check_liveliness(self, child: Child, now: float) -> None:
        """Kill a running service whose liveliness token has been gone for
        ``liveliness_timeout_s`` (hung, or cut off from the router); it is then restarted."""
        p = child.proc
        if p is None or p.poll() is not None:
            return
        with self._lock:
            alive = child.name in self.alive
        if alive:
            child.seen_alive = True
            child.lost_since = None
            return
        if not child.seen_alive:
            return  # still starting
        if child.lost_since is None:
            child.lost_since = now
        elif now - child.lost_since >= self.liveliness_timeout_s:
            if child.name in self.refresh_alive():
                child.lost_since = None
                return
            log.warning(
                "%s (pid %d) lost its liveliness token %.1f s ago: killing it",
                child.name,
                p.pid,
                now - child.lost_since,
            )
            p.kill()
            child.lost_since = None
            self._audit("supervisor", "service_killed", child.name, "liveliness token lost: killed")

    def _reap(self, child: Child, now: float) -> None:
        """Note a service that exited and schedule its restart (exponential backoff)."""
        p = child.proc
        if p is None or p.poll() is None:
            return
        child.exit_codes.append(p.returncode)
        up = now - child.started_at
        if up >= self.stable_s:
            child.backoff_s = 0.0
        child.backoff_s = (
            self.backoff_s
            if child.backoff_s == 0.0
            else min(2 * child.backoff_s, self.max_backoff_s)
        )
        child.next_start = now + child.backoff_s
        child.proc = None
        child.seen_alive = False
        log.warning(
            "%s exited with %s after %.1f s; restart in %.1f s",
            child.name,
            p.returncode,
            up,
            child.backoff_s,
        )
        self._audit(
            "supervisor",
            "service_exit",
            child.name,
            f"exit status {p.returncode} after {up:.1f} s (crash); restart in {child.backoff_s:.1f} s",
        )

    def _watch(self) -> None:
        """Start the services, watch them until :meth:`stop`, then stop them (this thread
        started them all: their parent-death signal is tied to it)."""
        for child in self.children.values():
            self._spawn(child)
        last_health = 0.0
        while not self._stop.wait(0.1):
            now = time.monotonic()
            if self._recheck:
                self._recheck = False
                try:
                    self.refresh_alive(0.5)
                except Exception as exc:  # noqa: BLE001 - keep supervising
                    log.debug("liveliness query failed: %s", exc)
            for child in self.children.values():
                self._check_liveliness(child, now)
            if now - last_health >= 1.0:
                last_health = now
                try:
                    self.publish_health()
                except Exception as exc:  # noqa: BLE001 - health must not stop supervision
                    log.debug("supervisor health not sent: %s", exc)
            for child in self.children.values():
                self._reap(child, now)
                if child.proc is None and now >= child.next_start and not self._stop.is_set():
                    child.restarts += 1
                    self._spawn(child)
        self.codes = self._stop_children()

    def _stop_children(self) -> dict[str, int | None]:
        """Stop the services but the recorder, record their exits and ``trail_end``, then stop
        the recorder (it records the end of the trail); exit codes."""
        first = [n for n in self.children if n != "recorder"]
        codes = self._stop_some(first)
        for n, code in codes.items():
            self._audit("supervisor", "service_exit", n, f"exit status {code} (stopped)")
        self._audit("supervisor", "trail_end", self.run_dir.name, "twin stopped")
        if "recorder" in self.children:
            rec = self.children["recorder"]
            if rec.proc is not None and rec.proc.poll() is None:
                time.sleep(self.trail_settle_s)  # the recorder takes the last records
            codes.update(self._stop_some(["recorder"]))
        return codes

    #: wall seconds the recorder is given to write the trail's last records before it stops
    trail_settle_s = 1.0

    def _stop_some(self, names: list[str]) -> dict[str, int | None]:
        """SIGTERM these services, wait ``stop_timeout_s``, SIGKILL what remains; exit codes."""
        procs = {n: c.proc for n, c in self.children.items() if c.proc is not None and n in names}
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + self.stop_timeout_s
        codes: dict[str, int | None] = {}
        for n, p in procs.items():
            try:
                codes[n] = p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.1f s: killing", n, self.stop_timeout_s)
                p.kill()
                codes[n] = p.wait()
            (self.run_dir / f"{n}.pid").unlink(missing_ok=True)
        return codes

    def wait_ready(self, timeout_s: float = 60.0) -> bool:
        """Wait until every service's liveliness token is alive."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if set(self.names) <= self.alive:
                    return True
            time.sleep(0.05)
        return False

    def pids(self) -> dict[str, int | None]:
        return {n: (c.proc.pid if c.proc else None) for n, c in self.children.items()}

    def stop(self) -> dict[str, int | None]:
        """Stop the services (the watcher thread: SIGTERM, wait, SIGKILL what remains), close
        the router, release the run lock; return the services' exit codes."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.stop_timeout_s + 30.0)
        with self._router_lock:
            self._close_router_session()
        self._close_security()
        self._lock_file.release()
        return self.codes
