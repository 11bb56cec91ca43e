"""Run-state helpers of the live services: the run's state directory, the run's lock file (one
``twin up`` per line and state directory; what the tools learn of the running twin), the
mark of the last output published (:class:`TickMark`), the idempotent output log (outputs already published, so that a restarted service does not publish
them again), and the one-line text of an OOS alert or divert command (``twin alerts``, ``twin
demo``) and the status table of the services (``twin status``)."""

from __future__ import annotations

import fcntl
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import (
    AdoptionProgress,
    BlenderDrive,
    BlenderModelUpdate,
    DivertCommand,
    FeederFlow,
    OosAlert,
    ServiceHealth,
)

#: environment variable naming the run's state directory (set by the supervisor)
STATE_ENV = "TWIN_STATE_DIR"


class OutputLog:
    """Append-only log of the outputs already published (idempotence across restarts).

    One line per output: ``id<TAB>channel<TAB>seq<TAB>wall time`` (a line of the id alone, the
    earlier format, is read too). A restarted service recomputes its outputs and publishes again
    none of those logged, except the ones logged within ``at_risk_s`` of wall time before the
    last line when the process did not stop cleanly (no closing line): an output is written here
    right after its publication, when it may still be in the process's send queue, and a SIGKILL
    then loses it (seen in the live test under load: a
    logged ``.final`` divert command that no subscriber received). Those are published once
    more, with the ``seq`` they had, so that every subscriber that drops duplicates by position
    (``services.bus.StreamOrder``: the services, the recorder) sees one message."""

    #: the line a clean stop writes (:meth:`close`)
    CLOSED = "#closed"

    def __init__(self, path: Path, at_risk_s: float = 2.0) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self.done: set[str] = set()
        #: output id -> (channel, seq) as logged
        self.positions: dict[str, tuple[str, int]] = {}
        #: ids logged in the last ``at_risk_s`` before the previous process stopped
        self.at_risk: set[str] = set()
        text = path.read_text() if path.exists() else ""
        # a torn last line (crash mid-write) is ignored: that output is sent again
        self._read(text.split("\n")[:-1], at_risk_s)
        self._f = path.open("a")
        if text and not text.endswith("\n"):
            self._f.write("\n")  # the next line must not continue the torn one

    def _read(self, lines: list[str], at_risk_s: float) -> None:
        walls: list[tuple[float, str]] = []
        for line in lines:
            if line == self.CLOSED:  # a clean stop: what came before it was sent
                walls.clear()
                continue
            if not line:
                continue
            parts = line.split("\t")
            self.done.add(parts[0])
            if len(parts) == 4:
                try:
                    self.positions[parts[0]] = (parts[1], int(parts[2]))
                    walls.append((float(parts[3]), parts[0]))
                except ValueError:
                    continue
        if walls:
            last = max(w for w, _ in walls)
            self.at_risk = {i for w, i in walls if w >= last - at_risk_s}

    def __contains__(self, output_id: str) -> bool:
        return output_id in self.done

    def next_seq(self, channel: str) -> int:
        """The ``seq`` after the largest one logged on ``channel`` (0 if none)."""
        seqs = [q for c, q in self.positions.values() if c == channel]
        return max(seqs) + 1 if seqs else 0

    def take_at_risk(self, output_id: str) -> tuple[str, int] | None:
        """The logged (channel, seq) of an at-risk output to publish once more, or None."""
        if output_id not in self.at_risk or output_id not in self.positions:
            return None
        self.at_risk.discard(output_id)
        return self.positions[output_id]

    def add(self, output_id: str, channel: str = "", seq: int | None = None) -> None:
        self.done.add(output_id)
        if seq is None:
            self._f.write(output_id + "\n")
        else:
            self.positions[output_id] = (channel, int(seq))
            self._f.write(f"{output_id}\t{channel}\t{int(seq)}\t{time.time():.6f}\n")
        self._f.flush()

    def close(self) -> None:
        """Close after a clean stop: nothing the process published is at risk any more."""
        self._f.write(self.CLOSED + "\n")
        self._f.close()


