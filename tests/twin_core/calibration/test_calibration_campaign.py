"""Design campaigns: parallel, resumable, on a process pool, any executor, or Dask."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import pandas as pd
import pytest

from twin_core.calibration import SEED_FACTORS, SEED_LEVELS, TwoStepRSM, definitive_screening_design
from twin_core.calibration.campaign import (
    export_results,
    run_campaign,
    run_seed,
    surrogate_drawdown,
)


def _design() -> pd.DataFrame:
    d = definitive_screening_design(SEED_LEVELS).physical.reset_index()
    return d


def test_process_pool_campaign_feeds_stepwise(tmp_path):
    """21-run DSD through the surrogate drawdown (seed surfaces + model-RMSE noise) on a
    2-process pool; the stepwise fit of the results finds the seed's shear-angle main effects
    PP_SF, PP_RF, PW_SF (Fig. 8.1)."""
    surrogate_drawdown(_design().iloc[0].to_dict(), 0)  # fit the surrogate once, before forking
    out = run_campaign(
        _design(), surrogate_drawdown, tmp_path / "res.csv", seed=5, n_workers=2, progress=False
    )
    assert len(out) == 21 and (out.status == "ok").all()
    assert {"shear_angle_deg", "AOR_deg", "mass_lower_kg", "max_flowrate_kg_s"} <= set(out.columns)
    fit = TwoStepRSM(SEED_FACTORS, criterion="aicc").fit(out, "shear_angle_deg")
    assert set(fit.main_effects_) >= {"PP_SF", "PW_SF"}
    # seeds depend on the run id only: same campaign seed -> same numbers
    again = run_campaign(
        _design(),
        surrogate_drawdown,
        tmp_path / "res2.csv",
        seed=5,
        executor=ThreadPoolExecutor(2),
        progress=False,
    )
    pd.testing.assert_series_equal(out["shear_angle_deg"], again["shear_angle_deg"])
    assert out.loc[0, "seed"] == run_seed(5, "1")


class Flaky:
    """Fails on runs whose PP_SF is 0.6 until ``healed``; counts calls (thread-safe)."""

    def __init__(self) -> None:
        self.healed = False
        self.calls = 0
        self.lock = threading.Lock()

    def __call__(self, params, seed):
        with self.lock:
            self.calls += 1
        if params["PP_SF"] == 0.6 and not self.healed:
            raise RuntimeError("simulated crash")
        if params["PP_SF"] == 0.1 and not self.healed:
            return {"y": float("nan")}  # a failed measurement
        return {"y": params["PP_SF"] + params["PW_SF"]}


def test_resume_skips_finished_runs_and_retries_failed(tmp_path):
    design = _design()
    flaky = Flaky()
    path = tmp_path / "res.csv"
    first = run_campaign(design, flaky, path, executor=ThreadPoolExecutor(2), progress=False)
    n_crash = int((design.PP_SF == 0.6).sum())
    n_bad = n_crash + int((design.PP_SF == 0.1).sum())
    assert (first.status == "error").sum() == n_bad and flaky.calls == 21
    assert first.error.str.contains("simulated crash").sum() == n_crash
    assert first.error.str.contains("non-finite response").sum() == n_bad - n_crash
    assert first.loc[first.status == "error", "y"].isna().all()
    flaky.healed = True
    second = run_campaign(design, flaky, path, executor=ThreadPoolExecutor(2), progress=False)
    assert flaky.calls == 21 + n_bad  # only the failed runs ran again
    assert (second.status == "ok").all()
    assert second["y"].tolist() == pytest.approx((design.PP_SF + design.PW_SF).tolist())
    third = run_campaign(design, flaky, path, executor=ThreadPoolExecutor(2), progress=False)
    assert flaky.calls == 21 + n_bad
    assert third.equals(second)


def test_dask_distributed_scheduler(tmp_path):
    """The same campaign on a Dask cluster given by its scheduler address."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
    ) as cluster:
        out = run_campaign(
            _design().head(6),
            surrogate_drawdown,
            tmp_path / "d.csv",
            scheduler=cluster.scheduler_address,
            progress=False,
        )
    assert len(out) == 6 and (out.status == "ok").all()


def test_bad_campaign_inputs(tmp_path):
    d = _design()
    with pytest.raises(ValueError, match="non-empty"):
        run_campaign(d.iloc[:0], surrogate_drawdown, tmp_path / "x.csv")
    with pytest.raises(ValueError, match="unique"):
        run_campaign(pd.concat([d, d]), surrogate_drawdown, tmp_path / "x.csv")
    with pytest.raises(ValueError, match="lacks factor"):
        run_campaign(d, surrogate_drawdown, tmp_path / "x.csv", factors=["nope"])
    with pytest.raises(ValueError, match="either scheduler or executor"):
        run_campaign(
            d,
            surrogate_drawdown,
            tmp_path / "x.csv",
            scheduler="tcp://x",
            executor=ThreadPoolExecutor(1),
        )
    with pytest.raises(ValueError, match=r"\.csv or \.parquet"):
        export_results(d, tmp_path / "x.txt")
    assert export_results(d, tmp_path / "x.csv").exists()
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        with pytest.raises(ValueError, match="pyarrow"):
            export_results(d, tmp_path / "x.parquet")


def test_workers_end_when_the_campaign_process_is_killed(tmp_path):
    """A campaign process killed outright (SIGKILL: no chance to stop its pool) leaves no
    worker running its long run: each worker watches the campaign process and ends itself."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    code = (
        "import pandas as pd\n"
        "from twin_core.calibration.campaign import run_campaign\n"
        "from tests.twin_core.calibration.campaign_work import sleepy_run\n"
        "run_campaign(pd.DataFrame({'run': ['a'], 'sleep_s': [120.0]}), sleepy_run,\n"
        f"             r'{tmp_path / 'res.csv'}', n_workers=1, progress=False)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(root), CAMPAIGN_TEST_PID_DIR=str(tmp_path))
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=root, env=env)
    try:
        deadline = time.monotonic() + 120.0
        while not list(tmp_path.glob("*.pid")) and time.monotonic() < deadline:
            assert proc.poll() is None, "the campaign ended before its run started"
            time.sleep(0.1)
        (pid_file,) = tmp_path.glob("*.pid")
        worker = int(pid_file.read_text())
        os.kill(worker, 0)  # the worker is running its 120 s run
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        deadline = time.monotonic() + 10.0
        alive = True
        while alive and time.monotonic() < deadline:
            try:
                os.kill(worker, 0)
                time.sleep(0.1)
            except ProcessLookupError:
                alive = False
        assert not alive, "the worker outlived the killed campaign process"
    finally:
        if proc.poll() is None:
            proc.kill()
