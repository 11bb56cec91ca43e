"""``twin bridge opcua`` against the loopback OPC UA plant (asyncua server on loopback serving
the bundled recording in plant time): subscription gives the recording's messages exactly;
NaN, wrong type and out-of-range values are counted and rejected; a server killed and started
again is reconnected to, the samples missed counted and the gap marked on the bus; divert
commands of the twin's diverter are written back over Basic256Sha256 SignAndEncrypt with
user/password, a forged one (another identity of the secured bus) never is; writing without
security is refused unless told."""

from __future__ import annotations

import asyncio
import math
import threading
from pathlib import Path

import pytest

from schemas import keys
from schemas.bus_config import BusConfig
from schemas.line import LineSpec
from schemas.messages import DivertCommand, Event, ServiceHealth
from services.bus import Publisher, free_port, open_session
from services.opcua_bridge import OpcuaBridge, refusal, wait_for
from services.opcua_plant import LoopbackPlant, recording_messages
from services.security import (
    RouterDictionary,
    RunCredentials,
    as_identity,
    secured_router,
    write_private,
)

ROOT = Path(__file__).resolve().parents[2]
RECORDING = ROOT / "recordings" / "line1_30min.mcap"
LINE = "line1"


@pytest.fixture(scope="module")
def loop():
    lp = asyncio.new_event_loop()
    th = threading.Thread(target=lp.run_forever, daemon=True)
    th.start()
    yield lambda coro, timeout=120: asyncio.run_coroutine_threadsafe(coro, lp).result(timeout)
    lp.call_soon_threadsafe(lp.stop)
    th.join(5)


@pytest.fixture(scope="module")
def messages():
    return recording_messages(RECORDING)


def _peer_bus() -> BusConfig:
    return BusConfig(mode="peer", listen=[f"tcp/127.0.0.1:{free_port()}"], connect=[])


class _Tap:
    """A zenoh subscriber on the bridge's bus: every (key, payload) in arrival order."""

    def __init__(self, bus: BusConfig, key_expr: str) -> None:
        self.got: list[tuple[str, bytes]] = []
        self.session = open_session(BusConfig(mode="peer", listen=[], connect=bus.listen))
        self.sub = self.session.declare_subscriber(
            key_expr, lambda s: self.got.append((str(s.key_expr), s.payload.to_bytes()))
        )

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


async def _untyped_write(plant: LoopbackPlant, name: str, value, t: float) -> None:
    """A faulty server that ignores its node's data type (asyncua's server refuses a value of
    another type, so the test clears the node's value around the write)."""
    from asyncua import ua

    node = plant.server.iserver.aspace._nodes[plant.vars[name].nodeid]
    attribute = node.attributes[ua.AttributeIds.Value]
    attribute.value = None
    await plant.write(name, value, t)
    attribute.value = None


