"""The audit trail: an append-only, hash-chained, authenticated record of what the twin did.

:class:`AuditTrail` appends :class:`~schemas.audit.AuditRecord` s: each carries a per-run
sequence number, the MAC of the record before it and its own MAC, an HMAC-SHA256 (RFC 2104,
Python's ``hmac``) under the **audit key** of the record's canonical JSON
(``schemas.audit.canonical_bytes``). The key is the plant's, held by the supervisor
(``<state_dir>/audit.key``, 32 random bytes, created once with mode 0600): a service, a tool
or a person editing a recording cannot forge a record without it. The supervisor publishes
each record on ``twin/<line>/audit/record`` (the recorder writes it to the MCAP file, where it
is exported and verified from) and appends it to ``<run dir>/audit.jsonl``.

:func:`verify_trail` checks a trail read back (``twin audit verify REC.mcap``): every record
parses, its MAC verifies under the key, its sequence number follows the one before, its
``prev_mac`` is the MAC of the record before, and the run's last record is its ``trail_end``;
it names the first record that fails (altered, inserted, removed, reordered, or the end cut
off).
"""

from __future__ import annotations

import csv
import datetime as dt
import hashlib
import hmac
import json
import os
import secrets
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from schemas.audit import GENESIS, AuditRecord, canonical_bytes
from services.security import write_private

#: bytes of a new audit key
KEY_BYTES = 32
AUDIT_KEY_FILE = "audit.key"


