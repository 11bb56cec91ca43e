"""``twin recover`` names every hole in what it wrote: the plant-time span of each lost stretch,
the messages and chunks lost, per channel, on stderr and in the output's ``recovery`` metadata
record, so that ``twin inspect`` and every reader of the recovered file see them too."""

from __future__ import annotations

import json
from pathlib import Path

from mcap.reader import make_reader

from schemas import keys
from schemas.messages import FeederFlow, MeasuredConcentration
from services.cli.main import main
from services.recording import McapRecorder, read_recording

LINE = "hline"
FLOW = keys.feeder_flow(LINE, "api")
CONC = keys.measured_concentration(LINE, "nir1")


def _sample(path: Path) -> None:
    """600 messages, flow and NIR alternating every 0.1 s (60 s), chunks of 100 messages."""
    with McapRecorder(path, flush_every=100, flush_period_s=None) as rec:
        for i in range(600):
            t, seq = i * 0.1, i // 2
            if i % 2 == 0:
                msg = FeederFlow(
                    t=t,
                    seq=seq,
                    component="api",
                    mass_flow_kg_h=0.6,
                    screw_speed_rpm=40.0,
                    hopper_mass_kg=2.0,
                    feed_factor_g_rev=0.25,
                )
                rec.write_message(FLOW, msg)
            else:
                c = MeasuredConcentration(
                    t=t, seq=seq, sensor="nir1", component="api", concentration_pct_w_w=5.0
                )
                rec.write_message(CONC, c)


def _chunks(path: Path) -> list:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    return sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)


def test_recover_names_the_hole_on_stderr_and_in_the_file(tmp_path, capsys):
    """A flipped byte in chunk 3 of 6 (plant time 20.0-29.9 s): the recovered file is complete,
    and the hole is named with its span, its 100 messages (50 per channel) and its chunk, on
    stderr, in the file's ``recovery`` metadata and by ``twin inspect``."""
    src = tmp_path / "six.mcap"
    _sample(src)
    c = _chunks(src)[2]
    data = bytearray(src.read_bytes())
    data[c.chunk_start_offset + c.chunk_length // 2] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    out = tmp_path / "fixed.mcap"
    assert main(["recover", str(bad), str(out)]) == 0
    err = capsys.readouterr().err
    line = next(x for x in err.splitlines() if x.startswith("hole:"))
    assert "plant time 20.000-29.900 s" in line and "100 messages in 1 chunk" in line
    assert f"{FLOW} 50" in line and f"{CONC} 50" in line
    back = read_recording(out)
    assert back.complete and len(back.messages) == 500
    [hole] = json.loads(back.metadata["recovery"]["holes"])
    assert (hole["start_s"], hole["end_s"], hole["messages"], hole["chunks"]) == (
        20.0,
        29.9,
        100,
        1,
    )
    assert hole["per_channel"] == {FLOW: 50, CONC: 50}
    assert "1 hole" in back.loss_report() and "plant time 20.000-29.900 s, 100 messages lost" in (
        back.loss_report()
    )
    assert main(["inspect", str(out)]) == 0
    assert "hole: plant time 20.000-29.900 s" in capsys.readouterr().out


def test_a_hole_without_its_chunk_header_is_bounded_by_its_neighbours(tmp_path, capsys):
    """No summary and the lost chunk's opcode destroyed (no header to read its times from): the
    hole is named between the last message before it and the first after it."""
    src = tmp_path / "six.mcap"
    _sample(src)
    c = _chunks(src)[2]
    data = bytearray(src.read_bytes())
    data[c.chunk_start_offset] = 0xEE  # no record: skipped up to the next valid chunk
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data[: len(data) - 1500]))  # the summary cut off: read in file order
    out = tmp_path / "fixed.mcap"
    assert main(["recover", str(bad), str(out)]) == 0
    err = capsys.readouterr().err
    assert "hole: plant time after 19.900 s, before 30.000 s" in err
    [hole] = json.loads(read_recording(out).metadata["recovery"]["holes"])
    assert (hole["after_s"], hole["before_s"]) == (19.9, 30.0)
