"""The blender's operating point as the plant reports it (blade speed, throughput).

:class:`OperatingPointTracker` follows the blade speed of ``BlenderDrive`` messages and the
throughput as the sum of the feeders' set points (``FeederFlow.setpoint_kg_h``), starting from
the point the line declares (``blender.blade_speed_rpm``, the feeders' ``setpoint_kg_h``). A
change larger than the tolerances (0.5 rev/min; 2 % of the throughput: set points, not the
noisy measured flows) is a new operating point; the blender and the diverter schedule it
(``BlenderKernel.schedule(t, "operating_point", ...)``) at the plant time of the message that
brought it, so both switch at the same tick whatever the machine load.
"""

from __future__ import annotations

from typing import Any

from twin_core.compartment.operating_point import OperatingPoint, configured_point

__all__ = ["OperatingPointTracker"]


class OperatingPointTracker:
    """See the module docstring.

    Args:
        config: the line (``schemas.line.LineConfig``).
        rpm_tol: smallest blade-speed change that counts, rev/min.
        throughput_rel_tol: smallest relative throughput change that counts.
    """

    def __init__(self, config: Any, rpm_tol: float = 0.5, throughput_rel_tol: float = 0.02) -> None:
        self.point = configured_point(config)
        self.rpm_tol = rpm_tol
        self.throughput_rel_tol = throughput_rel_tol
        self._setpoints = {f.id: float(f.setpoint_kg_h) for f in config.feeders}

    def drive(self, rpm: float) -> OperatingPoint | None:
        """A reported blade speed; the new operating point, or None when it did not change."""
        if rpm <= 0 or abs(rpm - self.point.rpm) < self.rpm_tol:
            return None
        self.point = OperatingPoint(float(rpm), self.point.throughput_kg_h)
        return self.point

    def setpoint(self, feeder: str, kg_h: float | None) -> OperatingPoint | None:
        """A feeder's reported set point (None: not reported); the new operating point, or
        None when the throughput did not change by the tolerance."""
        if kg_h is None or feeder not in self._setpoints:
            return None
        self._setpoints[feeder] = float(kg_h)
        q = sum(self._setpoints.values())
        ref = self.point.throughput_kg_h
        if q <= 0 or abs(q - ref) <= self.throughput_rel_tol * ref:
            return None
        self.point = OperatingPoint(self.point.rpm, q)
        return self.point
