"""The live twin end to end: supervisor, services as separate processes, loopback zenoh.

Two supervised runs share the module (multi-process start-up is slow):

- run A replays a recording with two known feeder disturbances through feeder, blender, oos and
  recorder, kills the oos service with SIGKILL between them, and injects malformed messages;
- run B replays a clean recording that was cut short (as by a crash of its writer).

Reference for the alert windows: RTD traceability of the injected disturbance (Engisch & Muzzio
2016; seed ch. 6 lot boundaries): [t_start + t(F=0.5 %), t_end + t(F=99.5 %)] with E(t) of the
configured blender (seed Table 6.2), computed here from the known disturbance, not from the data.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest
import zenoh
from twin_view import expected_windows, plant_replay, wait_until

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import DivertCommand, OosAlert, ServiceHealth
from services.bus import free_port, open_session
from services.recording import read_recording, write_messages
from services.supervisor import Supervisor
from twin_core.plant.messages import simulate_messages

CONFIG = Path(__file__).resolve().parents[2] / "services" / "configs" / "line1.yaml"
DISTURBANCES = [
    {"feeder": "api", "t_s": 300.0, "delta_kg_h": 0.6, "duration_s": 30.0},
    {"feeder": "api", "t_s": 1200.0, "delta_kg_h": -0.6, "duration_s": 40.0},
]

#: (plant time, rpm) of the plant's blade-speed reports
BLADE_SPEEDS = [(0.0, 100.0), (1500.0, 75.0)]


def make_spec(port: int, state: Path, services: list[str]) -> LineSpec:
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{port}"], "connect": []},
        services=services,
        state_dir=str(state),
        record_path="run.mcap",
    )
    return LineSpec.model_validate(data)


class Collector:
    """Every alert / divert / health message seen by a test-side subscriber (duplicates kept),
    as the run's operator."""

    def __init__(self, sup: Supervisor) -> None:
        self.alerts: list[OosAlert] = []
        self.diverts: list[DivertCommand] = []
        self.health: dict[str, ServiceHealth] = {}
        self.positions: set[tuple[str, float, int]] = set()
        self.resent = 0
        self.lock = threading.Lock()
        self.session = open_session(sup.client_config("operator"))
        line = sup.spec.name
        self.subs = [
            self.session.declare_subscriber(keys.oos_alert(line), self._cb(OosAlert)),
            self.session.declare_subscriber(keys.divert_command(line), self._cb(DivertCommand)),
            self.session.declare_subscriber(keys.services_health(line), self._cb(ServiceHealth)),
        ]

    def _cb(self, model):
        def on(sample: zenoh.Sample) -> None:
            msg = model.model_validate_json(sample.payload.to_bytes())
            with self.lock:
                position = (model.__name__, msg.t, msg.seq)
                if model is not ServiceHealth and position in self.positions:
                    # the same message again (a restarted diverter re-sends what it logged just
                    # before it died: services.common.OutputLog); dropped as every subscriber of
                    # the contract does (services.bus.StreamOrder), and counted
                    self.resent += 1
                    return
                self.positions.add(position)
                if model is OosAlert:
                    self.alerts.append(msg)
                elif model is DivertCommand:
                    self.diverts.append(msg)
                else:
                    self.health[msg.service] = msg

        return zenoh.handlers.Callback(on, lambda: None)

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


