"""The wire contract: every message validates good values and rejects each kind of bad value
with an error naming the field and the value; key expressions build and parse; JSON Schemas export."""

from __future__ import annotations

import json
import math

import pytest
from pydantic import ValidationError

from schemas import keys
from schemas.bus_config import AccessControl, BusConfig, Tls
from schemas.export import all_models, export_json_schemas
from schemas.messages import (
    MESSAGE_MODELS,
    AdoptionProgress,
    DemJobProgress,
    DemJobRequest,
    DemJobResult,
    DivertCommand,
    Event,
    FeederFlow,
    MeasuredConcentration,
    OosAlert,
    PredictedConcentration,
    RtdEstimate,
    RtdSkipped,
    ServiceHealth,
)

GOOD = {
    FeederFlow: dict(
        t=1.0,
        seq=0,
        component="api",
        mass_flow_kg_h=0.6,
        setpoint_kg_h=0.6,
        screw_speed_rpm=40.0,
        hopper_mass_kg=2.5,
        feed_factor_g_rev=0.25,
        refilling=False,
    ),
    MeasuredConcentration: dict(
        t=1.0, seq=1, sensor="nir1", component="api", concentration_pct_w_w=-0.05, quality="good"
    ),
    PredictedConcentration: dict(
        t=1.0,
        seq=2,
        model="rtd",
        component="api",
        concentration_pct_w_w=5.0,
        lower_pct_w_w=4.5,
        upper_pct_w_w=5.5,
    ),
    Event: dict(t=2.0, seq=3, kind="tracer_pulse", source="tracer", component="api", mass_kg=0.01),
    RtdEstimate: dict(
        t=3.0,
        seq=4,
        model="axial_dispersion_open",
        params={"tau_d": 11.92, "tau": 16.37, "pe": 7.67},
        stderr={"tau_d": 0.1},
        mean_residence_time_s=32.5,
        n_points=100,
    ),
    RtdSkipped: dict(
        t=3.5, seq=0, pulse_t_s=900.0, reason="fit_failed", detail="profile area must be > 0"
    ),
    AdoptionProgress: dict(t=960.0, seq=3, complete_to_s=1020.0),
    OosAlert: dict(
        t=4.0,
        seq=5,
        alert_id="a1",
        component="api",
        t_start_s=10.0,
        t_end_s=20.0,
        peak_deviation_pct_w_w=-1.2,
        limit_pct_w_w=0.5,
        cause="refill api",
    ),
    DivertCommand: dict(
        t=4.0,
        seq=6,
        command_id="c1",
        action="divert",
        t_start_s=30.0,
        t_end_s=80.0,
        alert_id="a1",
        reason="OOS a1",
    ),
    DemJobRequest: dict(
        t=0.0, seq=7, job_id="j1", scene="drawdown", params={"mu_s": 0.5, "n": 3}, duration_s=1.0
    ),
    DemJobProgress: dict(t=0.0, seq=8, job_id="j1", state="running", fraction=0.5, sim_time_s=0.5),
    DemJobResult: dict(t=0.0, seq=9, job_id="j1", state="done", metrics={"angle_deg": 33.0}),
    ServiceHealth: dict(
        t=0.0,
        seq=10,
        service="recorder",
        state="running",
        pid=1,
        uptime_s=1.0,
        wall_time_unix_s=1.7e9,
        counters={"received": 3, "rejected_json": 0},
    ),
}

#: (field, bad value) pairs per model: each must be rejected naming the field and value
BAD: list[tuple[type, str, object]] = []
for _model in MESSAGE_MODELS:
    BAD += [
        (_model, "t", float("nan")),
        (_model, "t", float("inf")),
        (_model, "t", -1.0),
        (_model, "seq", -1),
    ]
