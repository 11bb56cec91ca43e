"""Key expressions of the bus: ``twin/<line>/<unit>/<id>/<signal>`` (or ``twin/<line>/<unit>/<signal>``).

Examples::

    twin/line1/feeder/api/flow            FeederFlow
    twin/line1/pat/nir1/concentration     MeasuredConcentration
    twin/line1/blender/outlet/predicted   PredictedConcentration
    twin/line1/feeder/api/event           Event
    twin/line1/rtd/estimate               RtdEstimate        (no id)
    twin/line1/rtd/skipped                RtdSkipped         (no id)
    twin/line1/rtd/progress               AdoptionProgress   (no id; also closeloop/progress)
    twin/line1/oos/alert                  OosAlert           (no id)
    twin/line1/trace/outlet               LotComposition     (no id)
    twin/line1/trace/batch                BatchBoundary      (no id)
    twin/line1/divert/command             DivertCommand      (no id)
    twin/line1/dem/job7/request|progress|result
    twin/line1/service/recorder/health    ServiceHealth
    twin/line1/service/recorder/alive     liveliness token of a running service

Keys have no leading ``/``. Each segment is a non-empty token of ``[A-Za-z0-9_.-]``
(no wildcards), so a concrete key never matches more than itself.

Every key a service publishes and every key expression it subscribes to is built here: the
concrete builders below and the wildcard builders (``feeder_flows``, ``events``, ``everything``,
...), so that no other module spells a key.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import re
from dataclasses import dataclass

from schemas.base import IDENT_PATTERN, Message

ROOT = "twin"
_SEGMENT = re.compile(IDENT_PATTERN)
log = logging.getLogger(__name__)


def _check_segment(name: str, value: str) -> str:
    if not isinstance(value, str) or not _SEGMENT.match(value):
        raise ValueError(
            f"{name} must be a non-empty token of [A-Za-z0-9_.-] (no '/', wildcards or spaces), "
            f"got {value!r}"
        )
    return value


@dataclass(frozen=True)
class Key:
    """A parsed key expression. ``id`` is None for the 4-segment form."""

    line: str
    unit: str
    signal: str
    id: str | None = None

    def __post_init__(self) -> None:
        _check_segment("line", self.line)
        _check_segment("unit", self.unit)
        _check_segment("signal", self.signal)
        if self.id is not None:
            _check_segment("id", self.id)

    def __str__(self) -> str:
        if self.id is None:
            return f"{ROOT}/{self.line}/{self.unit}/{self.signal}"
        return f"{ROOT}/{self.line}/{self.unit}/{self.id}/{self.signal}"


def key(line: str, unit: str, signal: str, id: str | None = None) -> str:
    """Build a key expression, e.g. ``key("line1", "feeder", "flow", id="api")``
    -> ``"twin/line1/feeder/api/flow"``. Raises ValueError naming a bad segment."""
    return str(Key(line=line, unit=unit, signal=signal, id=id))


def parse_key(expr: str) -> Key:
    """Parse a concrete key expression; raises ValueError if it is not of the twin's form."""
    if not isinstance(expr, str):
        raise ValueError(f"key must be a string, got {expr!r}")
    parts = expr.split("/")
    if parts[0] != ROOT:
        raise ValueError(f"key must start with '{ROOT}/', got {expr!r}")
    if len(parts) == 4:
        return Key(line=parts[1], unit=parts[2], signal=parts[3])
    if len(parts) == 5:
        return Key(line=parts[1], unit=parts[2], id=parts[3], signal=parts[4])
    raise ValueError(
        f"key must have the form twin/<line>/<unit>/[<id>/]<signal>, got {expr!r} "
        f"({len(parts)} segments)"
    )


# Convenience builders for the standard keys.
def feeder_flow(line: str, feeder_id: str) -> str:
    return key(line, "feeder", "flow", feeder_id)


def measured_concentration(line: str, sensor: str) -> str:
    return key(line, "pat", "concentration", sensor)


def predicted_concentration(line: str, location: str = "outlet") -> str:
    return key(line, "blender", "predicted", location)


def blender_drive(line: str, blender_id: str = "blender") -> str:
    """The blade drive of a blender (``BlenderDrive``)."""
    return key(line, "blender", "drive", blender_id)


