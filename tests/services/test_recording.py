"""MCAP recordings: round trip (payload bytes identical, jsonschema schemas readable), recovery
of files cut short (truncation and a writer killed with SIGKILL), replay timing, looping,
record-while-replay without loss across processes, the line-data loader, the CLI."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from schemas import keys
from schemas.bus_config import BusConfig
from schemas.messages import Event, FeederFlow, MeasuredConcentration
from services.bus import free_port
from services.recording import (
    McapRecorder,
    load_line_data,
    read_recording,
    replay,
    replay_to_bus,
    summarize,
)
from services.service import Service

LINE = "rline"
FLOW = keys.feeder_flow(LINE, "api")
CONC = keys.measured_concentration(LINE, "nir1")
EVENT = keys.event(LINE, "feeder", "api")
TWIN = [sys.executable, "-m", "services.cli.main"]


def flow(t: float, seq: int, comp: str = "api", refilling: bool = False) -> FeederFlow:
    return FeederFlow(
        t=t,
        seq=seq,
        component=comp,
        mass_flow_kg_h=0.6 + 0.001 * seq,
        screw_speed_rpm=40.0,
        hopper_mass_kg=2.0,
        feed_factor_g_rev=0.25,
        refilling=refilling,
    )


def conc(t: float, seq: int) -> MeasuredConcentration:
    return MeasuredConcentration(
        t=t, seq=seq, sensor="nir1", component="api", concentration_pct_w_w=5 + math.sin(seq)
    )


def write_sample(path: Path, n: int, dt: float = 0.1, flush_every: int = 1000) -> list:
    """n messages alternating flow/concentration every dt; returns [(key, payload, t)]."""
    out = []
    with McapRecorder(path, flush_every=flush_every, flush_period_s=None) as rec:
        for i in range(n):
            key, msg = (FLOW, flow(i * dt, i // 2)) if i % 2 == 0 else (CONC, conc(i * dt, i // 2))
            rec.write_message(key, msg)
            out.append((key, msg.to_json_bytes(), msg.t))
    return out


def test_round_trip_bytes_schemas_and_layout(tmp_path):
    path = tmp_path / "rt.mcap"
    sent = write_sample(path, 500)
    rec = read_recording(path)
    assert not rec.truncated
    assert [(m.key, m.payload) for m in rec.messages] == [(k, p) for k, p, _ in sent]
    assert [m.log_time_ns for m in rec.messages] == [round(t * 1e9) for _, _, t in sent]
    assert rec.channels[FLOW].message_count == 250
    # the file itself, read with the mcap library: json encoding, jsonschema schemas, zstd chunks
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    topics = {c.topic: c for c in summary.channels.values()}
    assert set(topics) == {FLOW, CONC}
    for ch in topics.values():
        assert ch.message_encoding == "json"
        schema = summary.schemas[ch.schema_id]
        assert schema.encoding == "jsonschema"
        body = json.loads(schema.data)
        assert body["type"] == "object"
    assert summary.schemas[topics[FLOW].schema_id].name == "schemas.messages.FeederFlow"
    assert (
        "mass_flow_kg_h" in json.loads(summary.schemas[topics[FLOW].schema_id].data)["properties"]
    )
    assert len(summary.schemas) == 2  # each schema registered once
    assert {ci.compression for ci in summary.chunk_indexes} == {"zstd"}
    assert summary.statistics.message_count == 500
    # decoded messages equal what was sent
    assert rec.messages[0].decode() == flow(0.0, 0)


def test_truncated_file_recovers_every_complete_chunk(tmp_path):
    path = tmp_path / "full.mcap"
    sent = write_sample(path, 2000, flush_every=100)
    data = path.read_bytes()
    for frac in (0.1, 0.37, 0.5, 0.83, 0.99):
        cut = tmp_path / f"cut{frac}.mcap"
        cut.write_bytes(data[: int(len(data) * frac)])
        rec = read_recording(cut)
        assert rec.truncated and rec.error
        n = len(rec.messages)
        assert n % 100 == 0 and n > 0  # whole flushed chunks only
        assert n >= (frac * 2000) - 300  # nothing before the cut but the partial chunk is lost
        assert [m.payload for m in rec.messages] == [p for _, p, _ in sent[:n]]
        assert "TRUNCATED" in rec.loss_report() and str(n) in rec.loss_report()
        assert rec.bytes_read < rec.bytes_total == len(cut.read_bytes())


def flip_in_chunk(path: Path, k: int) -> tuple[bytes, int]:
    """The file's bytes with one byte flipped in the middle of its k-th chunk (0-based), and the
    messages that chunk held (from its message index)."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    c = chunks[k]
    data = bytearray(path.read_bytes())
    data[c.chunk_start_offset + c.chunk_length // 2] ^= 0xFF
    held = [m for m in read_recording(path).messages if c.message_start_time <= m.log_time_ns]
    held = [m for m in held if m.log_time_ns <= c.message_end_time]
    return bytes(data), len(held)


def test_a_corrupt_chunk_is_skipped_and_every_other_chunk_read(tmp_path):
    """One flipped byte in chunk 3 of 6: the other five chunks are read (through the chunk
    index; and in file order when the summary is cut off too), the loss is named (offset, plant
    time, messages), and `twin recover` writes a complete file that the mcap reader opens."""
    path = tmp_path / "six.mcap"
    sent = write_sample(path, 600, flush_every=100)
    data, n_bad = flip_in_chunk(path, 2)
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(data)
    rec = read_recording(bad)
    assert n_bad == 100 and not rec.truncated and not rec.complete
    assert len(rec.messages) == 500 and rec.messages_lost == 100
    [lost] = rec.lost
    assert "corrupt chunk" in lost.reason and lost.messages == 100
    good = [p for i, (_, p, _) in enumerate(sent) if not 200 <= i < 300]
    assert [m.payload for m in rec.messages] == good
    assert "100 messages lost" in rec.loss_report()
    # no summary either (cut after the last chunk): the file-order scan skips the same chunk
    cut = tmp_path / "flipped_cut.mcap"
    cut.write_bytes(data[: len(data) - 1500])
    scanned = read_recording(cut)
    assert scanned.truncated and [m.payload for m in scanned.messages] == good
    assert scanned.lost[0].messages == 100
    # twin recover: a complete file, footer and summary, that the mcap reader opens
    out = tmp_path / "recovered.mcap"
    r = subprocess.run([*TWIN, "recover", str(cut), str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "recovered 500 messages" in r.stdout
    with open(out, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary().statistics.message_count == 500
        assert [m.data for _, _, m in reader.iter_messages()] == good
    back = read_recording(out)
    assert back.complete and [m.sequence for m in back.messages] == [
        m.sequence for m in scanned.messages
    ]
    # an incomplete input is refused by the commands that read it, unless --allow-partial
    r = subprocess.run([*TWIN, "replay", str(bad), "--as-fast-as-possible"], capture_output=True)
    assert r.returncode == 2 and b"recording is incomplete" in r.stderr
    r = subprocess.run([*TWIN, "recover", str(bad), str(tmp_path / "no" / "x.mcap")])
    assert r.returncode == 2 and not (tmp_path / "no").exists()


CRASH_WRITER = textwrap.dedent(
    """
    import sys
    from services.recording import McapRecorder
    from schemas.messages import MeasuredConcentration
    rec = McapRecorder(sys.argv[1], flush_every=100, flush_period_s=None)
    i = 0
    while True:
        rec.write_message("twin/rline/pat/nir1/concentration", MeasuredConcentration(
            t=0.1 * i, seq=i, sensor="nir1", component="api", concentration_pct_w_w=i % 7))
        i += 1
        if i == 550:
            print("550", flush=True)
    """
)


def test_writer_killed_with_sigkill_still_replays(tmp_path):
    path = tmp_path / "crash.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", CRASH_WRITER, str(path)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout.readline().strip() == "550"
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    rec = read_recording(path)
    assert rec.truncated
    n = len(rec.messages)
    assert n >= 500 and n % 100 == 0
    assert [m.decode().seq for m in rec.messages] == list(range(n))
    published = []
    stats = replay(rec, lambda k, p: published.append(p), as_fast_as_possible=True)
    assert stats.published == n and published == [m.payload for m in rec.messages]


def test_replay_timing_within_5_percent_at_speed_10(tmp_path):
    """20 s of plant time at --speed 10 takes 2 s over the bus; every message arrives within
    5 % of the plant span of its due time."""
    path = tmp_path / "t.mcap"
    write_sample(path, 200, dt=0.1)  # 0 .. 19.9 s
    rec = read_recording(path)
    port = free_port()
    arrivals = []
    sink_cfg = BusConfig.loopback(port, listen=True, line=LINE)
    with Service("sink", sink_cfg, health_period_s=0, install_signal_handlers=False) as sink:
        for key in (FLOW, CONC):
            sink.subscribe(key, lambda k, m: arrivals.append((time.perf_counter(), m.t)))
        stats = replay_to_bus(
            rec,
            BusConfig.loopback(port, listen=False, line=LINE),
            speed=10,
            wait_for_subscribers_s=10,
            install_signal_handlers=False,
        )
        deadline = time.monotonic() + 5
        while len(arrivals) < 200 and time.monotonic() < deadline:
            time.sleep(0.01)
    data = sorted(arrivals)
    assert len(data) == 200
    span_wall = data[-1][0] - data[0][0]
    assert abs(span_wall - 1.99) / 1.99 < 0.05
    assert abs(stats.wall_s - 1.99) / 1.99 < 0.05
    w0, t0 = data[0]
    worst = max(abs((w - w0) - (t - t0) / 10) for w, t in data)
    assert worst < 0.05 * 1.99


def test_loop_shifts_time_and_seq(tmp_path):
    path = tmp_path / "l.mcap"
    write_sample(path, 10, dt=1.0)  # t = 0..9, seq 0..4 per key
    rec = read_recording(path)
    out = []
    stats = replay(
        rec,
        lambda k, p: out.append((k, json.loads(p))),
        as_fast_as_possible=True,
        loop=True,
        max_passes=3,
    )
    assert stats.passes == 3 and stats.published == 30
    ts = [d["t"] for _, d in out]
    assert ts == sorted(ts) and ts[10] == 10.0 and ts[-1] == 29.0
    flows = [d["seq"] for k, d in out if k == FLOW]
    assert flows == list(range(15))
    # the first pass is byte-identical
    first = []
    replay(rec, lambda k, p: first.append(p), as_fast_as_possible=True, loop=True, max_passes=1)
    assert first == [m.payload for m in rec.messages]


def test_record_while_replay_loses_no_message(tmp_path):
    """10,000 messages replayed as fast as possible by one process (`twin replay`) are all
    recorded by another (`twin record`), message for message and byte for byte."""
    src = tmp_path / "src.mcap"
    with McapRecorder(src, flush_period_s=None) as rec:
        for i in range(10_000):
            if i % 2:
                rec.write_message(FLOW, flow(0.5 * i, i // 2))
            else:
                rec.write_message(CONC, conc(0.5 * i, i // 2))
    out = tmp_path / "cap.mcap"
    ep = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    recorder = subprocess.Popen(
        [
            *TWIN,
            "record",
            str(out),
            "--listen",
            ep,
            "--count",
            "10000",
            "--no-health",
            "--duration",
            "60",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert recorder.stdout.readline().strip() == "ready"
        rp = subprocess.run(
            [
                *TWIN,
                "replay",
                str(src),
                "--connect",
                ep,
                "--as-fast-as-possible",
                "--wait-subscribers",
                "15",
            ],
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
        )
        assert rp.returncode == 0, rp.stderr
        r_out, r_err = recorder.communicate(timeout=60)
    finally:
        if recorder.poll() is None:
            recorder.kill()
    assert recorder.returncode == 0, r_err
    assert "recorded 10000 messages" in r_out and "stopped by count" in r_out
    a, b = read_recording(src), read_recording(out)
    for key in (FLOW, CONC):
        assert [m.payload for m in a.messages if m.key == key] == [
            m.payload for m in b.messages if m.key == key
        ]
    assert len(b.messages) == 10_000


def test_load_line_data(tmp_path):
    path = tmp_path / "line.mcap"
    with McapRecorder(path) as rec:
        for i in range(10):
            rec.write_message(FLOW, flow(float(i), i, refilling=i in (3, 4)))
            rec.write_message(keys.feeder_flow(LINE, "exc"), flow(float(i), i, comp="exc"))
            rec.write_message(CONC, conc(i + 0.5, i))
        rec.write_message(EVENT, Event(t=3.0, seq=0, kind="refill_start", source="api"))
        rec.write_message(EVENT, Event(t=5.0, seq=1, kind="refill_stop", source="api"))
        rec.write_message(
            keys.event(LINE, "tracer", "t1"),
            Event(
                t=2.0, seq=0, kind="tracer_pulse", source="tracer", component="api", mass_kg=0.01
            ),
        )
    signals, events = load_line_data(path)
    assert list(signals.index[:3]) == [0.0, 0.5, 1.0]
    assert signals.index.name == "t_s"
    assert signals.loc[0.0, "flow_api_kg_h"] == pytest.approx(0.6)
    assert signals.loc[2.0, "total_flow_kg_h"] == pytest.approx(2 * 0.602)
    assert math.isnan(signals.loc[0.5, "flow_api_kg_h"])
    assert signals.loc[0.5, "conc_nir1_api_pct_w_w"] == pytest.approx(5.0)
    assert signals.loc[3.0, "refilling_api"] == 1.0 and signals.loc[5.0, "refilling_api"] == 0.0
    assert signals.loc[1.5, "quality_nir1_api"] == "good"
    assert list(events["kind"]) == ["tracer_pulse", "refill_start", "refill_stop"]
    assert events.loc[0, "mass_kg"] == 0.01 and events.loc[0, "component"] == "api"


def test_load_line_data_keys_flows_by_feeder(tmp_path):
    """Two feeders of one component (the flows of ``twin/<line>/feeder/<id>/flow``) stay two
    signals: none overwrites the other, and the total is their sum."""
    path = tmp_path / "two.mcap"
    with McapRecorder(path) as rec:
        for i in range(5):
            for fid, q in (("api_a", 0.4), ("api_b", 0.8)):
                msg = flow(float(i), i).model_copy(update={"mass_flow_kg_h": q})
                rec.write_message(keys.feeder_flow(LINE, fid), msg)
    signals, _ = load_line_data(path)
    assert signals["flow_api_a_kg_h"].tolist() == [0.4] * 5
    assert signals["flow_api_b_kg_h"].tolist() == [0.8] * 5
    assert signals["total_flow_kg_h"].tolist() == pytest.approx([1.2] * 5)
    assert "flow_api_kg_h" not in signals


def test_cli_inspect_and_schemas(tmp_path):
    path = tmp_path / "i.mcap"
    write_sample(path, 300, flush_every=50)
    r = subprocess.run([*TWIN, "inspect", str(path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0
    assert FLOW in r.stdout and "150 msgs" in r.stdout and "schemas.messages.FeederFlow" in r.stdout
    assert "span 29.900 s" in r.stdout
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-2000])
    r = subprocess.run([*TWIN, "inspect", str(cut)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "TRUNCATED" in r.stdout
    assert r.stderr.strip().splitlines()[-1].startswith("error: recording is incomplete")
    r = subprocess.run(
        [*TWIN, "inspect", str(cut), "--allow-partial"], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0 and "TRUNCATED" in r.stdout
    assert summarize(read_recording(cut)) == r.stdout.strip()
    for bad, what in ((b"", "recording is empty"), (b"not mcap at all", "not an MCAP file")):
        other = tmp_path / "bad.mcap"
        other.write_bytes(bad)
        r = subprocess.run([*TWIN, "inspect", str(other)], capture_output=True, text=True)
        assert r.returncode == 2 and r.stderr.startswith(f"error: {what} (")
        assert len(r.stderr.strip().splitlines()) == 1
    r = subprocess.run(
        [*TWIN, "schemas", "export", str(tmp_path / "s")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0
    assert (tmp_path / "s" / "schemas.messages.OosAlert.json").exists()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_twin_record_finalizes_the_file_on_signal(tmp_path, sig):
    """`twin record` stopped by SIGINT/SIGTERM exits 0 and leaves a complete (indexed) file
    holding every message it received."""
    from services.bus import Publisher, barrier, open_session, ping

    out = tmp_path / "sig.mcap"
    ep = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [*TWIN, "record", str(out), "--listen", ep, "--no-health"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        with open_session(BusConfig(connect=[ep], line=LINE)) as s:
            pub = Publisher(s, CONC, MeasuredConcentration)
            deadline = time.monotonic() + 10
            while not pub.has_subscribers() and time.monotonic() < deadline:
                time.sleep(0.02)
            base = ping(s)
            for i in range(300):
                pub.publish(conc(0.1 * i, i))
            acks = barrier(s, sent={CONC: 300}, baseline=base, timeout_s=20)
            assert [h.service for h in acks] == ["recorder"]
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert "recorded 300 messages" in stdout and "stopped by signal" in stdout
    with open(out, "rb") as f:
        summary = make_reader(f).get_summary()  # a finalized file has its summary
    assert summary.statistics.message_count == 300
    assert [m.decode().seq for m in read_recording(out).messages] == list(range(300))