BAD += [
    (FeederFlow, "mass_flow_kg_h", -0.1),
    (FeederFlow, "mass_flow_kg_h", float("nan")),
    (FeederFlow, "mass_flow_kg_h", float("-inf")),
    (FeederFlow, "setpoint_kg_h", -2.0),
    (FeederFlow, "screw_speed_rpm", -3.0),
    (FeederFlow, "hopper_mass_kg", -4.0),
    (FeederFlow, "hopper_mass_kg", float("inf")),
    (FeederFlow, "feed_factor_g_rev", -0.5),
    (FeederFlow, "component", ""),
    (FeederFlow, "component", "a/b"),
    (MeasuredConcentration, "concentration_pct_w_w", float("nan")),
    (MeasuredConcentration, "sensor", ""),
    (MeasuredConcentration, "component", ""),
    (MeasuredConcentration, "quality", "great"),
    (PredictedConcentration, "concentration_pct_w_w", float("inf")),
    (PredictedConcentration, "model", ""),
    (Event, "kind", "explosion"),
    (Event, "source", ""),
    (Event, "mass_kg", -0.01),
    (Event, "duration_s", -1.0),
    (RtdEstimate, "mean_residence_time_s", -5.0),
    (RtdEstimate, "model", ""),
    (RtdEstimate, "applies_from_s", -1.0),
    (AdoptionProgress, "complete_to_s", -1.0),
    (AdoptionProgress, "complete_to_s", float("nan")),
    (OosAlert, "alert_id", ""),
    (OosAlert, "limit_pct_w_w", -0.5),
    (OosAlert, "peak_deviation_pct_w_w", float("nan")),
    (OosAlert, "cause", ""),
    (DivertCommand, "command_id", ""),
    (DivertCommand, "action", "explode"),
    (DivertCommand, "t_start_s", -1.0),
    (DemJobRequest, "job_id", ""),
    (DemJobRequest, "duration_s", 0.0),
    (DemJobProgress, "fraction", 1.5),
    (DemJobProgress, "fraction", float("nan")),
    (DemJobResult, "job_id", ""),
    (ServiceHealth, "service", ""),
    (ServiceHealth, "uptime_s", -1.0),
]


@pytest.mark.parametrize("model", MESSAGE_MODELS, ids=lambda m: m.__name__)
def test_good_message_round_trips_json(model):
    msg = model(**GOOD[model])
    payload = msg.to_json_bytes()
    assert model.from_json_bytes(payload) == msg
    assert json.loads(payload)["t"] == GOOD[model]["t"]


@pytest.mark.parametrize(
    "model,field,value", BAD, ids=[f"{m.__name__}.{f}={v!r}" for m, f, v in BAD]
)
def test_bad_value_rejected_naming_field_and_value(model, field, value):
    data = dict(GOOD[model])
    data[field] = value
    with pytest.raises(ValidationError) as info:
        model(**data)
    text = str(info.value)
    assert field in text
    assert repr(value) in text or str(value) in text


@pytest.mark.parametrize("model", MESSAGE_MODELS, ids=lambda m: m.__name__)
def test_unknown_field_rejected(model):
    with pytest.raises(ValidationError, match="not_a_field"):
        model(**GOOD[model], not_a_field=1)


def test_nan_in_json_payload_rejected():
    payload = (
        FeederFlow(**GOOD[FeederFlow])
        .model_dump_json()
        .replace('"mass_flow_kg_h":0.6', '"mass_flow_kg_h":NaN')
    )
    assert "NaN" in payload
    with pytest.raises(ValidationError, match="mass_flow_kg_h"):
        FeederFlow.from_json_bytes(payload)


def test_cross_field_rules_name_fields_and_values():
    with pytest.raises(
        ValidationError, match=r"t_end_s must be >= t_start_s, got t_end_s=5.0 < 10.0"
    ):
        OosAlert(**{**GOOD[OosAlert], "t_end_s": 5.0})
    with pytest.raises(ValidationError, match="t_end_s must be >= t_start_s"):
        DivertCommand(**{**GOOD[DivertCommand], "t_end_s": 1.0})
    with pytest.raises(ValidationError, match="lower_pct_w_w must be <= upper_pct_w_w"):
        PredictedConcentration(**{**GOOD[PredictedConcentration], "lower_pct_w_w": 6.0})
    with pytest.raises(ValidationError, match="params must not be empty"):
        RtdEstimate(**{**GOOD[RtdEstimate], "params": {}})
    with pytest.raises(ValidationError, match=r"params.tau"):
        RtdEstimate(**{**GOOD[RtdEstimate], "params": {"tau": math.nan}})
    with pytest.raises(ValidationError, match=r"counters\['received'\] must be >= 0, got -1"):
        ServiceHealth(**{**GOOD[ServiceHealth], "counters": {"received": -1}})
    with pytest.raises(ValidationError, match="error must be given"):
        DemJobResult(**{**GOOD[DemJobResult], "state": "failed"})


