"""The compartment blender follows the plant's operating point (the blender and the diverter as
shells, no bus): a blade-speed change (``BlenderDrive``) or a throughput change (the feeders'
set points) switches E(t) from the tick of its plant time, announced by a ``BlenderModelInUse``;
a new section model (``BlenderModelUpdate``) joins the table; the diverter's core switches at the
same plant time. Reference: the table's own E(t) at the new point
(``twin_core.compartment.operating_point``, tested against analytic laws there) and the blender
with the new point declared from the start, which must predict the same after the switch once
the old inlet has left (causal convolution of the same inputs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas import keys
from schemas.line import BlenderModelConfig, HoldupConfig, LineSpec
from schemas.messages import BlenderDrive, BlenderModelUpdate
from services.blender import BlenderService
from services.common import follow_operating_point
from twin_core.compartment import CompartmentModel, synthetic_blender_fields, to_blender_model
from twin_core.compartment.operating_point import OperatingPoint
from twin_core.online.blender import tick_grid
from twin_core.online.drive import OperatingPointTracker
from twin_core.online.oos import OosCore
from twin_core.plant.messages import feeder_flow_messages

CONFIG = Path(__file__).resolve().parents[2] / "services" / "configs" / "line1.yaml"


class Pub:
    def __init__(self) -> None:
        self.sent: list = []

    def publish(self, msg):
        self.sent.append(msg)
        return msg


def _section(mean_s: float, rpm: float, seed: int):
    fields = synthetic_blender_fields(4, 6, 6, mean_residence_s=mean_s, seed=seed).fields
    return to_blender_model(CompartmentModel().fit(fields), n_sections=4, rpm_basis=rpm)


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("models")
    _section(2.0, 100.0, 0).save(d / "s100.json")
    _section(4.4, 50.0, 1).save(d / "s50.json")
    return d


def spec_for(tmp_path: Path, model_dir: Path, rpm: float = 100.0) -> LineSpec:
    spec = LineSpec.from_file(CONFIG)
    spec.state_dir = str(tmp_path)
    spec.services = ["feeder", "blender", "oos"]
    spec.blender = spec.blender.model_copy(
        update={
            "kind": "compartment",
            "export_path": str(model_dir),
            "blade_speed_rpm": rpm,
            "holdup": HoldupConfig(kg=0.108, rpm=100.0, throughput_kg_h=12.0, beta=1.0),
        }
    )
    return spec


def blender(spec: LineSpec, state: Path) -> BlenderService:
    spec = spec.model_copy(update={"state_dir": str(state)})
    svc = BlenderService(spec, install_signal_handlers=False)
    svc.pub, svc.model_pub = Pub(), Pub()
    return svc


def feed(svc, flows, extra: dict[float, tuple[str, object]]) -> None:
    """The flows in order, each extra message handed over before the first flow at or after its
    plant time."""
    todo = sorted(extra.items())
    for k, f in flows:
        while todo and f.t >= todo[0][0]:
            svc.handle(*todo.pop(0)[1])
        svc.handle(k, f)


def api(svc) -> dict[float, float]:
    return {p.t: p.concentration_pct_w_w for p in svc.pub.sent if p.component == "api"}


def test_a_blade_speed_change_switches_the_model_at_its_plant_time(tmp_path, model_dir):
    spec = spec_for(tmp_path, model_dir)
    flows = feeder_flow_messages(spec, 1500.0)
    drive = (keys.blender_drive("line1"), BlenderDrive(t=600.0, seq=1, blade_speed_rpm=50.0))
    switched, plain = blender(spec, tmp_path / "s"), blender(spec, tmp_path / "p")
    slow = blender(spec_for(tmp_path, model_dir, rpm=50.0), tmp_path / "slow")
    feed(switched, flows, {600.0: drive})
    feed(plain, flows, {})
    feed(slow, flows, {})
    a, p, s = api(switched), api(plain), api(slow)
    assert {t: v for t, v in a.items() if t < 600.0} == {t: v for t, v in p.items() if t < 600.0}
    late = [t for t in a if t >= 1300.0]  # the inlet before 600 s has left (kernel 300 s)
    np.testing.assert_allclose([a[t] for t in late], [s[t] for t in late], rtol=1e-9)
    assert max(abs(a[t] - p[t]) for t in a if t >= 600.0) > 1e-3
    announced = switched.model_pub.sent
    assert [m.reason for m in announced] == ["start", "blade_speed"]
    assert announced[1].applies_from_s == 600.0 and announced[1].blade_speed_rpm == 50.0
    k = switched.core.kernel
    table_e = k.table.rtd(OperatingPoint(50.0, 12.0), tick_grid(spec.dt_s, spec.blender.kernel_s))
    np.testing.assert_allclose(k.e, table_e, rtol=1e-12)
    # the slower blades: a longer mean residence time (kappa(100) / kappa(50) > 1)
    assert announced[1].mean_residence_time_s > 1.5 * announced[0].mean_residence_time_s
    assert switched.counters.get("operating_point_changes") == 1
    assert switched.counters.get("model_switches") == 2


def test_throughput_and_new_model_and_the_diverter_follow(tmp_path, model_dir):
    """Set points doubled at 400 s (beta = 0: the mean halves); a new 100-rpm model at 700 s;
    the diverter's core schedules the same switches at the same plant times."""
    spec = spec_for(tmp_path, model_dir).model_copy()
    spec.blender = spec.blender.model_copy(
        update={"holdup": spec.blender.holdup.model_copy(update={"beta": 0.0})}
    )
    flows = feeder_flow_messages(spec, 900.0)
    doubled = [
        (k, f.model_copy(update={"setpoint_kg_h": 2 * f.setpoint_kg_h}) if f.t >= 400.0 else f)
        for k, f in flows
    ]
    new = _section(3.0, 100.0, 2)
    update = (
        keys.blender_model_update("line1", "dem"),
        BlenderModelUpdate(t=700.0, seq=0, model=new),
    )
    svc = blender(spec, tmp_path / "b")
    feed(svc, doubled, {700.0: update})
    reasons = [(m.reason, m.applies_from_s) for m in svc.model_pub.sent]
    assert reasons == [("start", 0.0), ("throughput", 400.0), ("new_model", 700.0)]
    taus = [m.mean_residence_time_s for m in svc.model_pub.sent]
    assert taus[1] == pytest.approx(taus[0] / 2, rel=0.02)  # discretised on 1 s ticks
    assert svc.model_pub.sent[1].throughput_kg_h == pytest.approx(24.0)

    class Shell:
        def __init__(self) -> None:
            self.core = OosCore(spec)
            self.counters = svc.counters.__class__()
            self.name, self.warnings = "oos", svc.warnings

    oos = Shell()
    tracker = OperatingPointTracker(spec)
    for k, f in doubled:
        if f.t > 750.0:
            break
        if f.t >= 700.0 and oos.counters.get("models_received") == 0:
            follow_operating_point(oos, tracker, update[0], update[1])
        follow_operating_point(oos, tracker, k, f)
    oos.core.kernel.apply_due(800.0)
    np.testing.assert_allclose(oos.core.kernel.e, svc.core.kernel.e, rtol=1e-12)


