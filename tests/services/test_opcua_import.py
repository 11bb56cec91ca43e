"""``twin import``: a historian export (wide CSV, or one file per tag) with wall-clock stamps in
a time zone and declared units becomes the recording the bridge would have made; gaps,
duplicates and unit mismatches are reported, never guessed; an unknown unit or a stamp without
time zone is refused in one line. Checked against the bundled recording: its first 120 s
exported in Europe/Berlin time and other units, imported back, equal the recording."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import pandas as pd
import pytest
import yaml

from schemas.messages import Event, FeederFlow, MeasuredConcentration
from services.cli.main import main
from services.opcua_plant import EPOCH, FEEDER_NODES, LoopbackPlant, recording_messages
from services.recording import read_recording

ROOT = Path(__file__).resolve().parents[2]
RECORDING = ROOT / "recordings" / "line1_30min.mcap"
SPAN_S = 120.0


@pytest.fixture(scope="module")
def source():
    msgs = [(k, m) for k, m in recording_messages(RECORDING) if m.t <= SPAN_S]
    return [(k, m) for k, m in msgs if isinstance(m, (FeederFlow, MeasuredConcentration))]


def _mapping(path: Path, source) -> Path:
    """The loopback plant's mapping with the hopper mass declared in g and the NIR as a
    fraction (the export's units), tags named as a historian would."""
    data = LoopbackPlant(source, port=1).bridge_config().model_dump(mode="json")
    for f in data["feeders"]:
        for name, node in f["nodes"].items():
            node["tag"] = f"{f['id']}_{FEEDER_NODES[name][0]}"
        f["nodes"]["hopper_mass_kg"]["unit"] = "g"
    data["sensor"]["node"].update(tag="nir_api", unit="fraction")
    data.pop("diverter")
    path.write_text(yaml.safe_dump(data))
    return path


def _columns(source) -> pd.DataFrame:
    rows: dict[float, dict[str, object]] = {}
    for key, m in source:
        row = rows.setdefault(m.t, {})
        if isinstance(m, FeederFlow):
            fid = key.split("/")[3]
            for name, (suffix, unit) in FEEDER_NODES.items():
                value = getattr(m, name)
                if name == "hopper_mass_kg":
                    value, unit = value * 1000.0, "g"
                row[f"{fid}_{suffix} [{unit}]"] = value
        else:
            row["nir_api [fraction]"] = m.concentration_pct_w_w / 100.0
    frame = pd.DataFrame([{"timestamp": t, **r} for t, r in sorted(rows.items())])
    stamps = [EPOCH + timedelta(seconds=t) for t in frame["timestamp"]]
    frame["timestamp"] = [pd.Timestamp(s).tz_convert("Europe/Berlin").isoformat() for s in stamps]
    return frame


def _same(out: Path, source) -> None:
    got = [(m.key, m.decode()) for m in read_recording(out).messages]
    assert len(got) == len(source)
    for (k1, a), (k2, b) in zip(
        sorted(got, key=lambda x: (x[1].t, x[0])), sorted(source, key=lambda x: (x[1].t, x[0]))
    ):
        assert k1 == k2 and a.t == b.t and a.seq == b.seq
        for name, value in b.model_dump().items():
            other = getattr(a, name)
            if isinstance(value, float):
                assert other == pytest.approx(value, rel=1e-12, abs=1e-12), (k1, a.t, name)
            else:
                assert other == value, (k1, a.t, name)


def _import(export: Path, cfg: Path, out: Path) -> int:
    return main(["import", str(export), "--config", str(cfg), "--out", str(out)])


def test_wide_and_per_tag_exports_give_the_recording(tmp_path, source, capsys):
    cfg = _mapping(tmp_path / "bridge.yaml", source)
    frame = _columns(source)
    frame.to_csv(tmp_path / "wide.csv", index=False)
    assert _import(tmp_path / "wide.csv", cfg, tmp_path / "wide.mcap") == 0
    _same(tmp_path / "wide.mcap", source)
    folder = tmp_path / "tags"
    folder.mkdir()
    for col in frame.columns[1:]:
        tag = col.split(" [")[0]
        unit = col.split(" [")[1].rstrip("]")
        frame[["timestamp", col]].rename(columns={col: f"value [{unit}]"}).to_csv(
            folder / f"{tag}.csv", index=False
        )
    assert _import(folder, cfg, tmp_path / "tags.mcap") == 0
    _same(tmp_path / "tags.mcap", source)


def test_gaps_duplicates_and_units_are_reported_never_guessed(tmp_path, source, capsys):
    cfg = _mapping(tmp_path / "bridge.yaml", source)
    frame = _columns(source)
    # a duplicated row (same values) and a conflicting one; 10 s of the NIR missing
    frame = pd.concat([frame, frame.iloc[[5]]], ignore_index=True)
    conflict = frame.iloc[[7]].copy()
    conflict["nir_api [fraction]"] = 0.5
    frame = pd.concat([frame, conflict], ignore_index=True)
    frame.loc[30:39, "nir_api [fraction]"] = None
    frame.to_csv(tmp_path / "wide.csv", index=False)
    assert _import(tmp_path / "wide.csv", cfg, tmp_path / "out.mcap") == 0
    err = capsys.readouterr().err
    assert "gap: nir_api: 10 samples missing between 29.000 s and 40.000 s" in err
    assert "duplicates: nir_api: 2 repeated stamps (1 with different values, dropped)" in err
    got = [m.decode() for m in read_recording(tmp_path / "out.mcap").messages]
    nir = [m for m in got if isinstance(m, MeasuredConcentration)]
    assert [m.t for m in nir if 25 <= m.t <= 41] == [25.0, 26.0, 27.0, 28.0, 29.0, 40.0, 41.0]
    assert 7.0 not in {m.t for m in nir}  # the conflicting stamp is dropped, not chosen
    # the sequence numbers skip the missed samples (stamp 7 and 30-39): each is its 1 Hz slot
    assert all(m.seq == int(m.t) for m in nir)
    assert not any(isinstance(m, Event) for m in got)


@pytest.mark.parametrize(
    ("header", "message"),
    [
        (
            "nir_api [% w/w]",
            "unit mismatch, 'nir_api': the export declares '% w/w', the mapping 'fraction'",
        ),
        ("nir_api [ppm-ish]", "unknown unit in the export, 'nir_api': 'ppm-ish'"),
    ],
)
def test_unit_mismatch_and_unknown_unit_refused_in_one_line(
    tmp_path, source, capsys, header, message
):
    cfg = _mapping(tmp_path / "bridge.yaml", source)
    _columns(source).rename(columns={"nir_api [fraction]": header}).to_csv(
        tmp_path / "wide.csv", index=False
    )
    assert _import(tmp_path / "wide.csv", cfg, tmp_path / "out.mcap") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {message}")
    assert not (tmp_path / "out.mcap").exists()


def test_stamps_without_time_zone_need_one(tmp_path, source, capsys):
    cfg = _mapping(tmp_path / "bridge.yaml", source)
    frame = _columns(source)
    frame["timestamp"] = [s[:-6] for s in frame["timestamp"]]  # local Berlin time, no offset
    frame.to_csv(tmp_path / "wide.csv", index=False)
    args = [
        "import",
        str(tmp_path / "wide.csv"),
        "--config",
        str(cfg),
        "--out",
        str(tmp_path / "out.mcap"),
    ]
    assert main(args) == 2
    assert "time stamps without time zone" in capsys.readouterr().err
    assert main([*args, "--timezone", "Europe/Berlin"]) == 0
    _same(tmp_path / "out.mcap", source)


def _api_flows(out: Path) -> dict[float, FeederFlow]:
    return {
        m.t: m.decode()
        for m in read_recording(out).messages
        if m.key == "twin/line1/feeder/api/flow"
    }


def test_a_blank_or_conflicting_tag_writes_no_message_at_its_stamp(tmp_path, source, capsys):
    """A blank flow at 5 s and two different screw speeds at 9 s: no ``FeederFlow`` of that
    feeder at 5 s or 9 s (never the previous second's value), the sequence skips both slots,
    and each stamp is named with its tag and why."""
    cfg = _mapping(tmp_path / "bridge.yaml", source)
    frame = _columns(source).astype(object)
    frame.loc[5, "api_MassFlow [kg/h]"] = None
    conflict = frame.iloc[[9]].copy()
    conflict["api_ScrewSpeed [rpm]"] = 99.0
    frame = pd.concat([frame, conflict], ignore_index=True)
    frame.to_csv(tmp_path / "wide.csv", index=False)
    assert _import(tmp_path / "wide.csv", cfg, tmp_path / "out.mcap") == 0
    err = capsys.readouterr().err
    flows = _api_flows(tmp_path / "out.mcap")
    assert 5.0 not in flows and 9.0 not in flows
    assert all(m.seq == int(t) for t, m in flows.items())  # each its own 1 Hz slot
    assert len(flows) == 119
    assert "no message: feeder api at 5.000 s: api_MassFlow empty" in err
    assert "no message: feeder api at 9.000 s: api_ScrewSpeed conflicting" in err
    # the excipient feeder and the NIR at those stamps are whole and written
    got = [m.decode() for m in read_recording(tmp_path / "out.mcap").messages]
    assert {m.t for m in got if isinstance(m, MeasuredConcentration)} >= {5.0, 9.0}


def _bad_export(tmp_path: Path, source) -> tuple[Path, Path]:
    """An export with three bad rows: a stamp that is no time (row of 3 s, file line 5), a
    flow that is text (12 s, line 14) and a negative hopper mass (20 s, line 22)."""
    cfg = _mapping(tmp_path / "bridge.yaml", source)
    frame = _columns(source).astype(object)
    frame.loc[3, "timestamp"] = "yesterday"
    frame.loc[12, "api_MassFlow [kg/h]"] = "abc"
    frame.loc[20, "excipient_HopperMass [g]"] = -5.0
    frame.to_csv(tmp_path / "wide.csv", index=False)
    return tmp_path / "wide.csv", cfg


def test_bad_rows_are_named_by_row_and_tag(tmp_path, source, capsys):
    """Without ``--skip-bad-rows`` the import stops (exit 2, no file, no traceback), having named
    every bad row: row, tag, value and reason."""
    export, cfg = _bad_export(tmp_path, source)
    assert _import(export, cfg, tmp_path / "out.mcap") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert not (tmp_path / "out.mcap").exists()
    assert "Traceback" not in "\n".join(err)
    assert err[-1].startswith("error: 3 bad rows in the export, wide.csv row 5")
    assert "--skip-bad-rows" in err[-1]
    named = "\n".join(err[:-1])
    assert "bad row: wide.csv row 5, 'timestamp': 'yesterday' (not an ISO 8601 stamp)" in named
    assert "bad row: wide.csv row 14, 'api_MassFlow': 'abc' (rejected_type" in named
    assert "bad row: wide.csv row 22, 'excipient_HopperMass': '-5.0' (" in named


def test_skip_bad_rows_skips_and_counts_them(tmp_path, source, capsys):
    """With ``--skip-bad-rows`` the bad rows are left out, counted and named; their stamps carry
    no message."""
    export, cfg = _bad_export(tmp_path, source)
    out = tmp_path / "out.mcap"
    args = ["import", str(export), "--config", str(cfg), "--out", str(out), "--skip-bad-rows"]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "skipped 3 bad rows" in err
    assert "bad row: wide.csv row 14, 'api_MassFlow': 'abc'" in err
    flows = _api_flows(out)
    assert {3.0, 12.0, 20.0}.isdisjoint(flows) and len(flows) == 118
    exc = [m.decode() for m in read_recording(out).messages if "excipient/flow" in m.key]
    assert 20.0 not in {m.t for m in exc}
