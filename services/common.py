"""Run-state helpers of the live services: the run's state directory, the run's lock file (one
``twin up`` per line and state directory; what the tools learn of the running twin), the
mark of the last output published (:class:`TickMark`), the idempotent output log (outputs already published, so that a restarted service does not publish
them again), and the one-line text of an OOS alert or divert command (``twin alerts``, ``twin
demo``) and the status table of the services (``twin status``)."""

from __future__ import annotations

import fcntl
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

from schemas.line import LineSpec
from schemas.messages import DivertCommand, OosAlert, ServiceHealth

#: environment variable naming the run's state directory (set by the supervisor)
STATE_ENV = "TWIN_STATE_DIR"


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
