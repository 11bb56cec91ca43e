"""Run-state helpers of the live services: the run's state directory, the idempotent output
log (outputs already published, so that a restarted service does not publish them again), and
the one-line text of an OOS alert or divert command (``twin alerts``, ``twin demo``) and the
status table of the services (``twin status``)."""

from __future__ import annotations

import os
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


def state_dir(spec: LineSpec) -> Path:
    """The run's state directory: ``$TWIN_STATE_DIR`` (set by ``twin up``) or ``spec.state_dir``."""
    return Path(os.environ.get(STATE_ENV) or spec.state_dir)


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
