"""Replay and record rates of MCAP recordings over the bus, with peers side by side.

1. Writing (in process, 20,000 FeederFlow/MeasuredConcentration messages, zstd, 1 MiB chunks):
   ``McapRecorder.write`` of pre-encoded payloads (our writer: channel lookup, log_time from t,
   sequence, periodic flush) vs the bare ``mcap.writer.Writer.add_message`` (peer).
2. Reading: ``read_recording`` (time-ordered, into memory) vs bare ``make_reader().iter_messages``
   in file order (peer).
3. Replay scheduling alone: ``replay(..., as_fast_as_possible=True)`` into a no-op publisher.
4. End to end over zenoh between two processes: ``twin replay --as-fast-as-possible`` (this
   process: ``replay_to_bus``, validating every message first) into ``twin record`` (a spawned
   process: validate + write). Reports the replay's publish rate and the recorder's
   record rate (messages / its wall time from ready to done) and checks nothing was lost.

Run: ``python benchmarks/bus_throughput.py [N]``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from machine import describe
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from schemas.bus_config import BusConfig
from schemas.messages import FeederFlow, MeasuredConcentration
from services.bus import free_port
from services.recording import McapRecorder, read_recording, replay, replay_to_bus

FLOW = "twin/bench/feeder/api/flow"
CONC = "twin/bench/pat/nir1/concentration"


def payloads(n: int) -> list[tuple[str, bytes, float]]:
    out = []
    for i in range(n):
        t = 0.01 * i
        if i % 2:
            m = FeederFlow(
                t=t,
                seq=i // 2,
                component="api",
                mass_flow_kg_h=0.6 + i % 7 * 1e-3,
                screw_speed_rpm=40.0,
                hopper_mass_kg=2.0,
                feed_factor_g_rev=0.25,
            )
            out.append((FLOW, m.to_json_bytes(), t))
        else:
            m = MeasuredConcentration(
                t=t,
                seq=i // 2,
                sensor="nir1",
                component="api",
                concentration_pct_w_w=5.0 + (i % 11) * 0.01,
            )
            out.append((CONC, m.to_json_bytes(), t))
    return out


def bench_write(data, d: Path) -> tuple[float, float]:
    t0 = time.perf_counter()
    with McapRecorder(d / "ours.mcap", flush_period_s=None) as rec:
        for key, p, t in data:
            rec.write(key, p, t)
    ours = len(data) / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    with open(d / "peer.mcap", "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        sid = w.register_schema("s", "jsonschema", b'{"type":"object"}')
        ch = {k: w.register_channel(k, "json", sid) for k in (FLOW, CONC)}
        for key, p, t in data:
            w.add_message(ch[key], int(t * 1e9), p, int(t * 1e9))
        w.finish()
    peer = len(data) / (time.perf_counter() - t0)
    return ours, peer


def bench_read(path: Path, n: int) -> tuple[float, float]:
    t0 = time.perf_counter()
    rec = read_recording(path)
    assert len(rec.messages) == n
    ours = n / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    with open(path, "rb") as f:
        k = sum(1 for _ in make_reader(f).iter_messages(log_time_order=False))
    assert k == n
    peer = n / (time.perf_counter() - t0)
    return ours, peer


def bench_end_to_end(path: Path, n: int, d: Path) -> dict[str, float]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    out = d / "capture.mcap"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli.main",
            "record",
            str(out),
            "--listen",
            ep,
            "--count",
            str(n),
            "--no-health",
            "--duration",
            "300",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    for line in proc.stdout:
        if line.strip() == "ready":
            break
    rec = read_recording(path)
    t0 = time.perf_counter()
    stats = replay_to_bus(
        rec,
        BusConfig(connect=[ep]),
        as_fast_as_possible=True,
        wait_for_subscribers_s=30,
        install_signal_handlers=False,
    )
    setup_s = time.perf_counter() - t0 - stats.wall_s
    rest, _ = proc.communicate(timeout=300)
    t_done = time.perf_counter()
    cap = read_recording(out)
    return {
        "replay_msg_s": stats.rate_msg_s,
        "end_to_end_msg_s": n / (t_done - t0 - setup_s),
        "captured": len(cap.messages),
        "identical": [m.payload for m in cap.messages] == [m.payload for m in rec.messages],
    }


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 20_000
    print(f"{describe()}; {n} messages (~130-190 B JSON each)")
    data = payloads(n)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        ours, peer = bench_write(data, d)
        print(
            f"write  McapRecorder {ours:9.0f} msg/s | bare mcap Writer {peer:9.0f} msg/s | "
            f"ratio {ours / peer:.2f}"
        )
        ours, peer = bench_read(d / "ours.mcap", n)
        print(
            f"read   read_recording {ours:7.0f} msg/s | bare iter_messages {peer:7.0f} msg/s | "
            f"ratio {ours / peer:.2f}"
        )
        rec = read_recording(d / "ours.mcap")
        st = replay(rec, lambda k, p: None, as_fast_as_possible=True)
        print(f"replay scheduling only (no-op publish): {st.rate_msg_s:9.0f} msg/s")
        e2e = bench_end_to_end(d / "ours.mcap", n, d)
        print(
            f"zenoh replay -> twin record (2 processes): replay publishes "
            f"{e2e['replay_msg_s']:.0f} msg/s; end-to-end recorded {e2e['end_to_end_msg_s']:.0f}"
            f" msg/s; captured {e2e['captured']}/{n}, identical={e2e['identical']}"
        )


if __name__ == "__main__":
    main()
