"""The replay/record check behind ``twin demo``.

:func:`run_replay_check` replays a recording over zenoh from this process while ``twin record``
captures the bus in another process, then checks that the capture equals the source message for
message (same keys, same payload bytes, same order per key) and returns a summary.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from schemas import keys
from schemas.bus_config import BusConfig
from services.bus import free_port
from services.recording import ReplayStats, read_recording, replay_to_bus, validate_messages

BUNDLED_RECORDING = Path(__file__).resolve().parent.parent / "recordings" / "line1_30min.mcap"


@dataclass
class ReplayCheckResult:
    """Outcome of :func:`run_replay_check`. ``ok``: every source message captured, identical."""

    recording: Path
    capture: Path
    source_counts: dict[str, int]
    captured_counts: dict[str, int]
    mismatched_keys: list[str]
    replay: ReplayStats
    recorder_wall_s: float
    recorder_output: str
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems and not self.mismatched_keys

    @property
    def source_total(self) -> int:
        return sum(self.source_counts.values())

    @property
    def captured_total(self) -> int:
        return sum(self.captured_counts.get(k, 0) for k in self.source_counts)

    def summary(self) -> str:
        lines = [
            f"recording: {self.recording}",
            f"replayed {self.replay.published} messages, plant span {self.replay.plant_span_s:.1f}"
            f" s, in {self.replay.wall_s:.2f} s wall ({self.replay.rate_msg_s:.0f} msg/s)",
            f"captured by `twin record` (another process) into {self.capture}",
        ]
        width = max((len(k) for k in self.source_counts), default=10)
        for key in sorted(self.source_counts):
            a, b = self.source_counts[key], self.captured_counts.get(key, 0)
            mark = "ok" if a == b and key not in self.mismatched_keys else "MISMATCH"
            lines.append(f"  {key:<{width}}  source {a:>6}  captured {b:>6}  {mark}")
        lines.extend(f"problem: {p}" for p in self.problems)
        lines.append(
            "RESULT: capture equals source, message for message"
            if self.ok
            else f"RESULT: FAILED ({self.captured_total}/{self.source_total} captured)"
        )
        return "\n".join(lines)


def run_replay_check(
    recording: str | Path = BUNDLED_RECORDING,
    *,
    speed: float = 1.0,
    as_fast_as_possible: bool = False,
    capture: str | Path | None = None,
    port: int | None = None,
    timeout_s: float = 120.0,
    line: str = "line1",
) -> ReplayCheckResult:
    """Replay ``recording`` over zenoh here while ``twin record`` captures it in a subprocess.

    The recorder listens on ``tcp/127.0.0.1:<port>`` (a free port by default) and stops after as
    many messages as the source holds (or ``timeout_s``); this process connects, waits until
    every channel has a subscriber, replays at ``speed`` (or as fast as possible), and compares
    the capture with the source per key: same count, same payload bytes in the same order.
    Only keys of the source are compared (service health is not recorded).
    """
    recording = Path(recording)
    src = read_recording(recording)
    valid, rejected = validate_messages(src)
    problems = []
    if src.truncated:
        problems.append(f"source recording is truncated: {src.loss_report()}")
    if any(rejected.values()):
        problems.append(f"source holds invalid messages (not replayed): {rejected}")
    tmpdir = None
    if capture is None:
        tmpdir = tempfile.mkdtemp(prefix="twin-demo-")
        capture = Path(tmpdir) / "capture.mcap"
    capture = Path(capture)
    endpoint = f"tcp/127.0.0.1:{port or free_port()}"
    cmd = [
        sys.executable, "-m", "services.cli.main", "record", str(capture),
        "--listen", endpoint, "--line", line, "--keys", keys.ALL_LINES, "--no-health",
        "--count", str(len(valid)), "--duration", str(timeout_s),
    ]  # fmt: skip
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    t0 = time.monotonic()
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    output = []
    try:
        for line_out in proc.stdout:  # wait until the recorder is subscribed
            output.append(line_out)
            if line_out.strip() == "ready":
                break
        else:
            raise RuntimeError(f"twin record exited before it was ready: {''.join(output)}")
        stats = replay_to_bus(
            src,
            BusConfig(connect=[endpoint], line=line),
            speed=speed,
            as_fast_as_possible=as_fast_as_possible,
            wait_for_subscribers_s=min(30.0, timeout_s),
            settle_s=0.2,
            service_name="demo-replay",
            install_signal_handlers=False,
        )
        rest, _ = proc.communicate(timeout=timeout_s)
        output.append(rest)
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
    rec_wall = time.monotonic() - t0
    if proc.returncode != 0:
        problems.append(f"twin record exited with {proc.returncode}")
    cap = read_recording(capture)
    if cap.truncated:
        problems.append(f"capture is truncated: {cap.loss_report()}")
    source_by_key: dict[str, list[bytes]] = {}
    for m in valid:
        source_by_key.setdefault(m.key, []).append(m.payload)
    captured_by_key: dict[str, list[bytes]] = {}
    for m in cap.messages:
        captured_by_key.setdefault(m.key, []).append(m.payload)
    mismatched = [k for k, v in source_by_key.items() if captured_by_key.get(k) != v]
    return ReplayCheckResult(
        recording=recording,
        capture=capture,
        source_counts={k: len(v) for k, v in source_by_key.items()},
        captured_counts={k: len(v) for k, v in captured_by_key.items()},
        mismatched_keys=sorted(mismatched),
        replay=stats,
        recorder_wall_s=rec_wall,
        recorder_output="".join(output),
        problems=problems,
    )
