"""The OPC UA mapping, pure: unit conversion (checked against the units' definitions), bad
values refused by reason, one message per unit and source time whatever the arrival order,
gaps counted, marked and left as a sequence gap (the close-loop's data-quality rule)."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from schemas.messages import Event, FeederFlow, MeasuredConcentration
from schemas.opcua import BridgeConfig, NodeMap
from twin_core.plant.opcua_map import BadValue, MessageAssembler, convert, gap_event


def _config(**over) -> BridgeConfig:
    data = {
        "endpoint": "opc.tcp://127.0.0.1:4840",
        "line": "line1",
        "epoch_utc": "2026-01-01T00:00:00+01:00",
        "feeders": [
            {
                "id": "api",
                "component": "api",
                "nodes": {
                    "mass_flow_kg_h": {"node_id": "q", "unit": "g/s", "valid_max": 10},
                    "screw_speed_rpm": {"node_id": "n", "unit": "rev/s"},
                    "hopper_mass_kg": {"node_id": "m", "unit": "g", "scale": 0.5},
                },
            }
        ],
        "sensor": {"id": "nir1", "component": "api", "node": {"node_id": "c", "unit": "fraction"}},
        "tracer": {"component": "api", "node": {"node_id": "tr", "unit": "g"}},
    }
    data.update(over)
    return BridgeConfig.model_validate(data)


def test_units_follow_their_definitions():
    """1 g/s = 3.6 kg/h, 1 rev/s = 60 rev/min, fraction 1 = 100 % w/w, scale and offset first."""
    assert convert(NodeMap(node_id="a", unit="g/s"), 1.0) == pytest.approx(3.6)
    assert convert(NodeMap(node_id="a", unit="rev/s"), 0.5) == pytest.approx(30.0)
    assert convert(NodeMap(node_id="a", unit="fraction"), 0.05) == pytest.approx(5.0)
    assert convert(NodeMap(node_id="a", unit="kg/h", scale=0.1, offset=1.0), 20) == pytest.approx(
        3.0
    )
    assert convert(NodeMap(node_id="a", unit="bool"), 1) is True


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        (math.nan, "rejected_nan"),
        (math.inf, "rejected_nan"),
        ("12.5", "rejected_type"),
        (None, "rejected_type"),
        (True, "rejected_type"),
        (11.0, "rejected_range"),
        (-0.5, "rejected_range"),
    ],
)
def test_bad_values_are_refused_by_reason(raw, reason):
    node = NodeMap(node_id="q", unit="g/s", valid_min=0, valid_max=10)
    with pytest.raises(BadValue) as exc:
        convert(node, raw)
    assert exc.value.reason == reason


def test_unknown_unit_and_wrong_quantity_are_refused_naming_the_field():
    with pytest.raises(ValidationError, match="unit must be one of"):
        NodeMap(node_id="a", unit="furlong/fortnight")
    with pytest.raises(ValidationError, match="mass_flow_kg_h.unit must be a unit of mass_flow"):
        _config(
            feeders=[
                {
                    "id": "api",
                    "component": "api",
                    "nodes": {
                        "mass_flow_kg_h": {"node_id": "q", "unit": "kg"},
                        "screw_speed_rpm": {"node_id": "n", "unit": "rpm"},
                        "hopper_mass_kg": {"node_id": "m", "unit": "kg"},
                    },
                }
            ]
        )
    with pytest.raises(ValidationError, match="epoch_utc must carry a time zone"):
        _config(epoch_utc="2026-01-01T00:00:00")


def test_one_message_per_unit_and_time_whatever_the_arrival_order():
    """Notifications arrive grouped by node (OPC UA keeps the order per monitored item only):
    each feeder message waits for all its nodes of that time, and messages leave in time
    order."""
    a = MessageAssembler(_config())
    out = []
    for node, t, raw in (("q", 1.0, 1.0), ("q", 2.0, 2.0), ("n", 1.0, 0.5), ("n", 2.0, 0.5)):
        out += a.add(node, t, raw)[0]
    assert out == []  # the hopper mass of both times is still missing
    out += a.add("m", 1.0, 100.0)[0]
    assert [m.t for _, m in out] == [1.0]
    out += a.add("m", 2.0, 200.0)[0]
    assert [m.t for _, m in out] == [1.0, 2.0]
    first = out[0][1]
    assert isinstance(first, FeederFlow)
    assert first.mass_flow_kg_h == pytest.approx(3.6) and first.hopper_mass_kg == pytest.approx(
        0.05
    )
    # feed factor by its definition: 1000 Q / (60 n) g/rev
    assert first.feed_factor_g_rev == pytest.approx(1000 * 3.6 / (60 * 30.0))
    assert [m.seq for _, m in out] == [0, 1]


def test_sensor_tracer_and_gap():
    a = MessageAssembler(_config())
    msgs = []
    for t in (0.0, 1.0, 2.0, 6.0):  # samples 3, 4, 5 never came
        m, gaps = a.add("c", t, 0.05)
        msgs += m
    assert [m.seq for _, m in msgs] == [0, 1, 2, 6]  # the sequence skips the 3 missed samples
    assert isinstance(msgs[0][1], MeasuredConcentration)
    assert msgs[0][1].concentration_pct_w_w == pytest.approx(5.0)
    assert a.counters["samples_missed"] == 3
    assert len(gaps) == 1 and (gaps[0].t_before_s, gaps[0].t_after_s, gaps[0].n_missed) == (
        2.0,
        6.0,
        3,
    )
    ev = gap_event(gaps[0], 0)
    assert ev.kind == "note" and "missed 3 samples" in ev.detail and ev.t == 6.0
    pulse, _ = a.add("tr", 300.0, 10.0)
    assert isinstance(pulse[0][1], Event) and pulse[0][1].kind == "tracer_pulse"
    assert pulse[0][1].mass_kg == pytest.approx(0.01)
    assert a.add("tr", 301.0, 0.0)[0] == []  # mass 0: no pulse


def test_bad_and_late_samples_are_counted_and_dropped():
    a = MessageAssembler(_config())
    assert a.add("c", 1.0, math.nan) == ([], [])
    assert a.add("c", 1.0, "x") == ([], [])
    assert a.add("c", 2.0, 0.05)[0]
    assert a.add("c", 1.5, 0.05) == ([], [])
    assert a.add("nope", 3.0, 1.0) == ([], [])
    c = a.counters
    assert (c["rejected_nan"], c["rejected_type"], c["late"], c["rejected_unknown"]) == (1, 1, 1, 1)


def test_a_node_stamped_only_on_change_is_not_waited_for():
    """A PLC that stamps the hopper mass only when it changes (declared ``on_change``): the
    flow's times leave with the last hopper mass (counted incomplete); declared
    ``every_sample``, they wait for it."""
    feeders = _config().model_dump()["feeders"]
    feeders[0]["nodes"]["hopper_mass_kg"]["stamped"] = "on_change"
    for cfg, n_out in ((_config(feeders=feeders), 5), (_config(), 1)):
        a = MessageAssembler(cfg)
        out = []
        for node, t, raw in (("q", 0.0, 1.0), ("n", 0.0, 0.5), ("m", 0.0, 100.0)):
            out += a.add(node, t, raw)[0]
        for t in range(1, 5):
            out += a.add("q", float(t), 1.0)[0] + a.add("n", float(t), 0.5)[0]
        assert [m.t for _, m in out] == [float(t) for t in range(n_out)]
        assert all(m.hopper_mass_kg == pytest.approx(0.05) for _, m in out)
        assert a.counters.get("incomplete", 0) == n_out - 1


def test_a_refused_value_drops_its_time_as_a_missed_sample():
    """A NaN flow at t = 1 is not replaced by a guess: time 1 is dropped, and the next message's
    sequence number skips it (a gap for the close-loop's data-quality step)."""
    a = MessageAssembler(_config())
    out = []
    for t, q in ((0.0, 1.0), (1.0, math.nan), (2.0, 1.0)):
        for node, raw in (("q", q), ("n", 0.5), ("m", 100.0)):
            out += a.add(node, t, raw)[0]
    assert [(m.t, m.seq) for _, m in out] == [(0.0, 0), (2.0, 2)]
    assert a.counters["dropped"] == 1 and a.counters["samples_missed"] == 1


def test_blade_speed_becomes_the_blender_drive():
    """The blender's blade speed node (rev/s) is the contract's ``BlenderDrive`` in rev/min."""
    from schemas.messages import BlenderDrive

    cfg = _config(blender={"node": {"node_id": "blade", "unit": "rev/s"}})
    ((key, msg),) = MessageAssembler(cfg).add("blade", 5.0, 2.5)[0]
    assert key == "twin/line1/blender/blender/drive"
    assert isinstance(msg, BlenderDrive) and msg.blade_speed_rpm == pytest.approx(150.0)
    with pytest.raises(ValidationError, match="node.unit must be a unit of rotation"):
        _config(blender={"node": {"node_id": "blade", "unit": "kg/h"}})


def test_the_close_loop_reads_a_bridge_gap_as_missing_data():
    """The close-loop's data-quality step (``stamp_flags``: a stamp gap with a sequence gap is
    missing data, one without is a clock jump) sees the assembler's gap as a ``gap`` of the
    missed samples, not as a ``time_jump``."""
    import numpy as np

    from twin_core.closeloop.data import StreamStamps
    from twin_core.closeloop.quality import stamp_flags

    a = MessageAssembler(_config())
    msgs = [m for t in [*range(10), *range(20, 30)] for _, m in a.add("c", float(t), 0.05)[0]]
    stamps = StreamStamps(np.array([m.t for m in msgs]), np.array([m.seq for m in msgs]))
    flags = stamp_flags("nir", stamps, 1.0)
    assert [(f.kind, f.t_start_s, f.t_end_s, f.n_samples) for f in flags] == [
        ("gap", 10.0, 19.0, 10)
    ]


def _live(a: MessageAssembler, node: str, t: float, raw, w: float) -> list:
    """A live sample received at wall time ``w``: the messages it releases."""
    return [m for _, m in a.add(node, t, raw, w)[0]]


def _tick(a: MessageAssembler, t: float, w: float) -> list:
    """One feeder tick (three nodes) and one NIR sample stamped ``t``, received at ``w``."""
    out = []
    for node, raw in (("q", 0.2), ("n", 0.5), ("m", 40.0)):
        out += _live(a, node, t, raw, w)
    return out + _live(a, "c", t, 0.05, w)


def test_a_value_stamped_ahead_of_the_plant_clock_is_refused_and_displaces_nothing():
    """The plant clock of the NIR is the feeder's latest stamp advanced at real time: a value
    stamped 340 s ahead (beyond ``future_tolerance_s``) is held, then refused (``future``)
    when the NIR reports the next real stamp, which is published (not ``late``)."""
    a = MessageAssembler(_config())
    assert a.tolerance_s == 1.0  # the default
    for t in range(5):
        _tick(a, float(t), w=100.0 + t)
    assert _live(a, "c", 400.0, 0.9, w=104.5) == []  # held, not published
    assert a.counters.get("future", 0) == 0
    out = _tick(a, 5.0, w=105.0)
    assert a.counters["future"] == 1 and a.counters.get("late", 0) == 0
    assert [f.t_s for f in a.refused] == [400.0] and "reported 5.000 s" in a.refused[0].why
    nir = [m for m in out if isinstance(m, MeasuredConcentration)]
    assert [(m.t, m.concentration_pct_w_w) for m in nir] == [(5.0, pytest.approx(5.0))]
    # within the tolerance, or once real time has brought the clock there: taken
    assert _live(a, "c", 5.5, 0.05, w=105.1)
    held = _live(a, "c", 9.0, 0.05, w=105.2)  # 3.5 s ahead: held...
    assert held == [] and a.tick(108.0)[0]  # ... and released when the clock gets there
    assert a.counters["future_held"] == 1 and a.counters["future"] == 1


def test_the_whole_plant_stepping_ahead_together_is_followed():
    """After an outage every unit comes back 300 s on: each supports the others' clock, so
    nothing is refused, whichever unit reports first; the gap is counted as before."""
    a = MessageAssembler(_config())
    for t in range(3):
        _tick(a, float(t), w=float(t))
    out = _live(a, "c", 300.0, 0.05, w=3.0)  # the NIR first: ahead of the feeder, held
    assert out == []
    for node, raw in (("q", 0.2), ("n", 0.5), ("m", 40.0)):  # the feeder: the NIR's held
        out += _live(a, node, 300.0, raw, w=3.1)  # stamp supports it, and it the NIR's
    assert a.counters.get("future", 0) == 0
    assert sorted(type(m).__name__ for m in out) == ["FeederFlow", "MeasuredConcentration"]
    assert a.counters["samples_missed"] == 2 * 297


def test_an_export_has_no_live_clock():
    """Without a receive time (``twin import``) nothing is held: a stamp far ahead is taken."""
    a = MessageAssembler(_config())
    a.add("q", 0.0, 0.2)
    assert a.add("c", 5000.0, 0.05)[0]
    assert a.counters.get("future", 0) == 0


def test_a_publish_after_a_stall_grouped_by_node_is_held_and_released_whole():
    """A client that stalled gets up to the server's queue of each node in one publish, node
    after node: the NIR's 2000 samples arrive ahead of the feeder's clock and are held, then
    released in order as the feeder's samples of the same publish come; none refused."""
    a = MessageAssembler(_config())
    for t in range(3):
        _tick(a, float(t), w=float(t))
    out = [m for t in range(3, 2003) for m in _live(a, "c", float(t), 0.05, w=3.0)]
    for node, raw in (("q", 0.2), ("n", 0.5), ("m", 40.0)):
        out += [m for t in range(3, 2003) for m in _live(a, node, float(t), raw, w=3.0)]
    assert a.counters.get("future", 0) == 0 and a.counters.get("late", 0) == 0
    assert a.counters["future_held"] >= 1990  # all but those within the tolerance
    nir = [m.t for m in out if isinstance(m, MeasuredConcentration)]
    assert nir == [float(t) for t in range(3, 2003)]
    assert sum(isinstance(m, FeederFlow) for m in out) == 2000
