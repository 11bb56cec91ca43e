"""Streaming, incremental computations for the live twin (no networking, no global state).

- :mod:`~twin_core.online.convolution`: streaming RTD convolution (outlet prediction).
- :mod:`~twin_core.online.alerts`: OOS episode tracking with hysteresis and stable ids.
- :mod:`~twin_core.online.funnel`: funnel-based early flag of feeder disturbances.
- :mod:`~twin_core.online.tracer`: tracer-pulse detection in a PAT signal.
- :mod:`~twin_core.online.inlet`: alignment of per-feeder flows into inlet composition.
- :mod:`~twin_core.online.diverter`: OOS alerts and divert commands of one component.
- :mod:`~twin_core.online.merge`: event-time (watermark) merge of streams.
"""

from twin_core.online.alerts import Episode, EpisodeEvent, HysteresisTracker, episode_id
from twin_core.online.convolution import StreamingConvolver
from twin_core.online.diverter import DiverterOutput, OosDecider
from twin_core.online.funnel import FlagEvent, FunnelFlagger, window_gain
from twin_core.online.inlet import InletAligner, TracerInjector, composition_pct
from twin_core.online.merge import WatermarkMerger
from twin_core.online.tracer import TracerPulseDetector, TracerSegment

__all__ = [
    "DiverterOutput",
    "Episode",
    "EpisodeEvent",
    "FlagEvent",
    "FunnelFlagger",
    "HysteresisTracker",
    "InletAligner",
    "OosDecider",
    "StreamingConvolver",
    "TracerPulseDetector",
    "TracerInjector",
    "TracerSegment",
    "WatermarkMerger",
    "composition_pct",
    "episode_id",
    "window_gain",
]