def publish_once(
    log: OutputLog,
    pub: Any,
    output_id: str,
    channel: str,
    make: Callable[[int], Any],
    counters: Any,
) -> Any | None:
    """Publish the output ``make(seq)`` on ``pub`` and log it, unless the log has it (a
    restarted service recomputing what it had published: counted in ``suppressed_republish``).
    One the log holds as at risk (:class:`OutputLog`) is published once more with the ``seq``
    it was logged with (``republished_at_risk``). Returns the message when it is new."""
    if output_id in log:
        again = log.take_at_risk(output_id)
        if again is None:
            counters.inc("suppressed_republish")
            return None
        following = pub.seq
        pub.publish(make(again[1]))
        pub.seq = max(following, again[1] + 1)
        counters.inc("republished_at_risk")
        return None
    msg = pub.publish(make(pub.seq))
    log.add(output_id, channel, msg.seq)
    return msg


class TickMark:
    """The plant time of the last output published, kept in a file across restarts: each
    :meth:`write` is one ``pwrite`` of a fixed-width number at offset 0 (no truncation, so a
    crash never leaves a torn or empty file)."""

    WIDTH = 24

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)

    def read(self) -> float:
        """The last plant time written (-1.0 if none)."""
        try:
            return float(os.pread(self._fd, self.WIDTH, 0).decode().strip() or -1.0)
        except ValueError:
            return -1.0

    def write(self, t: float) -> None:
        os.pwrite(self._fd, f"{t!r:>{self.WIDTH}}".encode()[: self.WIDTH], 0)

    def close(self) -> None:
        os.close(self._fd)


def applies_from(msg: Any, spec: LineSpec) -> float:
    """Plant time from which an ``RtdEstimate`` or a ``ModelFinding`` applies: its
    ``applies_from_s``, or (a message of contract < 1.5) ``t + blender.adoption_delay_s``."""
    t_from = getattr(msg, "applies_from_s", None)
    return float(msg.t + spec.blender.adoption_delay_s if t_from is None else t_from)


class ProducerProgress:
    """How far each producer of model updates (``rtd``, ``closeloop``) is known complete, from
    its ``AdoptionProgress`` reports and the updates received: a report counts only once the
    update it names (``last_update_t_s``) has arrived, since the bus may deliver the two keys
    out of order (a sample recovered from the publisher's cache comes later)."""

    def __init__(self, sources: list[str]) -> None:
        self.sources = list(sources)
        self.complete: dict[str, float] = {s: -math.inf for s in self.sources}
        self._newest: dict[str, float] = {s: -math.inf for s in self.sources}
        self._waiting: dict[str, list[tuple[float, float]]] = {s: [] for s in self.sources}
        #: wall time (monotonic) the progress last moved (or the start)
        self.moved_at = time.monotonic()

    @property
    def complete_to_s(self) -> float:
        """Plant time up to which every update of every producer is in (inf without any)."""
        return min(self.complete.values(), default=math.inf)

    def update(self, source: str, t: float) -> bool:
        """An update of plant time ``t`` from ``source`` arrived; returns whether that made a
        waiting report count (:attr:`complete` moved)."""
        if source not in self._newest:
            return False
        self._newest[source] = max(self._newest[source], t)
        return self._settle(source)

    def report(self, source: str, complete_to_s: float, last_update_t_s: float | None) -> bool:
        """A progress report of ``source``; returns whether :attr:`complete` moved."""
        if source not in self._waiting:
            return False
        need = -math.inf if last_update_t_s is None else last_update_t_s
        self._waiting[source].append((need, complete_to_s))
        return self._settle(source)

    def _settle(self, source: str) -> bool:
        have, before = self._newest[source], self.complete[source]
        kept = []
        for need, w in self._waiting[source]:
            if need <= have:
                self.complete[source] = max(self.complete[source], w)
            else:
                kept.append((need, w))
        self._waiting[source] = kept
        if self.complete[source] > before:
            self.moved_at = time.monotonic()
            return True
        return False

    def silent_for(self, wait_s: float, waiting_since: float = -math.inf) -> bool:
        """Whether there are producers and their progress has not moved for ``wait_s`` wall
        seconds while something waited for it (since ``waiting_since``, monotonic): down or
        stuck, the outputs may go on without them."""
        quiet_since = max(self.moved_at, waiting_since)
        return bool(self.sources) and time.monotonic() - quiet_since > wait_s


