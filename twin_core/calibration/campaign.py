"""Run a design's simulations in parallel, resumably, into a results table.

``run_campaign(design, run, results_csv)`` calls ``run(params, seed) -> {response: value}``
once per design row, on a standard executor:

* default: a local process pool (``concurrent.futures.ProcessPoolExecutor``; workers started
  by ``forkserver``, safe whatever threading layer the parent process has run; a worker ends
  itself when the campaign process is killed);
* ``scheduler="tcp://host:8786"``: a Dask distributed cluster (``dask.distributed.Client``);
* ``executor=...``: any ``concurrent.futures.Executor`` (e.g. a thread pool).

Every finished run is appended to the results CSV at once (run id, seed, status, error,
elapsed time, parameters, responses), so an interrupted campaign resumes where it stopped:
runs already ``ok`` in the file are skipped. The seed of each run depends only on the
campaign seed and the run id (``numpy.random.SeedSequence``), not on the execution order.
The returned table (design joined with responses) feeds :class:`~.rsm.TwoStepRSM`.
"""

from __future__ import annotations

import csv
import math
import multiprocessing
import os
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

__all__ = ["run_campaign", "run_seed", "surrogate_drawdown", "export_results"]

RunFunction = Callable[[dict[str, float], int], Mapping[str, float]]
_META = ["run", "seed", "status", "error", "elapsed_s"]