def blender_model_update(line: str, source: str) -> str:
    """A new compartment model of the blender from ``source`` (``BlenderModelUpdate``)."""
    return key(line, "blender", "model", source)


def blender_model_in_use(line: str, location: str = "outlet") -> str:
    """The model the blender predicts with (``BlenderModelInUse``)."""
    return key(line, "blender", "model_in_use", location)


def event(line: str, unit: str, id: str) -> str:
    return key(line, unit, "event", id)


def rtd_estimate(line: str) -> str:
    return key(line, "rtd", "estimate")


def rtd_skipped(line: str) -> str:
    """Tracer pulses the rtd service did not fit, and why (``RtdSkipped``)."""
    return key(line, "rtd", "skipped")


def model_finding(line: str) -> str:
    return key(line, "closeloop", "finding")


#: the producers of model updates the blender and the diverter adopt (``AdoptionProgress``)
ADOPTION_SOURCES = ("rtd", "closeloop")


def adoption_progress(line: str, unit: str) -> str:
    """How far the model updates of ``unit`` (``rtd`` or ``closeloop``) are complete
    (``AdoptionProgress``)."""
    if unit not in ADOPTION_SOURCES:
        raise ValueError(f"unit must be one of {list(ADOPTION_SOURCES)}, got {unit!r}")
    return key(line, unit, "progress")


def trace_outlet(line: str) -> str:
    """The lot composition of the product at the blender outlet (``LotComposition``)."""
    return key(line, "trace", "outlet")


def trace_batch(line: str) -> str:
    """Batch boundaries at the blender outlet (``BatchBoundary``)."""
    return key(line, "trace", "batch")


def oos_alert(line: str) -> str:
    return key(line, "oos", "alert")


def divert_command(line: str) -> str:
    return key(line, "divert", "command")


def audit_record(line: str) -> str:
    """The audit trail's records (``schemas.audit.AuditRecord``), published by the
    supervisor alone."""
    return key(line, "audit", "record")


def dem_job(line: str, job_id: str, signal: str) -> str:
    if signal not in ("request", "progress", "result"):
        raise ValueError(f"signal must be 'request', 'progress' or 'result', got {signal!r}")
    return key(line, "dem", signal, job_id)


def service_health(line: str, service: str) -> str:
    return key(line, "service", "health", service)


def service_alive(line: str, service: str) -> str:
    return key(line, "service", "alive", service)


def service_ping(line: str, service: str) -> str:
    """Queryable answering a ping with the service's health and per-key sample counts."""
    return key(line, "service", "ping", service)


def replay_event(line: str) -> str:
    """Events of the virtual plant's replay (``END_OF_STREAM`` after the last sample)."""
    return event(line, "plant", "replay")


# ---------------------------------------------------------------------------------------------
# wildcard key expressions (subscriptions, queries)

#: every key of every line
ALL_LINES = f"{ROOT}/**"


def _wild(line: str, *segments: str) -> str:
    """``twin/<line>/<segments>``; ``line`` may be ``*`` (every line), each other segment a token
    or the chunk wildcard ``*``."""
    if line != "*":
        _check_segment("line", line)
    for s in segments:
        if s not in ("*", "**"):
            _check_segment("segment", s)
    return "/".join((ROOT, line, *segments))


def everything(line: str) -> str:
    """Every key of a line (``twin/<line>/**``): what the recorder records."""
    return _wild(line, "**")


def feeder_flows(line: str) -> str:
    """The flows of every feeder (``twin/<line>/feeder/*/flow``)."""
    return _wild(line, "feeder", "*", "flow")


def blender_drives(line: str) -> str:
    """Every blender drive of a line."""
    return _wild(line, "blender", "*", "drive")


def blender_model_updates(line: str) -> str:
    """Every new blender model of a line."""
    return _wild(line, "blender", "*", "model")


def events(line: str) -> str:
    """Every event of every unit (``twin/<line>/*/*/event``)."""
    return _wild(line, "*", "*", "event")


def dem_requests(line: str) -> str:
    """DEM job requests of every job (``twin/<line>/dem/*/request``)."""
    return _wild(line, "dem", "*", "request")


def dem_jobs(line: str, signal: str) -> str:
    """One signal of every DEM job (``twin/<line>/dem/*/<signal>``)."""
    if signal not in ("request", "progress", "result"):
        raise ValueError(f"signal must be 'request', 'progress' or 'result', got {signal!r}")
    return _wild(line, "dem", "*", signal)


