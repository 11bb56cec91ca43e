"""A subscriber that joins a live line gets every publisher's whole history, each sample once.

Reference: the contract a restarted service relies on (``services.common`` module docstring) --
the payloads delivered for each key are exactly the publisher's sequence 0..n-1, with no gap and
no repeat, whatever the publishers were doing when the subscriber joined. Publishers run in
another process (separate zenoh client session, as in the live twin), behind a loopback router.
"""

from __future__ import annotations

import multiprocessing as mp
import threading
import time

import zenoh
import zenoh.ext as zext

from schemas.bus_config import BusConfig
from services.bus import HistoryFeed, free_port, open_session

N_KEYS = 5


def _bus(port: int, mode: str) -> BusConfig:
    if mode == "router":
        return BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], timestamping=True)
    return BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"], timestamping=True)


def _publish(port: int, started, stop) -> None:
    """Five advanced publishers with caches, one sample each every ~3 ms, payload = its index."""
    with open_session(_bus(port, "client")) as s:
        pubs = [
            zext.declare_advanced_publisher(
                s,
                f"twin/t/feeder/k{i}/flow",
                cache=zext.CacheConfig(max_samples=20000),
                sample_miss_detection=zext.MissDetectionConfig(heartbeat=0.5),
                publisher_detection=True,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            for i in range(N_KEYS)
        ]
        i = 0
        while not stop.is_set():
            for p in pubs:
                p.put(str(i).encode())
            i += 1
            if i == 200:
                started.set()
            time.sleep(0.003)
        for p in pubs:
            p.undeclare()


def test_late_wildcard_subscriber_gets_every_publishers_history_once():
    port = free_port()
    ctx = mp.get_context("spawn")
    started, stop = ctx.Event(), ctx.Event()
    with open_session(_bus(port, "router")):
        proc = ctx.Process(target=_publish, args=(port, started, stop), daemon=True)
        proc.start()
        try:
            assert started.wait(60), "publisher process did not start"
            for _join in range(3):
                got: dict[str, list[int]] = {}
                lock = threading.Lock()

                def sink(key: str, payload: bytes, got=got, lock=lock) -> None:
                    with lock:
                        got.setdefault(key, []).append(int(payload))

                with open_session(_bus(port, "client")) as s:
                    feed = HistoryFeed(s, "twin/t/feeder/*/flow", sink)
                    assert feed.history_complete.wait(15)
                    time.sleep(0.5)  # live samples keep coming after the history
                    feed.undeclare()
                assert len(got) == N_KEYS, sorted(got)
                for key, vals in got.items():
                    vals = sorted(vals)
                    # complete from the first sample, no gap, no duplicate
                    assert vals[0] == 0, (key, vals[:5])
                    assert vals == list(range(vals[-1] + 1)), (key, len(vals), vals[-1])
                assert feed.n_history > 0
                time.sleep(0.2)
        finally:
            stop.set()
            proc.join(10)
