"""DEM service over the bus: a job requested by a zenoh query runs, streams its progress and
publishes its result; bad requests are refused with a reason and the service keeps serving."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
import zenoh

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import DemJobProgress, DemJobRequest, DemJobResult
from services.bus import free_port, open_session
from services.supervisor import Supervisor

CONFIG = Path(__file__).resolve().parents[2] / "services" / "configs" / "line1.yaml"


@pytest.fixture(scope="module")
def dem_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dem")
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{free_port()}"], "connect": []},
        services=["dem"],
        state_dir=str(tmp),
    )
    spec = LineSpec.model_validate(data)
    progress: list[DemJobProgress] = []
    results: dict[str, DemJobResult] = {}
    lock = threading.Lock()
    out: dict = {}
    sup = Supervisor(spec).start()
    try:
        assert sup.wait_ready(120)
        s = open_session(sup.client_config("operator"))

        def on(sample: zenoh.Sample) -> None:
            k = keys.parse_key(str(sample.key_expr))
            with lock:
                if k.signal == "progress":
                    progress.append(DemJobProgress.model_validate_json(sample.payload.to_bytes()))
                elif k.signal == "result":
                    r = DemJobResult.model_validate_json(sample.payload.to_bytes())
                    results[r.job_id] = r

        sub = s.declare_subscriber("twin/line1/dem/**", zenoh.handlers.Callback(on, lambda: None))

        def ask(job: str, req: bytes) -> tuple[str, str]:
            for reply in s.get(keys.dem_job("line1", job, "request"), payload=req, timeout=10):
                if reply.ok is not None:
                    return "ok", reply.ok.payload.to_bytes().decode()
                return "err", reply.err.payload.to_bytes().decode()
            return "none", ""

        good = DemJobRequest(
            t=0.0,
            seq=0,
            job_id="j1",
            scene="drawdown",
            params={"radius": 0.004, "n_particles": 300},
            duration_s=0.004,
            seed=1,
        )
        out["good"] = ask("j1", good.to_json_bytes())
        out["dup"] = ask("j1", good.to_json_bytes())
        out["bad_json"] = ask("j2", b"{not json")
        up = b'{"t": 0, "seq": 0, "job_id": "..", "scene": "drawdown", "duration_s": 0.004}'
        out["dotdot"] = ask("..", up)
        long = good.model_copy(update={"job_id": "j4", "duration_s": 3600.0})
        out["too_long"] = ask("j4", long.to_json_bytes())
        bad_scene = good.model_copy(update={"job_id": "j3", "scene": "nosuchscene"})
        out["bad_scene"] = ask("j3", bad_scene.to_json_bytes())
        deadline = time.monotonic() + 240  # first run of the DEM kernels may compile (numba)
        while time.monotonic() < deadline and not {"j1", "j3"} <= set(results):
            time.sleep(0.2)
        sub.undeclare()
        s.close()
    finally:
        sup.stop()
    out["progress"] = [p for p in progress if p.job_id == "j1"]
    out["results"] = results
    return out


def test_dem_job_runs_with_progress_and_result(dem_run):
    kind, text = dem_run["good"]
    assert kind == "ok" and DemJobProgress.model_validate_json(text).state == "queued"
    r = dem_run["results"]["j1"]
    assert r.state == "done", r.error
    assert Path(r.outputs["checkpoint"]).exists()
    assert r.metrics["n_particles"] == 300
    assert r.metrics["sim_time_s"] == pytest.approx(0.004, rel=0.05)
    fr = [p.fraction for p in dem_run["progress"] if p.state == "running"]
    assert len(fr) >= 10 and fr == sorted(fr)
    assert dem_run["progress"][-1].state == "done" and dem_run["progress"][-1].fraction == 1.0


def test_dem_bad_requests_are_refused_with_a_reason(dem_run):
    assert dem_run["dup"][0] == "err" and "already submitted" in dem_run["dup"][1]
    assert dem_run["bad_json"][0] == "err" and "invalid DemJobRequest" in dem_run["bad_json"][1]
    # a job id that would name the run directory itself, a job beyond the duration quota
    assert dem_run["dotdot"][0] == "err" and "job_id" in dem_run["dotdot"][1]
    assert dem_run["too_long"][0] == "err" and "duration_s must be <=" in dem_run["too_long"][1]
    assert dem_run["bad_scene"][0] == "ok"  # well-formed: accepted, fails when run
    r = dem_run["results"]["j3"]
    assert r.state == "failed" and r.error