def load_or_create_key(path: Path) -> bytes:
    """The audit key in ``path`` (hex), created (0600, folder made) when it does not exist;
    a key file readable by others is refused (ValueError naming the file)."""
    if path.exists():
        mode = path.stat().st_mode & 0o777
        if mode & 0o077:
            raise ValueError(f"audit key file must be private (mode 0600), got {oct(mode)}: {path}")
        return read_key(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_private(path, secrets.token_hex(KEY_BYTES))
    return read_key(path)


def read_key(path: Path) -> bytes:
    """An audit key file's bytes (ValueError naming the file when it is not a hex key)."""
    try:
        text = path.read_text().strip()
        key = bytes.fromhex(text)
    except (OSError, ValueError) as exc:
        raise ValueError(f"audit key must be a hex key file, {path}: {exc}") from None
    if len(key) < 16:
        raise ValueError(f"audit key must hold >= 16 bytes, got {len(key)} in {path}")
    return key


def record_mac(key: bytes, fields: dict[str, Any]) -> str:
    """HMAC-SHA256 (RFC 2104) of a record's canonical bytes, hex."""
    return hmac.new(key, canonical_bytes(fields), hashlib.sha256).hexdigest()


def utc_now() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")


class AuditTrail:
    """Appends chained, authenticated records for one run (module docstring).

    Args:
        key: the audit key.
        run: the run's id (its run directory's name).
        publish: called with each record (the supervisor's bus publisher), or None.
        path: a JSON-lines file each record is appended to, or None.
    """

    def __init__(
        self,
        key: bytes,
        run: str,
        publish: Callable[[AuditRecord], None] | None = None,
        path: Path | None = None,
    ) -> None:
        self.key = key
        self.run = run
        self.publish = publish
        self.path = path
        self.seq = 0
        self.prev = GENESIS
        self.t = 0.0
        self._lock = threading.Lock()

    def see(self, t: float) -> None:
        """The plant time of a message the trail saw (records carry the latest)."""
        with self._lock:
            self.t = max(self.t, float(t))

    def append(self, actor: str, action: str, subject: str, detail: str = "") -> AuditRecord:
        """Add a record; returns it (published and written when configured)."""
        with self._lock:
            fields = {
                "t": self.t,
                "seq": self.seq,
                "utc": utc_now(),
                "run": self.run,
                "actor": actor,
                "action": action,
                "subject": subject[:4096] or "-",
                "detail": detail[:4096],
                "prev_mac": self.prev,
            }
            fields["mac"] = record_mac(self.key, fields)
            rec = AuditRecord.model_validate(fields)
            self.seq += 1
            self.prev = rec.mac
            if self.path is not None:
                with self.path.open("a") as fh:
                    fh.write(rec.model_dump_json() + "\n")
                    fh.flush()
                    os.fsync(fh.fileno())
            publish = self.publish
        if publish is not None:
            publish(rec)
        return rec


@dataclass
class TrailVerdict:
    """What :func:`verify_trail` found: ``ok``; ``records`` read; ``runs`` (run -> records);
    ``problem``: the first failure, naming the record, or ''."""

    ok: bool
    records: int
    runs: dict[str, int] = field(default_factory=dict)
    problem: str = ""
    first_utc: str = ""
    last_utc: str = ""


def _where(fields: dict[str, Any]) -> str:
    return (
        f"record seq {fields.get('seq')} of run {fields.get('run')} "
        f"({fields.get('action')}, {fields.get('subject')}, {fields.get('utc')})"
    )


def verify_trail(
    payloads: Iterable[bytes], key: bytes, *, require_end: bool = True
) -> TrailVerdict:
    """Check a trail read back in its order (module docstring); stops at the first failure."""
    state: dict[str, tuple[int, str, str]] = {}  # run -> (last seq, last mac, last action)
    n = 0
    first = last = ""
    for i, payload in enumerate(payloads):
        n += 1
        try:
            fields = json.loads(payload)
            AuditRecord.model_validate(fields)
        except ValueError as exc:
            return TrailVerdict(
                False, n, problem=f"record #{i + 1} of the trail is unreadable: {exc}"
            )
        if not hmac.compare_digest(record_mac(key, fields), fields["mac"]):
            return TrailVerdict(
                False, n, problem=f"{_where(fields)}: its MAC does not verify (altered or forged)"
            )
        run, seq = fields["run"], int(fields["seq"])
        last_seq, last_mac, _ = state.get(run, (-1, GENESIS, ""))
        if seq > last_seq + 1:
            missing = f"seq {last_seq + 1}" + (f"..{seq - 1}" if seq - 1 > last_seq + 1 else "")
            return TrailVerdict(
                False, n, problem=f"{_where(fields)}: record(s) {missing} before it are missing"
            )
        if seq <= last_seq:
            return TrailVerdict(
                False, n, problem=f"{_where(fields)}: out of order (after seq {last_seq})"
            )
        if fields["prev_mac"] != last_mac:
            return TrailVerdict(
                False, n, problem=f"{_where(fields)}: does not follow the record before it"
            )
        state[run] = (seq, fields["mac"], fields["action"])
        first = first or fields["utc"]
        last = fields["utc"]
    runs = {r: s + 1 for r, (s, _, _) in state.items()}
    if require_end:
        for run, (seq, _, action) in state.items():
            if action != "trail_end":
                return TrailVerdict(
                    False,
                    n,
                    runs,
                    f"the trail of run {run} ends at record seq {seq} ({action}) without its "
                    "trail_end record: cut off, or the twin was killed",
                    first,
                    last,
                )
    if n == 0:
        return TrailVerdict(False, 0, problem="no audit record in the recording")
    return TrailVerdict(True, n, runs, "", first, last)


EXPORT_FIELDS = (
    "run",
    "seq",
    "utc",
    "t",
    "actor",
    "action",
    "subject",
    "detail",
    "prev_mac",
    "mac",
)


def export_trail(payloads: Iterable[bytes], path: Path) -> int:
    """Write the records to ``path`` as CSV (``.csv``) or JSON (otherwise); returns the count."""
    rows = [json.loads(p) for p in payloads]
    if path.suffix.lower() == ".csv":
        with path.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=EXPORT_FIELDS, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
    else:
        path.write_text(json.dumps(rows, indent=1))
    return len(rows)