def test_an_rtd_blender_counts_what_it_cannot_model(tmp_path):
    spec = LineSpec.from_file(CONFIG)
    spec.services = ["feeder", "blender", "oos"]
    spec.blender = BlenderModelConfig()  # the seed's Table 6.2 axial dispersion
    svc = blender(spec, tmp_path)
    svc.handle(keys.blender_drive("line1"), BlenderDrive(t=5.0, seq=0, blade_speed_rpm=50.0))
    assert svc.counters.get("operating_point_not_modelled") == 1


def test_a_dem_jobs_section_model_is_published_and_swapped_in(tmp_path, model_dir):
    """The dem service's last step of a blender-section job: the compartment model of the run's
    fields (here synthetic fields with a known mean residence time of 3 s per section, at
    75 rpm) is saved and published as a BlenderModelUpdate; the blender adopts it into its
    table from the request's plant time and announces the switch."""
    from schemas.messages import DemJobRequest
    from services.dem import DemService
    from twin_core.compartment import save_fields

    job = tmp_path / "job"
    job.mkdir()
    save_fields(job / "fields.npz", synthetic_blender_fields(4, 6, 6, mean_residence_s=3.0).fields)
    rng = np.random.default_rng(0)
    np.savez(job / "transit_times.npz", transit_s=rng.gamma(4.0, 0.75, 200))
    spec = spec_for(tmp_path, model_dir)
    dem = DemService(spec, install_signal_handlers=False)
    pub = Pub()
    pub.seq = 0
    dem._pub_model = lambda: pub
    req = DemJobRequest(t=300.0, seq=0, job_id="b75", scene="blender", duration_s=1.0)
    scene = type("Scene", (), {"mix_s": 20.0, "scene": "blender"})()
    dem._publish_blender_model(req, job, 75.0, scene)
    (update,) = pub.sent
    assert update.model.rpm_basis == 75.0 and (job / "blender_model.json").exists()
    assert update.model.mean_residence_time_s == pytest.approx(8 * 3.0, rel=0.05)  # 8 sections
    svc = blender(
        spec.model_copy(
            update={"blender": spec.blender.model_copy(update={"blade_speed_rpm": 75.0})}
        ),
        tmp_path / "b",
    )
    feed(
        svc,
        feeder_flow_messages(spec, 400.0),
        {300.0: (keys.blender_model_update("line1", "dem"), update)},
    )
    assert [(m.reason, m.applies_from_s) for m in svc.model_pub.sent] == [
        ("start", 0.0),
        ("new_model", 300.0),
    ]
    assert svc.core.kernel.table.speeds == [50.0, 75.0, 100.0]
    assert "75 rpm x 1.00" in svc.model_pub.sent[1].name


