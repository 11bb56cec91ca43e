"""`twin audit verify REC.mcap` and `twin audit export REC.mcap --out FILE`: the audit trail of a
recording (``services.audit``).

``verify`` reads the recording's ``twin/<line>/audit/record`` channel in its order and checks
every record's MAC under the plant's audit key, the chain of sequence numbers and MACs, and
that each run's trail ends with its ``trail_end`` record; it prints ``intact: ...`` and exits 0,
or names the first record that fails (altered, forged, inserted, removed, reordered, the end
cut off, or records lost in unreadable chunks of the file) and exits 1. ``export`` writes the
records as CSV or JSON.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from services.cli.main import USAGE_ERROR

#: exit status of a trail that does not verify
NOT_INTACT = 1


def _trail_payloads(path: Path) -> tuple[list[bytes], str]:
    """The audit records' payloads of a recording, in its order, and what was lost reading it
    ('' when nothing)."""
    from services.recording import read_recording

    rec = read_recording(path)
    payloads = [m.payload for m in rec.messages if m.key.split("/")[2:] == ["audit", "record"]]
    lost = "" if rec.complete else rec.loss_report()
    return payloads, lost


def _key_path(args: argparse.Namespace) -> Path:
    from services.audit import AUDIT_KEY_FILE

    if args.key:
        return Path(args.key)
    if args.config:
        from schemas.line import LineSpec

        return Path(LineSpec.from_file(args.config).state_dir) / AUDIT_KEY_FILE
    return Path(".twin-state") / AUDIT_KEY_FILE


def cmd_verify(args: argparse.Namespace) -> int:
    from services.audit import read_key, verify_trail

    key_path = _key_path(args)
    if not key_path.exists():
        raise ValueError(f"audit key file not found (--key or the line's state_dir), {key_path}")
    key = read_key(key_path)
    payloads, lost = _trail_payloads(Path(args.recording))
    verdict = verify_trail(payloads, key)
    if lost and verdict.ok:
        print(f"not intact: the recording lost messages ({lost}); the trail itself verifies")
        return NOT_INTACT
    if not verdict.ok:
        extra = f" (the recording: {lost})" if lost else ""
        print(f"not intact: {verdict.problem}{extra}")
        return NOT_INTACT
    runs = ", ".join(f"{r} ({n} records)" for r, n in verdict.runs.items())
    print(
        f"intact: {verdict.records} audit records, run(s) {runs}, {verdict.first_utc} .. "
        f"{verdict.last_utc}"
    )
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from services.audit import export_trail
    from services.cli.bus import check_output_file

    out = Path(args.out)
    check_output_file(out)
    payloads, lost = _trail_payloads(Path(args.recording))
    n = export_trail(payloads, out)
    print(f"wrote {n} audit records to {out}" + (f" (the recording: {lost})" if lost else ""))
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "audit",
        help="verify or export the audit trail of a recording",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="audit_command", metavar="ACTION")
    v = sub.add_parser("verify", help="check the trail's chain and MACs; exit 1 if not intact")
    v.add_argument("recording", help="MCAP recording of a twin run")
    v.add_argument("--key", default=None, help="the audit key file (default: state_dir/audit.key)")
    v.add_argument("--config", default=None, help="line YAML/JSON (its state_dir holds the key)")
    v.set_defaults(func=cmd_verify)
    e = sub.add_parser("export", help="the trail as CSV (.csv) or JSON")
    e.add_argument("recording", help="MCAP recording of a twin run")
    e.add_argument("--out", required=True, help="output .csv or .json")
    e.set_defaults(func=cmd_export)
    p.set_defaults(func=lambda a: (p.print_help(), USAGE_ERROR)[1])
