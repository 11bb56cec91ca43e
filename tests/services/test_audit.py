"""The audit trail (``services.audit``, ``twin audit verify``): a trail written through the
recording path verifies; one byte changed in the file, one record deleted, two records swapped,
a forged record and a cut-off end are each named and exit non-zero. Reference: RFC 2104
(HMAC-SHA256, Python's ``hmac``) and the chain's definition in ``schemas.audit``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from schemas import keys
from schemas.audit import AuditRecord
from services.audit import AuditTrail, load_or_create_key, record_mac, verify_trail
from services.recording import write_messages

KEY = keys.audit_record("line1")


def _trail(tmp_path: Path, n: int = 12, end: bool = True) -> tuple[bytes, list[AuditRecord]]:
    key = load_or_create_key(tmp_path / "state" / "audit.key")
    trail = AuditTrail(key, "run-1", path=tmp_path / "audit.jsonl")
    recs = [trail.append("supervisor", "trail_start", "run-1", "line line1")]
    for i in range(n - 2):
        trail.see(10.0 * (i // 5))  # five records a plant time, as events come in bursts
        recs.append(trail.append("oos", "alert", f"line1.api.feed-{i:012d}", f"alert {i}"))
    if end:
        recs.append(trail.append("supervisor", "trail_end", "run-1", "twin stopped"))
    return key, recs


def _verify_cli(rec: Path, key_file: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "services.cli.main",
            "audit",
            "verify",
            str(rec),
            "--key",
            str(key_file),
        ],
        capture_output=True,
        text=True,
    )


def test_an_intact_trail_verifies_and_the_key_is_private(tmp_path):
    key, recs = _trail(tmp_path)
    assert (tmp_path / "state" / "audit.key").stat().st_mode & 0o777 == 0o600
    v = verify_trail([r.to_json_bytes() for r in recs], key)
    assert v.ok and v.records == 12 and v.runs == {"run-1": 12}
    path = tmp_path / "rec.mcap"
    write_messages(path, [(KEY, r) for r in recs])
    out = _verify_cli(path, tmp_path / "state" / "audit.key")
    assert out.returncode == 0 and out.stdout.startswith("intact: 12 audit records"), out
    assert len((tmp_path / "audit.jsonl").read_text().splitlines()) == 12
    # another key: every record fails its MAC
    assert not verify_trail([r.to_json_bytes() for r in recs], b"x" * 32).ok


def test_deleted_swapped_forged_and_cut_records_are_named(tmp_path):
    key, recs = _trail(tmp_path)
    p = [r.to_json_bytes() for r in recs]
    deleted = verify_trail(p[:5] + p[6:], key)
    assert not deleted.ok and "record seq 6 " in deleted.problem and "seq 5" in deleted.problem
    swapped = verify_trail(p[:4] + [p[5], p[4]] + p[6:], key)
    assert not swapped.ok and "record seq 5 " in swapped.problem
    fields = json.loads(p[7])
    fields["detail"] = "nothing happened"
    altered = verify_trail(p[:7] + [json.dumps(fields).encode()] + p[8:], key)
    assert not altered.ok and "record seq 7 " in altered.problem and "MAC" in altered.problem
    fields["mac"] = record_mac(b"another key", fields)
    forged = verify_trail(p[:7] + [json.dumps(fields).encode()] + p[8:], key)
    assert not forged.ok and "record seq 7 " in forged.problem
    cut = verify_trail(p[:-1], key)
    assert not cut.ok and "without its trail_end" in cut.problem and "seq 10" in cut.problem


def test_the_cli_names_a_deleted_and_two_swapped_records_and_one_changed_byte(tmp_path):
    key, recs = _trail(tmp_path, n=40)
    key_file = tmp_path / "state" / "audit.key"
    deleted = tmp_path / "deleted.mcap"
    write_messages(deleted, [(KEY, r) for i, r in enumerate(recs) if i != 20])
    out = _verify_cli(deleted, key_file)
    assert out.returncode == 1 and "record seq 21 " in out.stdout, out
    swapped = tmp_path / "swapped.mcap"  # two records of one plant time, in each other's place
    order = [*recs[:12], recs[13], recs[12], *recs[14:]]
    write_messages(swapped, [(KEY, r) for r in order])
    out = _verify_cli(swapped, key_file)
    assert out.returncode == 1 and "record seq 13 " in out.stdout, out
    intact = tmp_path / "intact.mcap"
    write_messages(intact, [(KEY, r) for r in recs])
    data = bytearray(intact.read_bytes())
    i = data.index(b"zstd")  # the records' chunk: its compression name, then its data
    data[i + 40] ^= 0x01
    changed = tmp_path / "changed.mcap"
    changed.write_bytes(bytes(data))
    out = _verify_cli(changed, key_file)
    assert out.returncode == 1 and out.stdout.startswith("not intact"), out


def test_a_readable_key_file_is_refused(tmp_path):
    path = tmp_path / "audit.key"
    path.write_text("00" * 32)
    path.chmod(0o644)
    with pytest.raises(ValueError, match="mode 0600"):
        load_or_create_key(path)
