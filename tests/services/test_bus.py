"""The bus: two processes exchanging typed messages over zenoh on loopback (spawned, never
forked), rejection and counting of invalid payloads, liveliness, health, clean shutdown."""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from schemas import keys
from schemas.bus_config import BusConfig
from schemas.messages import FeederFlow, MeasuredConcentration, ServiceHealth
from services.bus import (
    Counters,
    Publisher,
    barrier,
    free_port,
    live_services,
    open_session,
    ping,
)
from services.service import Service

LINE = "tline"
IN_KEY = keys.measured_concentration(LINE, "in")
OUT_KEY = keys.measured_concentration(LINE, "out")


def wait_for(predicate, timeout_s: float = 10.0, period_s: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return predicate()


def _echo_child(port: int, n: int, ready) -> None:
    """Child process: echo every concentration on IN_KEY to OUT_KEY with the value doubled."""
    cfg = BusConfig.loopback(port, listen=False, line=LINE)
    with Service("echo", cfg, health_period_s=0.2, install_signal_handlers=False) as svc:
        pub = svc.publisher(OUT_KEY, MeasuredConcentration)
        done = []

        def on_msg(key, msg):
            pub.publish(
                msg.model_copy(update={"concentration_pct_w_w": 2 * msg.concentration_pct_w_w})
            )
            done.append(1)

        svc.subscribe(IN_KEY, on_msg, model=MeasuredConcentration)
        ready.set()
        wait_for(lambda: len(done) >= n, timeout_s=30)
        time.sleep(0.3)


def test_two_processes_exchange_messages():
    port = free_port()
    n = 200
    ctx = mp.get_context("spawn")
    ready = ctx.Event()
    child = ctx.Process(target=_echo_child, args=(port, n, ready))
    got = []
    cfg = BusConfig.loopback(port, listen=True, line=LINE)
    with Service("driver", cfg, health_period_s=0, install_signal_handlers=False) as svc:
        child.start()
        try:
            svc.subscribe(OUT_KEY, lambda k, m: got.append(m), model=MeasuredConcentration)
            assert ready.wait(30)
            assert wait_for(lambda: "echo" in live_services(svc.session, LINE, 0.5), 15)
            pub = svc.publisher(IN_KEY, MeasuredConcentration)
            time.sleep(0.3)  # let the child's subscription reach us
            for i in range(n):
                pub.publish(dict(t=0.5 * i, sensor="in", component="api", concentration_pct_w_w=i))
            assert wait_for(lambda: len(got) >= n, 20)
        finally:
            child.join(30)
    assert child.exitcode == 0
    assert [m.seq for m in got] == list(range(n))
    assert [m.concentration_pct_w_w for m in got] == [2.0 * i for i in range(n)]
    assert svc.counters.get("received") == n
    assert svc.counters.get("published") == n


def test_invalid_payloads_are_counted_and_skipped():
    """Bad JSON, schema violations (NaN, negative flow, missing field), time going backwards and
    unknown keys are rejected with a reason, counted, and the subscriber keeps working."""
    port = free_port()
    key = keys.feeder_flow(LINE, "api")
    good = dict(
        component="api",
        mass_flow_kg_h=1.0,
        screw_speed_rpm=30,
        hopper_mass_kg=2,
        feed_factor_g_rev=0.5,
    )
    got = []
    with (
        Service(
            "sink",
            BusConfig.loopback(port, listen=True, line=LINE),
            health_period_s=0,
            install_signal_handlers=False,
        ) as sink,
        open_session(BusConfig.loopback(port, listen=False, line=LINE)) as src,
    ):
        sink.subscribe("twin/tline/feeder/**", lambda k, m: got.append(m))
        time.sleep(1.0)
        pub = Publisher(src, key, FeederFlow, check_time=False)
        pub.publish(dict(t=1.0, **good))
        src.put(key, b"{not json")
        src.put(key, b'{"t": 2.0, "seq": 1}')
        src.put(
            key,
            FeederFlow(t=2.0, seq=1, **good)
            .model_dump_json()
            .replace('"mass_flow_kg_h":1.0', '"mass_flow_kg_h":NaN'),
        )
        src.put(
            key,
            FeederFlow(t=2.0, seq=1, **good)
            .model_dump_json()
            .replace('"mass_flow_kg_h":1.0', '"mass_flow_kg_h":-1.0'),
        )
        pub.publish(dict(t=0.5, **good))  # backwards in time
        src.put("twin/tline/feeder/api/unknownsignal", b"{}")
        pub.publish(dict(t=3.0, **good))
        assert wait_for(lambda: len(got) == 2 and sink.counters.rejected() == 6, 10)
        health = sink.health()
    assert [m.t for m in got] == [1.0, 3.0]
    c = health.counters
    assert c["received"] == 2
    assert c["rejected_json"] == 1
    assert c["rejected_schema"] == 3  # missing fields, NaN, negative flow
    assert c["rejected_time"] == 1
    assert c["rejected_unknown"] == 1
    assert "unknownsignal" in health.last_error


def test_publish_validates():
    port = free_port()
    with open_session(BusConfig.loopback(port, listen=True)) as s:
        pub = Publisher(s, keys.feeder_flow("l", "api"), FeederFlow, counters=Counters())
        with pytest.raises(ValueError, match="mass_flow_kg_h"):
            pub.publish(
                dict(
                    t=0,
                    component="api",
                    mass_flow_kg_h=-1,
                    screw_speed_rpm=1,
                    hopper_mass_kg=1,
                    feed_factor_g_rev=1,
                )
            )
        with pytest.raises(TypeError, match="must be a FeederFlow"):
            pub.publish(
                MeasuredConcentration(
                    t=0, seq=0, sensor="s", component="c", concentration_pct_w_w=1
                )
            )
        with pytest.raises(ValueError, match=r"got .\*."):
            Publisher(s, "twin/l/feeder/*/flow", FeederFlow)
        assert pub.counters.get("published") == 0
        good = dict(
            component="api",
            mass_flow_kg_h=1,
            screw_speed_rpm=1,
            hopper_mass_kg=1,
            feed_factor_g_rev=1,
        )
        pub.publish(dict(t=5.0, **good))
        with pytest.raises(ValueError, match=r"t must not go backwards .* got t=4.0 after 5.0"):
            pub.publish(dict(t=4.0, **good))
        pub.publish(dict(t=5.0, **good))
        assert pub.counters.get("published") == 2 and pub.seq == 2


SERVICE_SCRIPT = textwrap.dedent(
    """
    import sys, time
    from schemas.bus_config import BusConfig
    from services.service import Service
    with Service("sleeper", BusConfig.loopback(int(sys.argv[1]), listen=False, line="tline"),
                 health_period_s=0.1) as svc:
        svc.subscribe("twin/**", lambda k, m: None)
        print("ready", flush=True)
        code = svc.run()
    print("clean exit", flush=True)
    sys.exit(code)
    """
)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_service_shuts_down_cleanly_on_signal(sig):
    port = free_port()
    health = []
    cfg = BusConfig.loopback(port, listen=True, line=LINE)
    with Service("watch", cfg, health_period_s=0, install_signal_handlers=False) as watch:
        watch.subscribe(
            keys.service_health(LINE, "sleeper"), lambda k, m: health.append(m), model=ServiceHealth
        )
        proc = subprocess.Popen(
            [sys.executable, "-c", SERVICE_SCRIPT, str(port)],
            stdout=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        try:
            assert proc.stdout.readline().strip() == "ready"
            assert wait_for(lambda: "sleeper" in live_services(watch.session, LINE, 0.5), 15)
            assert wait_for(lambda: len(health) >= 2, 10)
            proc.send_signal(sig)
            out, _ = proc.communicate(timeout=15)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == 0
        assert "clean exit" in out
        assert wait_for(lambda: health[-1].state == "stopping", 5)
        assert wait_for(lambda: "sleeper" not in live_services(watch.session, LINE, 0.5), 10)
    assert all(h.service == "sleeper" and h.pid == proc.pid for h in health)
    assert [h.seq for h in health] == list(range(len(health)))


def test_barrier_returns_after_every_service_processed_the_burst():
    """After a burst to a slow consumer, the barrier returns only once the consumer has every
    message, so the sender may close its session without losing its queued messages."""
    port = free_port()
    n = 3000
    seen = []

    def slow(key, msg):
        time.sleep(0.0002)
        seen.append(msg.seq)

    cfg = BusConfig.loopback(port, listen=True, line=LINE)
    with Service("slow", cfg, health_period_s=0, install_signal_handlers=False) as svc:
        svc.subscribe(IN_KEY, slow, model=MeasuredConcentration)
        with open_session(BusConfig.loopback(port, listen=False, line=LINE)) as src:
            pub = Publisher(src, IN_KEY, MeasuredConcentration)
            assert wait_for(pub.has_subscribers, 10)
            baseline = ping(src)
            for i in range(n):
                pub.publish(dict(t=i, sensor="in", component="api", concentration_pct_w_w=1.0))
            replies = barrier(src, timeout_s=20, sent={IN_KEY: n}, baseline=baseline)
            count_at_barrier = len(seen)
    assert [h.service for h in replies] == ["slow"], replies
    assert count_at_barrier == n
    assert replies[0].counters["received"] == n


def test_router_routes_between_clients():
    """The documented topology for more than two processes: a router and clients."""
    port = free_port()
    router_cfg = BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[], line=LINE)
    client_cfg = BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"], line=LINE)
    got = []
    with (
        Service("router", router_cfg, health_period_s=0, install_signal_handlers=False),
        Service("a", client_cfg, health_period_s=0, install_signal_handlers=False) as a,
        Service("b", client_cfg, health_period_s=0, install_signal_handlers=False) as b,
    ):
        b.subscribe(IN_KEY, lambda k, m: got.append(m.seq), model=MeasuredConcentration)
        pub = a.publisher(IN_KEY, MeasuredConcentration)
        assert wait_for(pub.has_subscribers, 10)
        for i in range(50):
            pub.publish(dict(t=i, sensor="in", component="api", concentration_pct_w_w=1.0))
        assert wait_for(lambda: len(got) == 50, 10)
        assert live_services(a.session, LINE) == ["a", "b", "router"]
    assert got == list(range(50))
