"""Round-trip latency of a 200-byte message between two processes over zenoh on loopback.

Method: a spawned child process echoes every message it receives; the parent sends one message,
waits for its echo, and repeats (``N`` round trips after ``WARMUP``). Two paths side by side:

- raw zenoh: 200 random bytes, ``session.put`` / Python callback subscriber (the peer baseline);
- typed twin bus: an ``Event`` whose JSON is 200 bytes, ``Publisher.publish`` (validate +
  encode) and ``TypedSubscriber`` (decode + validate + time-order check) at both ends.

Prints p50/p90/p99 in microseconds and the typed/raw ratios.
Run: ``python benchmarks/bus_latency.py [N]``.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
import threading
import time

import numpy as np
from machine import describe

from services.bus import free_port

WARMUP = 200


def typed_event(seq: int):
    from schemas.messages import Event

    msg = Event(t=float(seq), seq=seq, kind="note", source="bench", detail="")
    pad = 200 - len(msg.to_json_bytes())
    return msg.model_copy(update={"detail": "x" * pad})


def echo_child(port: int, mode: str, ready, stop) -> None:
    from schemas.bus_config import BusConfig
    from schemas.messages import Event
    from services.bus import Counters, Publisher, TypedSubscriber, open_session

    with open_session(BusConfig.loopback(port, listen=False)) as s:
        if mode == "raw":
            pub = s.declare_publisher("bench/pong")
            s.declare_subscriber("bench/ping", lambda sample: pub.put(sample.payload))
        else:
            pub = Publisher(s, "twin/bench/x/pong/event", Event, counters=Counters())
            TypedSubscriber(s, "twin/bench/x/ping/event", lambda k, m: pub.publish(m), model=Event)
        ready.set()
        stop.wait(120)


def measure(mode: str, n: int) -> np.ndarray:
    import zenoh

    from schemas.bus_config import BusConfig
    from schemas.messages import Event
    from services.bus import Counters, Publisher, TypedSubscriber, open_session

    port = free_port()
    ctx = mp.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    child = ctx.Process(target=echo_child, args=(port, mode, ready, stop))
    got = threading.Event()
    rtts = []
    with open_session(BusConfig.loopback(port, listen=True)) as s:
        child.start()
        try:
            ready.wait(60)
            if mode == "raw":
                pub = s.declare_publisher(
                    "bench/ping", congestion_control=zenoh.CongestionControl.BLOCK
                )
                s.declare_subscriber("bench/pong", lambda sample: got.set())
                payload = os.urandom(200)

                def send(i: int) -> None:
                    pub.put(payload)
            else:
                tpub = Publisher(s, "twin/bench/x/ping/event", Event, counters=Counters())
                TypedSubscriber(s, "twin/bench/x/pong/event", lambda k, m: got.set(), model=Event)

                def send(i: int) -> None:
                    tpub.publish(typed_event(i))

            time.sleep(1.0)
            for i in range(WARMUP + n):
                got.clear()
                t0 = time.perf_counter_ns()
                send(i)
                if not got.wait(5):
                    raise RuntimeError(f"{mode}: no echo for message {i}")
                if i >= WARMUP:
                    rtts.append(time.perf_counter_ns() - t0)
        finally:
            stop.set()
            child.join(30)
    return np.array(rtts) / 1000.0


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 3000
    print(f"{describe()}; {n} round trips after {WARMUP} warm-up")
    assert len(typed_event(WARMUP + n).to_json_bytes()) == 200
    res = {}
    for mode in ("raw", "typed"):
        us = measure(mode, n)
        res[mode] = {p: float(np.percentile(us, p)) for p in (50, 90, 99)}
        print(
            f"{mode:>6}: p50 {res[mode][50]:7.1f} us  p90 {res[mode][90]:7.1f} us  "
            f"p99 {res[mode][99]:7.1f} us"
        )
    for p in (50, 99):
        print(f"typed/raw ratio p{p}: {res['typed'][p] / res['raw'][p]:.2f}")


if __name__ == "__main__":
    main()
