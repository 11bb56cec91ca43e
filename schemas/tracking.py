"""Material tracking on the bus (contract 1.8): the raw-material lots in the product leaving
the blender. Key: ``twin/<line>/trace/outlet`` (``schemas.keys.trace_outlet``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from schemas.base import Fraction, Ident, Message, NonNegative


class LotComposition(Message):
    """The lot composition of the product leaving the blender at ``t``
    (``twin_core.tracking``): each lot's mass fraction of the product (lots at or below 1e-6
    left out) and its component, the outlet mass flow and the hopper model tracked with.
    Key: ``twin/<line>/trace/outlet``."""

    SIGNAL = "outlet"

    lots: dict[Ident, Fraction] = Field(description="lot -> mass fraction of the product")
    components: dict[Ident, Ident] = Field(description="lot -> its component")
    outlet_kg_h: NonNegative = Field(description="product mass flow at the outlet, kg/h")
    hopper_model: Literal["fifo", "mixed", "mixture"] = Field(description="the hoppers' law")


class BatchBoundary(Message):
    """A batch starts or ends at the blender outlet (the line config's ``batch:``, ICH Q13
    section 3.1; ``twin_core.tracking.batches.BatchCounter``): batch ``batch`` starts with the
    tick at ``t`` or ends with it. Key: ``twin/<line>/trace/batch``."""

    SIGNAL = "batch"

    batch: int = Field(ge=1, description="batch number, from 1")
    boundary: Literal["start", "end"] = Field(description="the batch starts or ends at t")
    by: Literal["product_mass", "api_mass", "run_time"] = Field(description="what cuts batches")
    total: NonNegative = Field(description="quantity since the first batch started, kg or s")