def test_subscription_reconnect_and_bad_values(loop, messages):
    port = free_port()
    plant = LoopbackPlant(messages, port=port, speed=200, insecure=True)
    loop(plant.start())
    cfg = plant.bridge_config()
    flow = cfg.feeders[0].nodes["mass_flow_kg_h"]
    cfg.feeders[0].nodes["mass_flow_kg_h"] = flow.model_copy(update={"valid_max": 50.0})
    bus = _peer_bus()
    published = []
    with OpcuaBridge(cfg, bus, insecure=True) as bridge:
        tap = _Tap(bus, keys.everything(LINE))
        bridge.on_publish = lambda k, m: published.append((k, m))
        assert bridge.connected.wait(20)
        # 1. subscription: the first 310 s of plant time, a tracer pulse included, arrive as
        # recorded (every field, t and seq)
        loop(plant.play(t_to=310))
        want = [(k, m) for k, m in messages if m.t <= 310 and not k.endswith("excipient/event")]
        assert wait_for(lambda: len(published) >= len(want), 20)
        assert sorted((k, m.t, m.model_dump_json()) for k, m in published) == sorted(
            (k, m.t, m.model_dump_json()) for k, m in want
        )
        assert wait_for(lambda: len(tap.got) >= len(want), 10)
        assert bridge.counters.get("incomplete") == 0
        # 2. bad values as a faulty PLC writes them: counted by reason, nothing published
        api, n0 = cfg.feeders[0].id, len(published)
        loop(plant.write(f"{api}.MassFlow", math.nan, 311.0))
        loop(_untyped_write(plant, f"{api}.MassFlow", None, 311.5))
        loop(_untyped_write(plant, f"{api}.MassFlow", "0.6 kg/h", 312.0))
        loop(plant.write(f"{api}.MassFlow", 99.0, 313.0))
        assert wait_for(lambda: bridge.counters.get("rejected_range") == 1, 10)
        assert bridge.counters.get("rejected_nan") == 1
        assert bridge.counters.get("rejected_type") == 2
        assert len(published) == n0
        # 3. the server killed and started again: reconnect, samples missed counted, gap marked
        loop(plant.stop())
        assert wait_for(lambda: not bridge.connected.is_set(), 20)
        plant2 = LoopbackPlant(messages, port=port, speed=200, insecure=True)
        loop(plant2.start())
        assert bridge.connected.wait(30)
        loop(plant2.play(t_from=400, t_to=420))
        assert wait_for(lambda: any(m.t == 420 for _, m in published), 20)
        assert bridge.counters.get("reconnects") == 1
        # flows and NIR: 311..399 never came (the bad values did not count as samples)
        assert bridge.counters.get("samples_missed") == 3 * 89
        after = [m for k, m in published if k == keys.feeder_flow(LINE, api) and m.t >= 400]
        before = [m for k, m in published if k == keys.feeder_flow(LINE, api) and m.t <= 310]
        assert after[0].seq == before[-1].seq + 1 + 89  # the close-loop sees a sequence gap
        gap_key = keys.event(LINE, "plant", "opcua")
        assert wait_for(lambda: sum(k == gap_key for k, _ in tap.got) == 3, 10)
        marks = [Event.model_validate_json(p) for k, p in tap.got if k == gap_key]
        assert all(e.kind == "note" and "missed 89 samples" in e.detail for e in marks)
        assert {e.t for e in marks} == {400.0}
        tap.close()
        loop(plant2.stop())


def _certificates(d: Path, loop) -> dict[str, Path]:
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    out = {}
    for who, use, uri in (
        ("server", ExtendedKeyUsageOID.SERVER_AUTH, "urn:powder-twin:loopback-plant"),
        ("client", ExtendedKeyUsageOID.CLIENT_AUTH, "urn:freeopcua:client"),
    ):
        key, cert = d / f"{who}.pem", d / f"{who}.der"
        loop(setup_self_signed_certificate(key, cert, uri, "localhost", [use], {"commonName": who}))
        out[who], out[f"{who}_key"] = cert, key
    return out