class AdoptionGate(ProducerProgress):
    """Feeder flows held until every producer of model updates has reported that every update
    applying up to their plant time is in (:class:`ProducerProgress`); the model used at each
    plant time is then a function of the plant data only. No sources: nothing is held."""

    def __init__(self, sources: list[str]) -> None:
        super().__init__(sources)
        self._held: list[tuple[str, Any]] = []
        #: wall time (monotonic) the oldest held flow was held
        self.held_since = -math.inf
        #: go on without the producers (they were silent too long) until they move again
        self.bypass = False

    def _settle(self, source: str) -> bool:
        moved = super()._settle(source)
        if moved:
            self.bypass = False
        return moved

    def release_all(self) -> list[tuple[str, Any]]:
        """Every held flow, in arrival order; then go on without the producers until their
        progress moves again (:attr:`bypass`)."""
        free, self._held = self._held, []
        self.bypass = True
        return free

    def hold(self, key: str, msg: Any) -> bool:
        """Whether the flow ``msg`` on ``key`` must wait (then kept, in arrival order)."""
        if self.bypass and not self._held:
            return False
        if self._held or msg.t > self.complete_to_s:
            if not self._held:
                self.held_since = time.monotonic()
            self._held.append((key, msg))
            return True
        return False

    def stalled(self, wait_s: float) -> bool:
        """Whether flows have waited ``wait_s`` wall seconds without the producers' progress
        moving (:meth:`ProducerProgress.silent_for`)."""
        return bool(self._held) and self.silent_for(wait_s, self.held_since)

    def free(self) -> list[tuple[str, Any]]:
        """The held flows now free, in arrival order (each key's flows stay in order: a flow
        waits behind an earlier one of its key)."""
        bound, free, kept, blocked = self.complete_to_s, [], [], set()
        for key, msg in self._held:
            if key in blocked or msg.t > bound:
                blocked.add(key)
                kept.append((key, msg))
            else:
                free.append((key, msg))
        self._held = kept
        return free

    def __len__(self) -> int:
        return len(self._held)


class ProgressReport:
    """A producer's :class:`~schemas.messages.AdoptionProgress`: how far its model updates are
    complete. Published when it has moved ``step_s`` of plant time, and on :meth:`flush` (the
    producer idle: the last one is never held back); never again below what was published
    before a restart (the mark is kept in the run's state directory). ``pub``: the producer's
    publisher, set once its session is open (until then nothing is published)."""

    def __init__(self, mark_path: Path, step_s: float) -> None:
        self.pub: Any = None
        self.step_s = step_s
        self._mark = TickMark(mark_path)
        self.sent = self._mark.read()
        self._pending: tuple[float, float] | None = None
        #: ``t`` of the newest update published by this process (None: none yet)
        self.last_update_t: float | None = None

    def updated(self, t: float) -> None:
        """The producer published an update of plant time ``t``."""
        self.last_update_t = t

    def advance(self, t: float, complete_to_s: float) -> None:
        """Every update applying up to ``complete_to_s`` is out (data read up to ``t``)."""
        if complete_to_s <= self.sent:
            return
        self._pending = (t, complete_to_s)
        if complete_to_s - self.sent >= self.step_s:
            self.flush()

    def flush(self) -> None:
        if self._pending is None or self.pub is None:
            return
        t, w = self._pending
        self._pending = None
        self.pub.publish(
            AdoptionProgress(
                t=t, seq=self.pub.seq, complete_to_s=w, last_update_t_s=self.last_update_t
            )
        )
        self.sent = w
        self._mark.write(w)

    def close(self) -> None:
        self._mark.close()