def measured_concentrations(line: str) -> str:
    """The concentration of every PAT sensor (``twin/<line>/pat/*/concentration``)."""
    return _wild(line, "pat", "*", "concentration")


def service_keys(line: str, service: str) -> str:
    """A service's own keys: health, liveliness token, ping (``twin/<line>/service/<name>/*``)."""
    return _wild(line, "service", service, "*")


def services_health(line: str) -> str:
    """Health of every service (``twin/<line>/service/*/health``; ``line`` may be ``*``)."""
    return _wild(line, "service", "*", "health")


def services_alive(line: str) -> str:
    """Liveliness tokens of every service (``twin/<line>/service/*/alive``)."""
    return _wild(line, "service", "*", "alive")


def services_ping(line: str) -> str:
    """Ping queryables of every service (``twin/<line>/service/*/ping``)."""
    return _wild(line, "service", "*", "ping")


def is_service_key(expr: str) -> bool:
    """Whether a key belongs to a service's own reporting (health, ping), not to plant data."""
    parts = expr.split("/")
    return len(parts) > 2 and parts[0] == ROOT and parts[2] == "service"


#: suffix of the cache queryables of zenoh advanced publishers
#: (``<key>/@adv/pub/<zid>/<eid>/<meta>``, zenoh-ext's advanced pub/sub wire protocol)
ADVANCED_CACHE_SUFFIX = "@adv/pub/**"


def advanced_caches(key_expr: str) -> str:
    """The cache queryables of the advanced publishers on ``key_expr`` (their history)."""
    return f"{key_expr}/{ADVANCED_CACHE_SUFFIX}"


#: the chunk under which zenoh-ext advanced publishers and subscribers keep their caches,
#: heartbeats and detection tokens (a verbatim chunk: ``*`` and ``**`` do not match it)
ADVANCED_CHUNK = "@adv"


def advanced(key_expr: str) -> str:
    """Everything zenoh-ext keeps under ``key_expr`` for advanced publishers and subscribers
    (caches, miss-detection heartbeats, detection tokens): ``<key_expr>/@adv/**``."""
    return f"{key_expr}/{ADVANCED_CHUNK}/**"


# ---------------------------------------------------------------------------------------------
# signal -> model registry

_REGISTRY: dict[str, type[Message]] = {}
_MISSES: set[str] = set()
_discovered = False


def register_signal(signal: str, model: type[Message]) -> None:
    """Map a signal name (last key segment) to its message model. Overrides earlier entries."""
    _check_segment("signal", signal)
    _REGISTRY[signal] = model
    _MISSES.discard(signal)


def _all_subclasses(cls: type) -> list[type]:
    out = []
    for sub in cls.__subclasses__():
        out.append(sub)
        out.extend(_all_subclasses(sub))
    return out


def discover_schema_modules() -> list[str]:
    """Import every module of the ``schemas`` package (pkgutil); return the names imported.

    A module that fails to import is logged and skipped (it cannot take the bus down).
    """
    import schemas

    names = []
    for info in pkgutil.iter_modules(schemas.__path__, prefix="schemas."):
        try:
            importlib.import_module(info.name)
        except Exception as exc:  # noqa: BLE001 - another area's module must not break ours
            log.warning("cannot import %s: %s", info.name, exc)
            continue
        names.append(info.name)
    return names


def _refresh() -> None:
    global _discovered
    import schemas.messages  # noqa: F401 - defines the standard messages

    if not _discovered:
        discover_schema_modules()
        _discovered = True
    for model in _all_subclasses(Message):
        signal = getattr(model, "SIGNAL", None)
        if signal and signal not in _REGISTRY:
            _REGISTRY[signal] = model


def model_for_signal(signal: str) -> type[Message] | None:
    """Message model registered for a signal name, or None."""
    if signal not in _REGISTRY and signal not in _MISSES:
        _refresh()
        if signal not in _REGISTRY:
            _MISSES.add(signal)
    return _REGISTRY.get(signal)


def model_for_key(expr: str) -> type[Message] | None:
    """Message model of a concrete key expression (by its signal), or None if unknown."""
    try:
        signal = parse_key(expr).signal
    except ValueError:
        return None
    return model_for_signal(signal)