def test_key_builder_and_parser():
    assert keys.feeder_flow("line1", "api") == "twin/line1/feeder/api/flow"
    assert keys.measured_concentration("line1", "nir1") == "twin/line1/pat/nir1/concentration"
    assert keys.predicted_concentration("line1") == "twin/line1/blender/outlet/predicted"
    assert keys.rtd_estimate("line1") == "twin/line1/rtd/estimate"
    assert keys.oos_alert("line1") == "twin/line1/oos/alert"
    assert keys.divert_command("line1") == "twin/line1/divert/command"
    k = keys.parse_key("twin/line1/feeder/api/flow")
    assert (k.line, k.unit, k.id, k.signal) == ("line1", "feeder", "api", "flow")
    k = keys.parse_key("twin/line1/rtd/estimate")
    assert (k.line, k.unit, k.id, k.signal) == ("line1", "rtd", None, "estimate")
    for expr in ["twin/line1/oos/alert", "twin/l/dem/j1/progress", "twin/l/service/x/health"]:
        assert str(keys.parse_key(expr)) == expr


@pytest.mark.parametrize(
    "expr",
    [
        "",
        "/twin/line1/oos/alert",
        "foo/line1/oos/alert",
        "twin/line1/alert",
        "twin/a/b/c/d/e",
        "twin/line1/*/alert",
        "twin/line1/feeder/**",
        "twin/line1//alert",
        "twin/line 1/oos/alert",
    ],
)
def test_parse_key_rejects(expr):
    with pytest.raises(ValueError, match="got"):
        keys.parse_key(expr)


def test_key_builder_names_bad_segment():
    with pytest.raises(ValueError, match=r"id must be .* got 'a/b'"):
        keys.key("line1", "feeder", "flow", id="a/b")
    with pytest.raises(ValueError, match=r"line must be .* got ''"):
        keys.key("", "feeder", "flow")


def test_model_for_key():
    assert keys.model_for_key("twin/line1/feeder/api/flow") is FeederFlow
    assert keys.model_for_key("twin/line1/pat/nir1/concentration") is MeasuredConcentration
    assert keys.model_for_key("twin/line1/divert/command") is DivertCommand
    assert keys.model_for_key("twin/line1/service/rec/health") is ServiceHealth
    assert keys.model_for_key("twin/line1/x/unknown_signal_xyz") is None
    assert keys.model_for_key("not a key") is None


def test_export_writes_every_model(tmp_path):
    paths = export_json_schemas(tmp_path)
    names = {p.name for p in paths}
    for model in MESSAGE_MODELS:
        assert f"schemas.messages.{model.__name__}.json" in names
    assert "schemas.bus_config.BusConfig.json" in names
    # every discovered model (other areas' modules included) is exported
    assert names == {f"{q}.json" for q in all_models()}
    schema = json.loads((tmp_path / "schemas.messages.FeederFlow.json").read_text())
    assert schema["type"] == "object"
    assert schema["properties"]["mass_flow_kg_h"]["minimum"] == 0.0
    assert "mass_flow_kg_h" in schema["required"]


def test_bus_config_defaults_and_security_rendering(tmp_path):
    cfg = BusConfig().to_zenoh_dict()
    assert cfg["mode"] == "peer"
    assert cfg["scouting"]["multicast"]["enabled"] is False
    assert cfg["scouting"]["gossip"]["enabled"] is False
    assert cfg["connect"]["endpoints"] == ["tcp/127.0.0.1:7447"]
    assert cfg["listen"]["endpoints"] == []
    with pytest.raises(ValidationError, match="endpoint must look like"):
        BusConfig(listen=["127.0.0.1:7447"])
    with pytest.raises(ValidationError, match="listen_certificate and listen_private_key"):
        Tls(root_ca_certificate=tmp_path / "ca.pem", listen_certificate=tmp_path / "c.pem")
    with pytest.raises(ValidationError, match="unknown rule id, got 'nope'"):
        AccessControl(
            rules=[],
            subjects=[{"id": "s", "usernames": ["u"]}],
            policies=[{"rules": ["nope"], "subjects": ["s"]}],
        )
    (tmp_path / "bus.yaml").write_text(
        "mode: router\nlisten: ['tcp/127.0.0.1:7500']\nconnect: []\n"
    )
    loaded = BusConfig.from_file(tmp_path / "bus.yaml")
    assert loaded.mode == "router" and loaded.listen == ["tcp/127.0.0.1:7500"]


def test_register_signal_after_a_miss():
    from schemas.base import Message

    class Foo(Message):
        value: float

    assert keys.model_for_key("twin/l/x/y/foo_signal_test") is None
    keys.register_signal("foo_signal_test", Foo)
    assert keys.model_for_key("twin/l/x/y/foo_signal_test") is Foo
