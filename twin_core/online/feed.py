"""Does what the twin is fed match its configuration? The twin's predictions and limits hold
only for the line it declares: a recording or a line with other feeders, components or set
points gives false alarms (a 5 % API recording read with a 10 % target is a whole-run OOS).

Two sources are compared with the declared line (:class:`~schemas.line.LineConfig`):

- a recording's provenance (its line configuration, :func:`line_mismatches`): line name,
  feeder ids, their components and set points, the sensor and the component it measures;
- the first messages of a feed (:class:`FeedCheck`): the first flow of each feeder (its
  component and set point) and the first measurement (sensor and component).

Set points are equal within ``SETPOINT_RTOL`` (recordings round them). Each difference is a
:class:`Mismatch` naming the field, the fed value and the configured one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from schemas.line import LineConfig

__all__ = ["SETPOINT_RTOL", "FeedCheck", "Mismatch", "line_mismatches"]

#: relative tolerance of a set point (recordings store them rounded)
SETPOINT_RTOL = 1e-3


@dataclass(frozen=True)
class Mismatch:
    """One difference between a feed and the declared line: ``field`` (dotted path of the line
    configuration), the value fed and the value configured."""

    field: str
    fed: Any
    configured: Any

    def __str__(self) -> str:
        return f"{self.field}: fed {self.fed!r}, configured {self.configured!r}"


def _setpoint_differs(fed: float | None, configured: float) -> bool:
    if fed is None:
        return False
    return not math.isclose(fed, configured, rel_tol=SETPOINT_RTOL, abs_tol=1e-9)


def line_mismatches(configured: LineConfig, fed: Mapping[str, Any]) -> list[Mismatch]:
    """The differences between a recorded line configuration ``fed`` (a ``LineConfig`` dict,
    e.g. a recording's provenance) and the ``configured`` line: name, feeders (ids, components,
    set points), sensor (id, component)."""
    out: list[Mismatch] = []
    if fed.get("name") not in (None, configured.name):
        out.append(Mismatch("name", fed.get("name"), configured.name))
    fed_feeders = {f["id"]: f for f in fed.get("feeders", [])}
    ours = {f.id: f for f in configured.feeders}
    if set(fed_feeders) != set(ours):
        out.append(Mismatch("feeders", sorted(fed_feeders), sorted(ours)))
    for fid in sorted(set(fed_feeders) & set(ours)):
        f, c = fed_feeders[fid], ours[fid]
        if f.get("component") != c.component:
            out.append(Mismatch(f"feeders.{fid}.component", f.get("component"), c.component))
        if _setpoint_differs(f.get("setpoint_kg_h"), c.setpoint_kg_h):
            out.append(
                Mismatch(f"feeders.{fid}.setpoint_kg_h", f["setpoint_kg_h"], c.setpoint_kg_h)
            )
    sensor = fed.get("sensor") or {}
    for name in ("id", "component"):
        if sensor.get(name) not in (None, getattr(configured.sensor, name)):
            out.append(Mismatch(f"sensor.{name}", sensor[name], getattr(configured.sensor, name)))
    return out


class FeedCheck:
    """Checks the first messages of a feed against the declared line (module docstring): call
    :meth:`flow` and :meth:`measured` with every message; each returns the mismatches found by
    the first message of its feeder or sensor (later ones return ``[]``). :attr:`mismatches`
    holds all found so far."""

    def __init__(self, line: LineConfig) -> None:
        self.line = line
        self.feeders = {f.id: f for f in line.feeders}
        self.mismatches: list[Mismatch] = []
        self._seen: set[str] = set()

    def _first(self, what: str) -> bool:
        if what in self._seen:
            return False
        self._seen.add(what)
        return True

    def _found(self, found: list[Mismatch]) -> list[Mismatch]:
        self.mismatches += found
        return found

    def flow(self, feeder: str, component: str, setpoint_kg_h: float | None) -> list[Mismatch]:
        """A flow of ``feeder`` (its component and set point as fed)."""
        if not self._first(f"feeder:{feeder}"):
            return []
        c = self.feeders.get(feeder)
        if c is None:
            return self._found([Mismatch("feeders", feeder, sorted(self.feeders))])
        found = []
        if component != c.component:
            found.append(Mismatch(f"feeders.{feeder}.component", component, c.component))
        if _setpoint_differs(setpoint_kg_h, c.setpoint_kg_h):
            found.append(
                Mismatch(f"feeders.{feeder}.setpoint_kg_h", setpoint_kg_h, c.setpoint_kg_h)
            )
        return self._found(found)

    def measured(self, sensor: str, component: str) -> list[Mismatch]:
        """A measurement of ``sensor`` (the component it says it measures)."""
        if not self._first(f"sensor:{sensor}"):
            return []
        s = self.line.sensor
        found = []
        if sensor != s.id:
            found.append(Mismatch("sensor.id", sensor, s.id))
        if component != s.component:
            found.append(Mismatch("sensor.component", component, s.component))
        return self._found(found)
