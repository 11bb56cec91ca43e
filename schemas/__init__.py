"""The wire contract: pydantic models of every bus message and configuration.

Pure data, validators and key builders: nothing here imports ``twin_core`` or ``services``
(numerics on a schema, e.g. a ``BlenderModel``'s E(t), live in ``twin_core``). One model per
concept: ``schemas.messages.Event`` is the plant event (also the simulator's),
``schemas.line.LineConfig`` / ``LineSpec`` the line with its feeders, blender and sensor.

``from schemas import FeederFlow, key`` works for the standard messages; other areas' schema
modules (``schemas.line``, ...) are imported explicitly by whoever uses them (never eagerly here).
"""

from schemas.base import Message, StrictModel, json_schema
from schemas.keys import Key, key, model_for_key, parse_key
from schemas.messages import (
    MESSAGE_MODELS,
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
    ServiceHealth,
)

__all__ = [
    "MESSAGE_MODELS",
    "DemJobProgress",
    "DemJobRequest",
    "DemJobResult",
    "DivertCommand",
    "Event",
    "FeederFlow",
    "Key",
    "MeasuredConcentration",
    "Message",
    "OosAlert",
    "PredictedConcentration",
    "RtdEstimate",
    "ServiceHealth",
    "StrictModel",
    "json_schema",
    "key",
    "model_for_key",
    "parse_key",
]