class _Reporting(Protocol):
    name: str
    counters: Any
    warnings: Any


def record_late(service: _Reporting, late_s: float, msg: Any) -> None:
    """An update that came ``late_s`` of plant time after the first output it applies to
    (0: in time): counted in ``adopted_late``, the largest in ``adopted_late_max_ms``,
    logged (rate-limited)."""
    if late_s <= 0:
        return
    service.counters.inc("adopted_late")
    service.counters.raise_to("adopted_late_max_ms", int(round(late_s * 1000)))
    service.warnings.warn(
        "adopted_late",
        f"{service.name}: {type(msg).__name__} of t={msg.t:.1f} s applied {late_s:.1f} s "
        "of plant time late (its producer did not report its progress in time)",
    )


def follow_operating_point(service: Any, tracker: Any, key: str, msg: Any) -> None:
    """Schedule on ``service.core`` (blender or diverter core) the model switch a plant message
    brings, at its plant time: a ``BlenderDrive`` with a new blade speed or a ``FeederFlow``
    whose set point changes the throughput (``twin_core.online.drive.OperatingPointTracker``), or
    a ``BlenderModelUpdate`` (a new section model). Counted in ``operating_point_changes`` /
    ``models_received``; for an RTD-model blender, which has no law for the operating point, in
    ``operating_point_not_modelled``."""
    kernel = service.core.kernel
    if isinstance(msg, BlenderModelUpdate):
        if kernel.table is None:
            service.counters.inc("operating_point_not_modelled")
            return
        record_late(service, service.core.schedule(msg.t, "model", msg.model), msg)
        service.counters.inc("models_received")
        return
    if isinstance(msg, BlenderDrive):
        point, reason = tracker.drive(msg.blade_speed_rpm), "blade_speed"
    elif isinstance(msg, FeederFlow):
        point, reason = tracker.setpoint(keys.parse_key(key).id, msg.setpoint_kg_h), "throughput"
    else:
        return
    if point is None:
        return
    if kernel.table is None:
        service.counters.inc("operating_point_not_modelled")
        return
    late = service.core.schedule(msg.t, "operating_point", (point, reason))
    record_late(service, late, msg)
    service.counters.inc("operating_point_changes")


def state_dir(spec: LineSpec) -> Path:
    """The run's state directory: ``$TWIN_STATE_DIR`` (set by ``twin up``) or ``spec.state_dir``."""
    return Path(os.environ.get(STATE_ENV) or spec.state_dir)


@dataclass
class RunInfo:
    """What a running ``twin up`` tells the tools (in its lock file): its pid, run directory,
    router endpoints and whether the bus is secured (credentials in ``<run_dir>/credentials``)."""

    pid: int
    run_dir: str
    line: str
    listen: list[str]
    secure: bool


def lock_path(spec: LineSpec) -> Path:
    """The run lock of a line: ``<state_dir>/twin-<line>.lock``."""
    return Path(spec.state_dir) / f"twin-{spec.name}.lock"


