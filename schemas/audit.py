"""The audit trail's record (key ``twin/<line>/audit/record``): who did what and when, chained.

One :class:`AuditRecord` per event that matters for GMP (21 CFR Part 11 §11.10(e), EU GMP
Annex 11 §9): service start / exit / restart, configuration loaded, alerts and divert
commands, model changes, rejected messages, data-quality findings, the trail's own start and
end. Each record carries the MAC of the record before it (``prev_mac``) and its own ``mac``, an
HMAC-SHA256 (RFC 2104) under the supervisor's audit key of the record's canonical JSON
without ``mac`` (:func:`canonical_bytes`): a record altered, inserted, removed or moved breaks
the chain (``services.audit.verify_trail``).
"""

from __future__ import annotations

import json
from typing import Any, ClassVar, Literal

from pydantic import Field

from schemas.base import Ident, Message, Text

#: what an audit record says happened
AuditAction = Literal[
    "trail_start",
    "trail_end",
    "config_loaded",
    "service_start",
    "service_exit",
    "service_restart",
    "service_killed",
    "alert",
    "divert_command",
    "model_adopted",
    "model_finding",
    "rejected_messages",
    "data_quality",
    "operator_action",
]

#: ``prev_mac`` of a run's first record
GENESIS = "0" * 64


class AuditRecord(Message):
    """One record of the audit trail (module docstring). ``t``: the latest plant time the
    trail had seen (s); ``utc``: the wall time of the event (ISO 8601, UTC); ``run``: the run
    it belongs to (each ``twin up`` starts a chain); ``actor``: the identity that acted (a
    service, ``supervisor``, ``operator``, ``plant``); ``subject``: what it acted on (an alert,
    a service, a model id); ``detail``: the rest, in words."""

    SIGNAL: ClassVar[str] = "record"

    utc: Text = Field(description="wall time of the event, ISO 8601 UTC")
    run: Ident = Field(description="the run (twin up) whose chain this record is in")
    actor: Ident
    action: AuditAction
    subject: Text
    detail: str = Field("", max_length=4096)
    prev_mac: str = Field(pattern=r"^[0-9a-f]{64}$", description="mac of the record before")
    mac: str = Field(pattern=r"^[0-9a-f]{64}$", description="HMAC-SHA256 of this record")


def canonical_bytes(fields: dict[str, Any]) -> bytes:
    """The bytes a record's MAC covers: its fields except ``mac``, as JSON with sorted keys
    and no spaces (one spelling per record)."""
    body = {k: v for k, v in fields.items() if k != "mac"}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True).encode()