def test_divert_written_back_only_from_the_diverter_and_only_secured(loop, messages, tmp_path):
    """A secured twin bus (the router's access control: only ``oos`` publishes divert
    commands) and a Basic256Sha256 SignAndEncrypt OPC UA session with user/password."""
    certs = _certificates(tmp_path, loop)
    plant = LoopbackPlant(
        messages,
        port=free_port(),
        speed=400,
        certificate=certs["server"],
        private_key=certs["server_key"],
        users={"twin": "s3cret-pw"},
    )
    loop(plant.start())
    pw = tmp_path / "opcua.pw"
    write_private(pw, "s3cret-pw")
    security = {
        "policy": "Basic256Sha256",
        "mode": "SignAndEncrypt",
        "certificate": str(certs["client"]),
        "private_key": str(certs["client_key"]),
        "server_certificate": str(certs["server"]),
        "user": "twin",
        "password_file": str(pw),
    }
    cfg = plant.bridge_config(security=security)
    spec = LineSpec.from_file(ROOT / "services" / "configs" / "line1_5pct.yaml")
    router_port = free_port()
    spec = spec.model_copy(
        update={
            "bus": BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{router_port}"], connect=[])
        }
    )
    creds = RunCredentials.generate(["oos", "plant"])
    dictionary = RouterDictionary(creds, tmp_path)
    router = open_session(secured_router(spec.bus, spec, ["oos", "plant"], dictionary.path))
    client = spec.client_bus()
    for who in ("oos", "plant"):
        write_private(tmp_path / who, creds.passwords[who])
    as_plant = as_identity(client, "plant", password_file=tmp_path / "plant")
    as_oos = as_identity(client, "oos", password_file=tmp_path / "oos")
    # no security on either side: refused unless told
    assert "not secured" in refusal(cfg, client, insecure=False)
    assert "not signed and encrypted" in refusal(plant.bridge_config(), as_plant, insecure=False)
    assert refusal(plant.bridge_config(), client, insecure=True) is None
    with pytest.raises(ValueError, match="refusing to write divert commands"):
        OpcuaBridge(plant.bridge_config(), as_plant)
    try:
        with OpcuaBridge(cfg, as_plant) as bridge:
            assert bridge.connected.wait(30)
            loop(plant.play(t_to=5))
            assert wait_for(lambda: bridge.counters.get("published") >= 18, 10)
            cmd = DivertCommand(
                t=5.0,
                seq=0,
                command_id="c1",
                action="divert",
                t_start_s=17.2,
                t_end_s=73.2,
                reason="test",
            )
            forged = cmd.model_copy(update={"command_id": "forged", "seq": 1, "t": 6.0})
            with open_session(as_oos) as s_oos, open_session(as_plant) as s_plant:
                Publisher(s_plant, keys.divert_command(LINE), DivertCommand).publish(forged)
                Publisher(s_oos, keys.divert_command(LINE), DivertCommand).publish(cmd)
                assert wait_for(lambda: len(plant.commands) >= 1, 10)
                wait_for(lambda: len(plant.commands) >= 2, 1.5)
            assert [c["command_id"] for c in plant.commands] == ["c1"]
            assert DivertCommand.model_validate(plant.commands[0]) == cmd
            assert bridge.counters.get("divert_written") == 1
        # a wrong OPC UA password never connects
        bad = tmp_path / "bad.pw"
        write_private(bad, "wrong")
        wrong = plant.bridge_config(
            security={**security, "password_file": str(bad)}, reconnect_s=0.2
        )
        with OpcuaBridge(wrong, as_plant) as bridge:
            assert wait_for(lambda: bridge.counters.get("connect_failed") >= 1, 20)
            assert not bridge.connected.is_set()
    finally:
        loop(plant.stop())
        router.close()
        dictionary.close()


def test_the_bridge_as_a_supervised_service(loop, messages, tmp_path):
    """``services: [bridge]`` with ``opcua_bridge: BRIDGE.yaml``: ``twin up`` runs the bridge
    as identity ``bridge`` on its secured bus (the router lets it publish the plant's inputs);
    its messages reach a subscriber."""
    import yaml

    from services.supervisor import Supervisor

    plant = LoopbackPlant(messages, port=free_port(), speed=100, insecure=True)
    loop(plant.start())
    bridge_yaml = tmp_path / "bridge.yaml"
    bridge_yaml.write_text(
        yaml.safe_dump(plant.bridge_config(diverter=None).model_dump(mode="json"))
    )
    spec = LineSpec.from_file(ROOT / "services" / "configs" / "line1_5pct.yaml")
    spec = LineSpec.model_validate(
        {
            **spec.model_dump(),
            "bus": {"mode": "router", "listen": [f"tcp/127.0.0.1:{free_port()}"], "connect": []},
            "services": ["bridge"],
            "opcua_bridge": str(bridge_yaml),
            "state_dir": str(tmp_path / "state"),
        }
    )
    got: list[str] = []
    sessions: list[int] = []
    try:
        with Supervisor(spec, backoff_s=0.5) as sup:
            assert sup.wait_ready(60)
            with open_session(sup.client_config("operator")) as session:
                sub = session.declare_subscriber(
                    keys.feeder_flows(LINE), lambda s: got.append(str(s.key_expr))
                )
                health = session.declare_subscriber(
                    keys.service_health(LINE, "bridge"),
                    lambda s: sessions.append(
                        ServiceHealth.model_validate_json(s.payload.to_bytes()).counters.get(
                            "sessions", 0
                        )
                    ),
                )
                assert wait_for(lambda: max(sessions, default=0) >= 1, 30)  # OPC UA connected
                loop(plant.play(t_to=20))
                assert wait_for(lambda: len(got) >= 42, 20)
                sub.undeclare()
                health.undeclare()
    finally:
        loop(plant.stop())
    assert sorted(set(got)) == [keys.feeder_flow(LINE, "api"), keys.feeder_flow(LINE, "excipient")]