@pytest.fixture(scope="module")
def run_a(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("live_a")
    spec = make_spec(free_port(), tmp, ["feeder", "blender", "oos", "recorder"])
    # the plant reports its blade speed, and changes it after the second disturbance's window
    run, msgs = simulate_messages(
        spec, 1800.0, seed=3, disturbances=DISTURBANCES, blade_speeds=BLADE_SPEEDS
    )
    rec_path = tmp / "disturbed.mcap"
    write_messages(rec_path, msgs)
    rec = read_recording(rec_path)
    out: dict = {"spec": spec, "n_recorded": len(rec.messages)}
    sup = Supervisor(spec, backoff_s=0.2).start()
    col = None
    try:
        assert sup.wait_ready(120), f"services not ready: alive {sup.alive}"
        col = Collector(sup)
        with plant_replay(rec, sup) as rp:
            killer_done = threading.Event()

            def kill_oos() -> None:
                # after the first alert, before the second disturbance reaches the inlet; once
                # the alert is in the diverter's output log (a kill between its publication and
                # that write, a few microseconds, makes the restarted diverter publish it again;
                # one right after the write can leave it, or the `.final` logged next, in the
                # send queue: the restarted diverter sends those again with their positions,
                # docs/services.md, "Restarts")
                log = sup.run_dir / "oos.published"
                wait_until(
                    lambda: (
                        len(col.alerts) >= 1
                        and log.exists()
                        and col.alerts[0].alert_id
                        in {ln.split("\t")[0] for ln in log.read_text().split("\n")}
                    ),
                    60,
                )
                pid = sup.pids()["oos"]
                os.kill(pid, signal.SIGKILL)
                out["killed_pid"] = pid
                out["alerts_before_kill"] = len(col.alerts)
                killer_done.set()

            threading.Thread(target=kill_oos, daemon=True).start()
            # malformed input on the bus, mid-run
            bad = rp.svc.session.declare_publisher(keys.feeder_flow("line1", "api"))
            for payload in (b"not json", b'{"t": 1, "seq": 0}', b'{"t": NaN}'):
                bad.put(payload)
            out["n_sent"] = rp.replay(speed=300.0).published
            killer_done.wait(60)
            # the restarted oos catches up from the publishers' history
            ok = wait_until(lambda: len(col.alerts) >= 2, 90)
            assert ok, (
                col.alerts,
                {k: (h.state, h.t, h.counters) for k, h in col.health.items()},
                sup.children["oos"].exit_codes,
            )
            time.sleep(1.5)  # anything duplicated would arrive now
            bad.undeclare()
        out["restarts"] = sup.children["oos"].restarts
        out["health"] = dict(col.health)
    finally:
        out["codes"] = sup.stop()
        if col is not None:
            col.close()
    out["alerts"] = list(col.alerts)
    out["diverts"] = list(col.diverts)
    out["recorded"] = read_recording(sup.run_dir / "run.mcap")
    return out


def test_known_disturbances_give_exactly_the_expected_alert_windows(run_a):
    spec = run_a["spec"]
    alerts = sorted(run_a["alerts"], key=lambda a: a.t_start_s)
    assert len(alerts) == 2, ([a.alert_id for a in alerts], run_a["health"]["oos"].counters)
    for a, (lo, hi) in zip(alerts, expected_windows(spec, DISTURBANCES)):
        assert abs(a.t_start_s - lo) <= spec.dt_s, (a.t_start_s, lo)
        assert abs(a.t_end_s - hi) <= spec.dt_s, (a.t_end_s, hi)
        assert a.component == "api" and abs(a.peak_deviation_pct_w_w) > a.limit_pct_w_w
    # divert commands: an early one (issued before the window starts) and the final window
    for a in alerts:
        cmds = {d.command_id: d for d in run_a["diverts"] if d.alert_id == a.alert_id}
        assert set(cmds) == {f"{a.alert_id}.open", f"{a.alert_id}.final"}
        assert cmds[f"{a.alert_id}.open"].t < a.t_start_s  # flagged before it reaches the outlet
        assert cmds[f"{a.alert_id}.final"].t_start_s == a.t_start_s
        assert cmds[f"{a.alert_id}.final"].t_end_s == a.t_end_s


def test_sigkill_restarts_the_service_without_loss_or_duplicate(run_a):
    assert run_a["restarts"] >= 1
    assert run_a["health"]["supervisor"].counters["restarts_oos"] >= 1  # seen by `twin status`
    assert run_a["alerts_before_kill"] == 1
    ids = [a.alert_id for a in run_a["alerts"]]
    assert len(ids) == len(set(ids)) == 2
    cmd_ids = [d.command_id for d in run_a["diverts"]]
    assert len(cmd_ids) == len(set(cmd_ids)) == 4


def test_malformed_messages_are_counted_and_ignored(run_a):
    h = run_a["health"]["blender"].counters
    assert h.get("rejected_json", 0) >= 1  # "not json"
    assert h.get("rejected_schema", 0) >= 2  # missing fields; NaN time
    assert run_a["health"]["blender"].state == "running"


def test_no_message_dropped_and_recorded(run_a):
    rec = run_a["recorded"]
    counts: dict[str, int] = {}
    for m in rec.messages:
        counts[m.key] = counts.get(m.key, 0) + 1
    n_ticks = 1801
    for f in ("api", "excipient"):  # the plant's flows, as replayed (no second copy)
        assert counts[keys.feeder_flow("line1", f)] == n_ticks
    assert not [k for k in counts if "/loadcell/" in k]
    assert counts["twin/line1/blender/outlet/predicted"] == 2 * n_ticks
    assert counts["twin/line1/oos/alert"] == 2


def test_a_recorded_blade_speed_change_switches_the_blender_model(run_a):
    """The recording's blade speed drops to 75 rpm at 1,500 s: the compartment blender switches
    its model from that plant time, and the switch is on the twin's own recording. On a loaded
    machine the drive message can reach the blender after its predictions have passed 1,500 s
    (the wait for its producer's progress ran out): then the switch applies from the first
    prediction after, and never silently: counted in ``adopted_late`` with its lateness."""
    rec = run_a["recorded"]
    used = {}
    for m in rec.messages:
        if m.key == keys.blender_model_in_use("line1"):
            msg = m.decode()
            used[msg.seq] = (msg.reason, msg.applies_from_s, msg.blade_speed_rpm)
    switches = [used[k] for k in sorted(used)]
    assert switches[0][0] == "start" and switches[0][2] == 100.0
    assert [(r, rpm) for r, _, rpm in switches[1:]] == [("blade_speed", 75.0)]
    t_switch = switches[1][1]
    if t_switch != 1500.0:
        h = run_a["health"]["blender"].counters
        assert h.get("adopted_late", 0) >= 1, (t_switch, h)
        assert 1500.0 < t_switch <= 1500.0 + h["adopted_late_max_ms"] / 1000.0 + 1e-6, (t_switch, h)


@pytest.fixture(scope="module")
def run_b(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("live_b")
    spec = make_spec(free_port(), tmp, ["blender", "oos"])
    _, msgs = simulate_messages(spec, 1200.0, seed=4)
    path = tmp / "clean.mcap"
    write_messages(path, msgs)
    data = path.read_bytes()
    cut = tmp / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    rec = read_recording(cut)
    out: dict = {"rec": rec, "n_full": len(msgs)}
    sup = Supervisor(spec).start()
    col = None
    try:
        assert sup.wait_ready(120)
        col = Collector(sup)
        with plant_replay(rec, sup) as rp:
            out["n_sent"] = rp.replay(as_fast_as_possible=True).published
            assert wait_until(
                lambda: "oos" in col.health and col.health["oos"].t >= rec.messages[-1].t - 1, 60
            )
            time.sleep(2.5)  # past the idle release of the diverter
        out["alerts"] = list(col.alerts)
        out["diverts"] = list(col.diverts)
        out["health"] = dict(col.health)
    finally:
        sup.stop()
        if col is not None:
            col.close()
    return out


def test_clean_recording_cut_short_replays_and_yields_no_alert(run_b):
    rec = run_b["rec"]
    assert rec.truncated and 0 < len(rec.messages) < run_b["n_full"]
    assert run_b["n_sent"] == len(rec.messages)
    assert run_b["alerts"] == [] and run_b["diverts"] == []
    oos = run_b["health"]["oos"].counters
    assert oos.get("received", 0) >= len(rec.messages)  # every replayed message processed


def test_status_and_alerts_json_shape(run_a):
    """`twin alerts --json` prints each alert once as the wire model (schema round trip)."""
    for a in run_a["alerts"]:
        back = OosAlert.model_validate_json(json.dumps(a.model_dump(mode="json")))
        assert back == a
