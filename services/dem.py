"""DEM service: runs DEM jobs on request, streams their progress, publishes their results.

Requests: a zenoh query (``get``) on ``twin/<line>/dem/<job_id>/request`` whose payload is a
:class:`~schemas.messages.DemJobRequest` is validated and answered at once with a
:class:`~schemas.messages.DemJobProgress` (``queued``) or an error reply naming the problem; a
``put`` on the same key is accepted the same way (no reply). Jobs run one at a time in a worker
thread:

- ``scene`` is a scene of ``schemas.dem_scene`` (``drawdown``, ``blender``, ``silo``, ...);
  ``params`` override its fields (``rpm`` is the blade speed of a blender section);
- default: the scene is built (``twin_core.scenes.<scene>.build``) and advanced by
  ``duration_s`` with ``twin_core.dem.Simulation.run``, whose callback streams
  ``DemJobProgress`` (20 updates) on ``twin/<line>/dem/<job_id>/progress``; the result holds
  the checkpoint file and particle metrics;
- ``params.preset``: a packaged scene configuration (``twin_core/scenes/configs/<preset>.yaml``)
  the other parameters override;
- ``params.analysis = true``: the scene's full run and analysis
  (``twin_core.scenes.<scene>.run``: results.json, grid fields for the compartment model,
  feed-factor curves...) into the job directory; the result lists its files and scalar results.
  For a blender section (unless ``params.build_model = false``) the compartment model of the
  run is built (``twin_core.compartment.build``), saved as ``blender_model.json`` and published
  as a :class:`~schemas.messages.BlenderModelUpdate` on ``twin/<line>/blender/dem/model``: the
  blender and the diverter add it to their table of models from the request's plant time.

Results: :class:`~schemas.messages.DemJobResult` on ``twin/<line>/dem/<job_id>/result``; a
failing job gives ``state: failed`` with the error, never a dead service. Job directories are
``<run dir>/dem/<job_id>`` (a job id is a safe file name, ``schemas.messages.JobId``, and the
directory is checked to lie inside ``<run dir>/dem``).

Quotas (refused with the reason): ``duration_s`` above :attr:`DemService.max_duration_s`, a scene
of more than :attr:`DemService.max_particles` particles (its ``n_particles`` when it names one,
else the built simulation's), more than :attr:`DemService.max_pending` jobs waiting or running.
On a secured bus only the ``operator`` identity may request jobs (``services.security``).
"""

from __future__ import annotations

import importlib
import logging
import math
import queue
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from pydantic import ValidationError

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import BlenderModelUpdate, DemJobProgress, DemJobRequest, DemJobResult
from services.bus import Publisher
from services.service import Service
from twin_core.scenes.presets import scene_data

log = logging.getLogger(__name__)