class RunLock:
    """An exclusive lock (``flock``) on the line's lock file, held while ``twin up`` runs and
    released by the kernel when its process dies; the file holds the :class:`RunInfo`."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._f = None

    def acquire(self, info: RunInfo) -> None:
        """Take the lock and write ``info``; raise RuntimeError naming the running twin if
        another process holds it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = self.path.open("a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            text = f.read()
            f.close()
            raise RuntimeError(
                f"a twin of line {info.line} is already running, {_describe(text)} "
                f"(lock {self.path})"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(json.dumps(asdict(info)))
        f.flush()
        self._f = f

    def release(self) -> None:
        if self._f is not None:
            self._f.seek(0)
            self._f.truncate()
            fcntl.flock(self._f, fcntl.LOCK_UN)
            self._f.close()
            self._f = None


def _describe(text: str) -> str:
    try:
        data = json.loads(text)
        return f"pid {data['pid']}, run dir {data['run_dir']}"
    except (ValueError, KeyError, TypeError):
        return "pid unknown"


def running_twin(spec: LineSpec) -> RunInfo | None:
    """The :class:`RunInfo` of the ``twin up`` holding the line's lock, or None when none does
    (no lock file, or one left by a process that is gone)."""
    path = lock_path(spec)
    try:
        f = path.open()
    except OSError:
        return None
    with f:
        try:
            fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                return RunInfo(**json.loads(f.read()))
            except (ValueError, TypeError):
                return None
        fcntl.flock(f, fcntl.LOCK_UN)
        return None


def running_line(info: RunInfo) -> LineSpec:
    """The line configuration a running ``twin up`` runs with (``<run dir>/line.json``); a
    ValueError naming the file when it cannot be read."""
    path = Path(info.run_dir) / "line.json"
    try:
        return LineSpec.from_file(path)
    except (OSError, ValueError) as exc:
        raise ValueError(
            f"the running twin's configuration cannot be read, {path}: {exc}"
        ) from None


def write_pid(run_dir: Path, name: str, pid: int) -> None:
    """``<run_dir>/<name>.pid``: the process of a supervised service."""
    (run_dir / f"{name}.pid").write_text(str(pid))


def live_service_processes(state_root: Path, line: str) -> dict[int, str]:
    """Service processes of earlier runs of ``line`` under ``state_root`` that still run:
    pid -> pid file (``run-*/<name>.pid`` of a run whose ``line.json`` names the line, whose
    process is a ``services.runner``)."""
    found: dict[int, str] = {}
    for pidfile in state_root.glob("run-*/*.pid"):
        try:
            if json.loads((pidfile.parent / "line.json").read_text()).get("name") != line:
                continue
            pid = int(pidfile.read_text().strip())
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        except (OSError, ValueError, AttributeError):
            continue
        if b"services.runner" in cmdline:
            found[pid] = str(pidfile)
    return found


def format_alert(msg: OosAlert | DivertCommand) -> str:
    """One line for an OOS alert or a divert command."""
    if isinstance(msg, OosAlert):
        return (
            f"ALERT  {msg.alert_id}  {msg.component}  outlet {msg.t_start_s:.1f}-{msg.t_end_s:.1f} s"
            f"  peak {msg.peak_deviation_pct_w_w:+.3f} % w/w (limit {msg.limit_pct_w_w})"
            f"  [{msg.cause}]"
        )
    return (
        f"DIVERT {msg.command_id}  {msg.action} {msg.t_start_s:.1f}-{msg.t_end_s:.1f} s"
        f"  (t={msg.t:.1f} s)"
    )


def status_rows(alive: list[str], health: dict[str, ServiceHealth]) -> dict[str, dict]:
    """Per service (alive or reporting health): ``alive`` and its latest health fields."""
    return {
        n: {"alive": n in alive, **(health[n].model_dump(mode="json") if n in health else {})}
        for n in sorted(set(alive) | set(health))
    }


def status_table(rows: dict[str, dict]) -> list[str]:
    """``twin status``'s table of :func:`status_rows`: alive, state, pid, uptime, plant time,
    counters."""
    lines = [
        f"{'service':<10} {'alive':<6} {'state':<9} {'pid':>7} {'up_s':>8} {'plant_t':>9}  counters"
    ]
    for n, r in rows.items():
        alive = "yes" if r["alive"] else "no"
        if "state" not in r:
            lines.append(f"{n:<10} {alive:<6}")
            continue
        c = " ".join(f"{k}={v}" for k, v in sorted(r["counters"].items()))
        lines.append(
            f"{n:<10} {alive:<6} {r['state']:<9} {r['pid']:>7} "
            f"{r['uptime_s']:>8.1f} {r['t']:>9.1f}  {c}"
        )
    return lines