def run_seed(campaign_seed: int, run_id: Any) -> int:
    """Seed of one run from the campaign seed and the run id (order independent)."""
    key = [int(campaign_seed)] + [ord(ch) for ch in str(run_id)]
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def _parent_alive(pid: int) -> bool:
    """Whether process ``pid`` still exists (signal 0 checks without sending anything)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists but not ours, or no such check on this platform
        return True
    return True


def _exit_with_parent(parent_pid: int, poll_s: float = 0.5) -> None:
    """Pool initializer: a daemon thread ends the worker once the campaign process is gone
    (killed before it could stop its pool), so no worker runs on as an orphan; the run it was
    doing is not recorded and is redone on resume."""

    def watch() -> None:
        while _parent_alive(parent_pid):
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=watch, name="campaign-parent-watch", daemon=True).start()


def _execute(run: RunFunction, run_id: Any, params: dict[str, float], seed: int) -> dict[str, Any]:
    """Call ``run`` and capture its result or its error (runs in the worker)."""
    t0 = time.perf_counter()
    row: dict[str, Any] = {"run": run_id, "seed": seed, "status": "ok", "error": ""}
    try:
        out = run(dict(params), seed)
        if not isinstance(out, Mapping):
            raise TypeError(
                f"run function must return a dict of responses, got {type(out).__name__}"
            )
        for k, v in out.items():
            row[f"y:{k}"] = float(v)
        bad = [k for k, v in out.items() if not math.isfinite(float(v))]
        if bad:  # a failed measurement: kept in the table, retried on resume
            row["status"] = "error"
            row["error"] = f"non-finite response(s): {', '.join(bad)}"
    except Exception as exc:  # noqa: BLE001 - a failed run is recorded, not fatal
        row["status"] = "error"
        row["error"] = f"{type(exc).__name__}: {exc}"
        row["traceback"] = traceback.format_exc(limit=5)
    row["elapsed_s"] = time.perf_counter() - t0
    return row


def _read_done(path: Path) -> pd.DataFrame:
    if not path.exists() or path.stat().st_size == 0:
        return pd.DataFrame(columns=_META)
    return pd.read_csv(path, dtype={"run": str})


def _append(path: Path, row: dict[str, Any], columns: list[str]) -> list[str]:
    """Append one row; if new response columns appear, rewrite the file with them."""
    new_cols = [c for c in row if c not in columns and c != "traceback"]
    if new_cols and path.exists() and path.stat().st_size > 0:
        old = pd.read_csv(path, dtype={"run": str})
        columns = columns + new_cols
        old = old.reindex(columns=columns)
        tmp = path.with_suffix(path.suffix + ".tmp")
        old.to_csv(tmp, index=False)
        os.replace(tmp, path)
    elif new_cols:
        columns = columns + new_cols
    exists = path.exists() and path.stat().st_size > 0
    with path.open("a", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        if not exists:
            w.writeheader()
        w.writerow(row)
        fh.flush()
        os.fsync(fh.fileno())
    return columns


def run_campaign(
    design: pd.DataFrame,
    run: RunFunction,
    results_csv: str | os.PathLike[str],
    seed: int = 0,
    factors: list[str] | None = None,
    scheduler: str | None = None,
    executor: Executor | None = None,
    n_workers: int | None = None,
    resume: bool = True,
    retry_failed: bool = True,
    progress: bool = True,
) -> pd.DataFrame:
    """Run every design row through ``run`` and return design + responses.

    ``design``: one row per run, factor columns in physical units (a ``run`` column, if
    present, is the run id; otherwise the index). ``run`` must be picklable (a module-level
    function) for process pools and Dask. ``factors``: columns passed to ``run`` (default all
    but ``run``). Returns one row per design run with columns ``run, seed, status, error,
    elapsed_s``, the factors and the responses (failed runs have NaN responses).
    """
    if not isinstance(design, pd.DataFrame) or design.empty:
        raise ValueError("design must be a non-empty pandas DataFrame")
    if not callable(run):
        raise ValueError(f"run must be callable, got {type(run).__name__}")
    if scheduler is not None and executor is not None:
        raise ValueError("give either scheduler or executor, not both")
    if n_workers is not None and n_workers < 1:
        raise ValueError(f"n_workers must be >= 1, got {n_workers}")
    ids = design["run"].astype(str) if "run" in design.columns else design.index.astype(str)
    ids = pd.Index(ids, name="run")
    if ids.duplicated().any():
        raise ValueError(
            f"run ids must be unique, duplicated: {sorted(set(ids[ids.duplicated()]))}"
        )
    factors = factors or [c for c in design.columns if c != "run"]
    missing = [f for f in factors if f not in design.columns]
    if missing:
        raise ValueError(f"design lacks factor column(s) {missing}")
    path = Path(results_csv)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not resume and path.exists():
        path.unlink()
    done = _read_done(path)
    ok = set(done.loc[done["status"] == "ok", "run"].astype(str)) if len(done) else set()
    if not retry_failed and len(done):
        ok |= set(done["run"].astype(str))
    columns = list(done.columns) if len(done.columns) else _META + list(factors)
    for c in _META + list(factors):
        if c not in columns:
            columns.append(c)
    todo = []
    for rid, (_, row) in zip(ids, design.iterrows()):
        if rid in ok:
            continue
        params = {f: float(row[f]) for f in factors}
        todo.append((rid, params, run_seed(seed, rid)))

    bar = None
    if progress and todo:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(todo), desc="campaign", unit="run")

    def record(row: dict[str, Any], params: dict[str, float]) -> None:
        nonlocal columns
        row = {**row, **params}
        columns = _append(path, row, columns)
        if bar is not None:
            bar.update(1)

    if todo:
        if scheduler is not None:
            from dask.distributed import Client
            from dask.distributed import as_completed as dask_as_completed

            with Client(scheduler) as client:
                futs = {
                    client.submit(_execute, run, rid, params, s, pure=False): params
                    for rid, params, s in todo
                }
                for fut in dask_as_completed(futs):
                    record(fut.result(), futs[fut])
        else:
            own = executor is None
            ex = executor or ProcessPoolExecutor(
                max_workers=n_workers or os.cpu_count() or 1,
                mp_context=multiprocessing.get_context("forkserver"),
                initializer=_exit_with_parent,
                initargs=(os.getpid(),),
            )
            try:
                futs = {ex.submit(_execute, run, rid, params, s): params for rid, params, s in todo}
                for fut in as_completed(futs):
                    record(fut.result(), futs[fut])
            finally:
                if own:
                    ex.shutdown(wait=True, cancel_futures=True)
    if bar is not None:
        bar.close()
    return _collect(path, ids, design, factors)


def _collect(path: Path, ids: pd.Index, design: pd.DataFrame, factors: list[str]) -> pd.DataFrame:
    res = _read_done(path)
    res = res.drop_duplicates("run", keep="last").set_index("run")
    out = pd.DataFrame({"run": ids})
    meta = res.reindex(ids)[[c for c in ("seed", "status", "error", "elapsed_s") if c in res]]
    out = pd.concat([out.reset_index(drop=True), meta.reset_index(drop=True)], axis=1)
    out = pd.concat([out, design[factors].reset_index(drop=True)], axis=1)
    ycols = [c for c in res.columns if c.startswith("y:")]
    ys = res.reindex(ids)[ycols].reset_index(drop=True)
    ys.columns = [c[2:] for c in ycols]
    out = pd.concat([out, ys], axis=1)
    out["error"] = [e if isinstance(e, str) else "" for e in out["error"]]
    return out


def export_results(table: pd.DataFrame, path: str | os.PathLike[str]) -> Path:
    """Write a results table to ``.csv``, or to ``.parquet`` when pyarrow is installed."""
    p = Path(path)
    if p.suffix == ".parquet":
        try:
            import pyarrow  # noqa: F401
        except ImportError as exc:
            raise ValueError(
                "writing .parquet needs pyarrow, which is not installed; use .csv"
            ) from exc
        table.to_parquet(p, index=False)
    elif p.suffix == ".csv":
        table.to_csv(p, index=False)
    else:
        raise ValueError(f"path must end in .csv or .parquet, got {p.name!r}")
    return p


# --------------------------------------------------------------------------- surrogate
_SURROGATE: dict[str, Any] = {}


def surrogate_drawdown(params: dict[str, float], seed: int) -> dict[str, float]:
    """A cheap stand-in for the DEM drawdown test: the four bulk responses predicted by the
    surfaces refitted to the seed's Tables 3.2/3.3 (min-AICc two-step stepwise), plus Gaussian
    noise with each model's RMSE. Module-level and picklable, for testing campaigns and
    demonstrating the workflow end to end without DEM."""
    if not _SURROGATE:
        from .rsm import TwoStepRSM
        from .tables import SEED_BULK_RESPONSES, SEED_FACTORS, load_seed_table

        table = load_seed_table("bulk")
        for r in SEED_BULK_RESPONSES:
            _SURROGATE[r] = TwoStepRSM(SEED_FACTORS, criterion="aicc").fit(table, r).model_
    rng = np.random.default_rng(seed)
    out = {}
    for name, model in _SURROGATE.items():
        missing = [f for f in model.factors_ if f not in params]
        if missing:
            raise ValueError(f"params lack {missing} needed for {name}")
        mu = float(model.predict({f: [params[f]] for f in model.factors_})[0])
        out[name] = mu + model.rmse_ * float(rng.standard_normal())
        if not math.isfinite(out[name]):
            raise ValueError(f"non-finite {name} for {params}")
    return out