class DemService(Service):
    """See the module docstring."""

    #: simulated time a job may ask for, s
    max_duration_s: float = 60.0
    #: particles a job's scene may hold
    max_particles: int = 200_000
    #: jobs waiting or running at a time
    max_pending: int = 4

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("dem", spec=spec, **kwargs)
        self.jobs: queue.SimpleQueue[DemJobRequest | None] = queue.SimpleQueue()
        self.known: set[str] = set()
        self.pending = 0
        self._lock = threading.Lock()
        self._pubs: dict[str, Publisher] = {}
        self._worker: threading.Thread | None = None

    def setup(self) -> None:
        key = keys.dem_requests(self.spec.name)
        self._queryable = self.session.declare_queryable(
            key, zenoh.handlers.Callback(self._on_query, lambda: None)
        )
        self._sub = self.session.declare_subscriber(
            key, zenoh.handlers.Callback(self._on_put, lambda: None)
        )
        self._entities += [self._queryable, self._sub]
        self._worker = threading.Thread(target=self._work, name="dem-worker", daemon=True)
        self._worker.start()

    # -- requests --------------------------------------------------------------------------
    def _accept(self, key: str, payload: bytes | None) -> DemJobRequest:
        """Validate a request; raise ValueError with the reason."""
        if payload is None:
            raise ValueError("request payload must be a DemJobRequest JSON, got nothing")
        try:
            req = DemJobRequest.model_validate_json(payload)
        except ValidationError as exc:
            self.counters.inc("rejected_schema")
            raise ValueError(f"invalid DemJobRequest: {exc.errors(include_url=False)}") from exc
        job = keys.parse_key(key).id
        if req.job_id != job:
            self.counters.inc("rejected_schema")
            raise ValueError(f"job_id must match the key's id {job!r}, got {req.job_id!r}")
        self._check_quota(req)
        with self._lock:
            if req.job_id in self.known:
                raise ValueError(f"job_id must be new, got {req.job_id!r} (already submitted)")
            if self.pending >= self.max_pending:
                self.counters.inc("rejected_quota")
                raise ValueError(
                    f"jobs waiting or running must be at most {self.max_pending}, got "
                    f"{self.pending} already: try again later"
                )
            self.known.add(req.job_id)
            self.pending += 1
        self.counters.inc("jobs_accepted")
        self.jobs.put(req)
        return req

    def _check_quota(self, req: DemJobRequest) -> None:
        """Refuse a job beyond the quotas (module docstring), naming the field and value."""
        if req.duration_s > self.max_duration_s:
            self.counters.inc("rejected_quota")
            raise ValueError(f"duration_s must be <= {self.max_duration_s} s, got {req.duration_s}")
        n = req.params.get("n_particles")
        if isinstance(n, (int, float)) and n > self.max_particles:
            self.counters.inc("rejected_quota")
            raise ValueError(f"params.n_particles must be <= {self.max_particles}, got {n}")

    def _job_dir(self, job_id: str) -> Path:
        """``<run dir>/dem/<job_id>``, which must lie inside ``<run dir>/dem``."""
        root = (self.state_path / "dem").resolve()
        job_dir = (root / job_id).resolve()
        if job_dir.parent != root:
            raise ValueError(f"job_id must be a plain file name, got {job_id!r}")
        return job_dir

    def _queued(self, req: DemJobRequest) -> DemJobProgress:
        return DemJobProgress(
            t=req.t, seq=0, job_id=req.job_id, state="queued", fraction=0.0, message="accepted"
        )

    def _on_query(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        try:
            payload = query.payload.to_bytes() if query.payload is not None else None
            req = self._accept(key, payload)
            query.reply(key, self._queued(req).to_json_bytes())
        except ValueError as exc:
            query.reply_err(str(exc)[:2000])

    def _on_put(self, sample: zenoh.Sample) -> None:
        try:
            self._accept(str(sample.key_expr), sample.payload.to_bytes())
        except ValueError as exc:
            self.counters.last_error = str(exc)[:500]
            log.warning("dem request rejected: %s", exc)

    # -- jobs --------------------------------------------------------------------------------
    def _pub(self, job: str, signal: str, model: type) -> Publisher:
        return self._cached_pub(keys.dem_job(self.spec.name, job, signal), model)

    def _cached_pub(self, key: str, model: type) -> Publisher:
        """The service's one publisher (with history) of ``key``."""
        if key not in self._pubs:
            self._pubs[key] = self.publisher(key, model, history=True)
        return self._pubs[key]

    def _progress(
        self, req: DemJobRequest, state: str, fraction: float, sim: Any = None, message: str = ""
    ) -> None:
        pub = self._pub(req.job_id, "progress", DemJobProgress)
        pub.publish(
            DemJobProgress(
                t=req.t,
                seq=pub.seq,
                job_id=req.job_id,
                state=state,
                fraction=min(max(fraction, 0.0), 1.0),
                sim_time_s=float(sim.t) if sim is not None else 0.0,
                n_particles=int(sim.n_particles) if sim is not None else 0,
                message=message,
            )
        )

    def _work(self) -> None:
        while not self.stopping:
            try:
                req = self.jobs.get(timeout=0.2)
            except queue.Empty:
                continue
            if req is None:
                return
            t0 = time.perf_counter()
            try:
                outputs, metrics = self.run_job(req)
                result = DemJobResult(
                    t=req.t,
                    seq=0,
                    job_id=req.job_id,
                    state="done",
                    outputs=outputs,
                    metrics=metrics,
                    wall_time_s=time.perf_counter() - t0,
                )
                self.counters.inc("jobs_done")
            except Exception as exc:  # noqa: BLE001 - a failing job must not kill the service
                log.exception("dem job %s failed", req.job_id)
                self.counters.inc("jobs_failed")
                result = DemJobResult(
                    t=req.t,
                    seq=0,
                    job_id=req.job_id,
                    state="failed",
                    wall_time_s=time.perf_counter() - t0,
                    error=f"{type(exc).__name__}: {exc}"[:4000],
                )
                self._progress(req, "failed", 0.0, message=result.error or "")
            with self._lock:
                self.pending -= 1
            self._pub(req.job_id, "result", DemJobResult).publish(result)

    def run_job(self, req: DemJobRequest) -> tuple[dict[str, str], dict[str, float]]:
        """Run one job (see the module docstring); return (outputs, metrics). The engine
        chooses its thread count at run time (``twin_core.dem.threads``): the service shares
        its machine with the rest of the twin, where two threads can run at a quarter of one."""
        from twin_core.dem.threads import adaptive_threads

        with adaptive_threads():
            return self._run_job(req)

    def _run_job(self, req: DemJobRequest) -> tuple[dict[str, str], dict[str, float]]:
        from schemas.dem_scene import load_scene

        params = dict(req.params)
        analysis = bool(params.pop("analysis", False))
        build_model = bool(params.pop("build_model", True))
        rpm = params.pop("rpm", None)
        cfg = load_scene(scene_data(req.scene, req.job_id, params, req.seed))
        module = importlib.import_module(f"twin_core.scenes.{cfg.scene}")
        needs_rpm = cfg.scene == "blender"
        if needs_rpm and rpm is None:
            rpm = cfg.rpms[0]
        job_dir = self._job_dir(req.job_id)
        job_dir.mkdir(parents=True, exist_ok=True)
        self._progress(req, "running", 0.0, message=f"{cfg.scene}: building")
        if analysis:
            args = (cfg, float(rpm), job_dir) if needs_rpm else (cfg, job_dir)
            results = module.run(*args, resume=True, progress=False)
            if needs_rpm and build_model:
                self._publish_blender_model(req, job_dir, float(rpm), cfg)
            self._progress(req, "done", 1.0, message="analysis written")
            outputs = {
                p.stem.replace(" ", "_")[:128]: str(p)
                for p in sorted(job_dir.glob("*"))
                if p.is_file() and p.suffix in (".json", ".npz", ".csv", ".png")
            }
            metrics = {
                k: float(v)
                for k, v in (results or {}).items()
                if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            }
            return outputs, metrics
        sim, _geo = module.build(cfg, float(rpm)) if needs_rpm else module.build(cfg)
        if sim.n_particles > self.max_particles:
            raise ValueError(
                f"the scene's particles must be at most {self.max_particles}, got {sim.n_particles}"
            )
        t_start = float(sim.t)

        def on_step(s: Any) -> None:
            if self.stopping:
                raise InterruptedError("service stopping")
            self._progress(req, "running", (s.t - t_start) / req.duration_s, s)

        sim.run(req.duration_s, callback=on_step, callback_every_s=req.duration_s / 20)
        ckpt = sim.save_checkpoint(job_dir / "checkpoint.npz")
        self._progress(req, "done", 1.0, sim, message="checkpoint written")
        vel = np.asarray(sim.vel, float)
        speed = np.linalg.norm(vel, axis=1) if vel.size else np.zeros(1)
        pos = np.asarray(sim.pos, float)
        metrics = {
            "n_particles": float(sim.n_particles),
            "sim_time_s": float(sim.t),
            "mean_speed_m_s": float(speed.mean()),
            "max_speed_m_s": float(speed.max()),
        }
        if pos.size:
            metrics["mean_height_m"] = float(pos[:, 2].mean())
        return {"checkpoint": str(ckpt)}, metrics

    def _publish_blender_model(
        self, req: DemJobRequest, job_dir: Path, rpm: float, cfg: Any
    ) -> None:
        """The compartment model of a blender-section run (``build_blender_model`` on its fields
        and transit times) saved as ``blender_model.json`` and published as a
        ``BlenderModelUpdate``, which the blender and the diverter add to their table."""
        from twin_core.compartment import load_fields
        from twin_core.compartment.build import BuildOptions, build_blender_model

        transit = np.load(job_dir / "transit_times.npz")["transit_s"]
        opts = BuildOptions(rpm=rpm, transit_times=transit, transit_window_s=cfg.mix_s)
        built = build_blender_model(load_fields(job_dir / "fields.npz"), opts, source=req.job_id)
        built.blender.save(job_dir / "blender_model.json")
        pub = self._pub_model()
        pub.publish(
            BlenderModelUpdate(
                t=req.t,
                seq=pub.seq,
                model=built.blender,
                detail=f"dem job {req.job_id}: {cfg.scene} at {rpm:g} rpm, {cfg.mix_s:g} s",
            )
        )
        self.counters.inc("models_published")

    def _pub_model(self) -> Publisher:
        return self._cached_pub(
            keys.blender_model_update(self.spec.name, "dem"), BlenderModelUpdate
        )

    def finish(self) -> None:
        self.jobs.put(None)
        if self._worker is not None:
            self._worker.join(timeout=5.0)