def _oos_outputs(published: list) -> list:
    """The diverter's decisions (``twin_core.online.oos.OosCore``, measured NIR and the traced
    feeder flows, no blender) on what the bridge published."""
    from schemas.messages import FeederFlow, MeasuredConcentration
    from twin_core.online.oos import OosCore

    spec = LineSpec.from_file(ROOT / "services" / "configs" / "line1_5pct.yaml")
    core = OosCore(spec.model_copy(update={"services": ["oos"]}))
    out = []
    for k, m in sorted(published, key=lambda km: km[1].t):
        if isinstance(m, FeederFlow):
            out += core.flow(keys.parse_key(k).id, m.t, m.mass_flow_kg_h, m.refilling)
        elif isinstance(m, MeasuredConcentration):
            out += core.measured(m.component, m.t, m.concentration_pct_w_w)
    return out + core.end_of_stream()


def test_values_stamped_in_the_future_are_refused_and_displace_nothing(loop, messages):
    """Six NIR values three times the upper limit, stamped 340 s ahead of the plant (a forged
    write, a PLC clock jump): refused and counted (``future``); the real samples after them
    are all published (none taken for ``late``) and the diverter decides nothing."""
    plant = LoopbackPlant(messages, port=free_port(), speed=200, insecure=True)
    loop(plant.start())
    cfg = plant.bridge_config()
    sid = cfg.sensor.id
    nir = keys.measured_concentration(LINE, sid)
    published = []
    with OpcuaBridge(cfg, _peer_bus(), insecure=True) as bridge:
        bridge.on_publish = lambda k, m: published.append((k, m))
        assert bridge.connected.wait(20)
        loop(plant.play(t_to=60))
        assert wait_for(lambda: any(k == nir and m.t == 60 for k, m in published), 20)
        for i in range(6):
            loop(plant.write(f"{sid}.Concentration", 17.25, 400.0 + i))
        loop(plant.play(t_from=61, t_to=80))
        assert wait_for(lambda: any(k == nir and m.t == 80 for k, m in published), 20)
        assert wait_for(lambda: bridge.counters.get("future") == 6, 10)
        assert bridge.health()["future"] == 6  # in the health report (twin status)
        assert bridge.counters.get("late") == 0
    got = sorted(m.t for k, m in published if k == nir)
    assert got == [float(t) for t in range(0, 81)]
    assert not [o for o in _oos_outputs(published) if o.kind == "alert"]
    loop(plant.stop())


def test_the_log_of_a_bridged_run_is_bounded(loop, messages, caplog):
    """300 s of plant time through the bridge (13 node updates a second): a handful of INFO
    lines, not one per OPC UA update or publish (asyncua's per-publish lines are DEBUG)."""
    import logging

    caplog.set_level(logging.INFO)
    plant = LoopbackPlant(messages, port=free_port(), speed=200, insecure=True)
    loop(plant.start())
    with OpcuaBridge(plant.bridge_config(), _peer_bus(), insecure=True) as bridge:
        assert bridge.connected.wait(20)
        loop(plant.play(t_to=300))
        assert wait_for(lambda: bridge.counters.get("published") >= 904, 20)
    loop(plant.stop())
    lines = [r for r in caplog.records if r.levelno >= logging.INFO]
    text = sum(len(r.getMessage()) for r in lines)
    assert len(lines) <= 20 and text <= 4000, (len(lines), text)
