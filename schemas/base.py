"""Base types of the wire contract: the common message base and constrained field types.

Every bus message derives from :class:`Message` and carries ``t`` (plant time, s) and ``seq``
(per-publisher sequence number). Float fields reject NaN and +/-inf (``allow_inf_nan=False``),
unknown fields are rejected (``extra="forbid"``), and identifiers must be non-empty tokens that
are safe inside a zenoh key expression. A rejected value raises :class:`pydantic.ValidationError`
(a ``ValueError``) whose text names the field and the offending value, e.g.::

    1 validation error for FeederFlow
    mass_flow_kg_h
      Input should be greater than or equal to 0 [type=greater_than_equal, input_value=-1.0, ...]
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any, ClassVar, Self

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    ValidationError,
)

#: characters allowed in an identifier (and in one key-expression segment)
IDENT_PATTERN = r"^[A-Za-z0-9_.\-]+$"

#: a non-empty identifier usable as a key-expression segment (no '/', '*', '$', '?', '#', spaces)
Ident = Annotated[str, StringConstraints(min_length=1, max_length=128, pattern=IDENT_PATTERN)]


def _finite(value: float) -> float:
    if not math.isfinite(value):
        raise ValueError(f"must be a finite number, got {value!r}")
    return value


#: a finite float (NaN and +/-inf rejected even where a model allows them globally)
Finite = Annotated[float, AfterValidator(_finite)]
#: a finite float >= 0 (flows, masses, durations, speeds)
NonNegative = Annotated[float, Field(ge=0.0), AfterValidator(_finite)]
#: a finite float > 0
Positive = Annotated[float, Field(gt=0.0), AfterValidator(_finite)]
#: a finite fraction in [0, 1]
Fraction = Annotated[float, Field(ge=0.0, le=1.0), AfterValidator(_finite)]
#: a non-empty free-text string (reasons, causes)
Text = Annotated[str, StringConstraints(min_length=1, max_length=4096)]


def read_mapping(path: str | Path) -> dict[str, Any]:
    """The mapping held by a YAML (``.yaml``/``.yml``) or JSON file (an empty file: ``{}``)."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"file does not exist: {p}")
    text = p.read_text()
    if p.suffix in (".yaml", ".yml"):
        import yaml

        data = yaml.safe_load(text)
    else:
        data = json.loads(text) if text.strip() else None
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ValueError(f"{p} must hold a mapping, got {type(data).__name__}")
    return data


def validation_summary(exc: ValidationError) -> str:
    """A validation error on one line: ``field.path: message (got value)`` for every rejected
    field, joined by ``; `` (for command-line errors)."""
    parts = []
    for e in exc.errors(include_url=False):
        loc = ".".join(str(p) for p in e["loc"]) or "<root>"
        if e["type"] == "value_error":  # a validator's message names the value itself
            parts.append(f"{loc}: {e['msg'].removeprefix('Value error, ')}")
        elif e["type"] == "missing":
            parts.append(f"{loc}: {e['msg']}")
        else:
            parts.append(f"{loc}: {e['msg']} (got {e['input']!r:.80})")
    return "; ".join(parts)


class StrictModel(BaseModel):
    """Base of every schema model (messages and configs): unknown fields and NaN/inf rejected."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)

    @classmethod
    def from_file(cls, path: str | Path) -> Self:
        """Load and validate from a YAML (``.yaml``/``.yml``) or JSON file."""
        return cls.model_validate(read_mapping(path))


class Message(StrictModel):
    """Base of every bus message.

    Attributes:
        t: plant time of the sample, s (finite, >= 0).
        seq: per-publisher sequence number (>= 0), incremented by the publisher for each message.

    Subclasses set the class variable ``SIGNAL`` to the last segment of the key expressions they
    are published on (``twin/<line>/<unit>/<id>/<signal>``); the recorder and the typed
    subscriber use it to find the model of a key (see :func:`schemas.keys.model_for_key`).
    """

    SIGNAL: ClassVar[str | None] = None

    t: NonNegative = Field(description="plant time, s")
    seq: int = Field(ge=0, description="per-publisher sequence number")

    def to_json_bytes(self) -> bytes:
        """The wire payload: compact JSON (UTF-8)."""
        return self.model_dump_json().encode()

    @classmethod
    def from_json_bytes(cls, payload: bytes | str) -> Message:
        """Parse and validate a wire payload; raises ``pydantic.ValidationError`` if invalid."""
        return cls.model_validate_json(payload)


def json_schema(model: type[BaseModel]) -> dict[str, Any]:
    """JSON Schema (draft 2020-12, pydantic flavour) of a model, with ``"type": "object"``.

    This is the schema stored in MCAP channels (Foxglove ``jsonschema`` convention).
    """
    schema = model.model_json_schema()
    schema.setdefault("type", "object")
    return schema