def test_a_blade_speed_outside_the_table_requests_a_section_run(tmp_path, model_dir):
    """150 rpm is beyond the table's 50-100 rpm: the blender extrapolates and, the dem service
    being in the line, requests one section run there with the packaged preset (once per speed);
    the dem service builds that request's scene from the preset (the packaged blender_small
    configuration at 150 rpm)."""
    from schemas.dem_scene import load_scene
    from twin_core.scenes.presets import scene_data

    spec = spec_for(tmp_path, model_dir)
    spec.services = ["feeder", "blender", "oos", "dem"]
    svc = blender(spec, tmp_path / "b")
    sent = []
    svc.publish_request = sent.append
    key = keys.blender_drive("line1")
    for t, rpm in ((10.0, 90.0), (20.0, 150.0), (30.0, 150.2), (40.0, 25.0)):
        svc.handle(key, BlenderDrive(t=t, seq=int(t), blade_speed_rpm=rpm))
    assert [(r.job_id, r.params["rpm"], r.t) for r in sent] == [
        ("blender_150rpm", 150.0, 20.0),
        ("blender_25rpm", 25.0, 40.0),
    ]
    assert svc.counters.get("dem_runs_requested") == 2
    req = sent[0]
    params = {k: v for k, v in req.params.items() if k not in ("rpm", "analysis")}
    scene = load_scene(scene_data(req.scene, req.job_id, params, None))
    assert scene.n_per_type == 300 and scene.radius == 0.0025
    assert req.duration_s == pytest.approx(scene.settle_s + scene.mix_s)
    with pytest.raises(ValueError, match="params.preset must be one of"):
        scene_data("blender", "j", {"preset": "../etc/passwd"}, None)
    with pytest.raises(ValueError, match="is a 'drawdown' scene"):
        scene_data("blender", "j", {"preset": "drawdown_small"}, None)
