"""The DEM processes' threading layer (``twin_core.dem.threads.prefer_openmp``) and the
calibration campaign's process pool, which must stay usable after a parallel region under it
(GNU OpenMP is not fork-safe: a forked child that runs a parallel region aborts). Each case runs
in a fresh interpreter, because numba fixes its layer at the first parallel region."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]


def _run(code: str, **env: str) -> subprocess.CompletedProcess:
    e = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING_LAYER")}
    e.update(env)
    e["PYTHONPATH"] = str(ROOT)
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=ROOT, env=e, capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip


LAYER = """
    import numpy as np
    from numba import njit, prange, threading_layer
    from twin_core.dem.threads import prefer_openmp

    @njit(parallel=True)
    def twice(a):
        for i in prange(a.size):
            a[i] *= 2.0

    print(prefer_openmp())
    twice(np.ones(100))
    print(threading_layer())
"""


@functools.cache
def _openmp_available() -> bool:
    """Whether numba's OpenMP layer loads here (one fresh interpreter, asked once)."""
    out = _run(LAYER, NUMBA_THREADING_LAYER="omp")
    return out.returncode == 0 and out.stdout.split()[-1] == "omp"


def test_prefer_openmp_picks_openmp_unless_the_environment_chooses():
    if not _openmp_available():
        pytest.skip("numba's OpenMP layer cannot load on this machine")
    out = _run(LAYER)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["('omp',", "'tbb',", "'workqueue')", "omp"]
    out = _run(LAYER, NUMBA_THREADING_LAYER="workqueue")
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["None", "workqueue"]


def test_campaign_pool_runs_parallel_work_after_the_parent_used_openmp(tmp_path):
    """A campaign started by a process that has run a parallel region under OpenMP (a DEM run,
    then its analysis campaign): the workers run parallel regions too and finish (with a
    forked pool, GNU OpenMP aborts them), under OpenMP too (inherited through the environment)."""
    if not _openmp_available():
        pytest.skip("numba's OpenMP layer cannot load on this machine")
    code = f"""
    import numpy as np
    import pandas as pd
    from twin_core.calibration.campaign import run_campaign
    from twin_core.dem.threads import prefer_openmp
    from tests.twin_core.dem.parallel_work import parallel_sum

    prefer_openmp()
    print(parallel_sum({{"n": 10}}, 0)["total"])
    out = run_campaign(pd.DataFrame({{"run": ["a", "b"], "n": [100, 1000]}}), parallel_sum,
                       r"{tmp_path / "res.csv"}", n_workers=2, progress=False)
    print(list(out["status"]), list(out["total"]), list(out["openmp"]))
    from numba import threading_layer
    print(threading_layer())
    """
    out = _run(code)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.strip().splitlines()
    assert lines[-3:] == ["20.0", "['ok', 'ok'] [200.0, 2000.0] [1.0, 1.0]", "omp"]
