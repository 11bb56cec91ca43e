"""Streaming, incremental computations for the live twin (no networking, no global state): the
cores of the live services, usable from a notebook.

- :mod:`~twin_core.online.blender`: the blender's prediction core (``BlenderPredictor``) and its
  E(t) as the twin adopts it (``BlenderKernel``, shared with the diverter).
- :mod:`~twin_core.online.oos`: the diverter's stream core (``OosCore``).
- :mod:`~twin_core.online.rtd`: tracer-pulse experiments -> RTD estimates (``RtdCore``).
- :mod:`~twin_core.online.convolution`: streaming RTD convolution (outlet prediction).
- :mod:`~twin_core.online.alerts`: OOS episode tracking with hysteresis and stable ids.
- :mod:`~twin_core.online.funnel`: funnel-based early flag of feeder disturbances (the funnel
  gain itself is ``twin_core.quality.funnel.funnel_gain``).
- :mod:`~twin_core.online.tracer`: tracer-pulse detection in a PAT signal.
- :mod:`~twin_core.online.inlet`: the one alignment of per-feeder samples into inlet ticks, the
  tracer pulses they hold, the one reading of a tracer event.
- :mod:`~twin_core.online.diverter`: OOS alerts and divert commands of one component.
- :mod:`~twin_core.online.merge`: event-time (watermark) merge of streams.
- :mod:`~twin_core.online.plots`: figures of the live twin.

The close-loop's streaming core is ``twin_core.closeloop.online.OnlineCloseLoop``.
"""

from twin_core.online.alerts import Episode, EpisodeEvent, HysteresisTracker, episode_id
from twin_core.online.blender import BlenderKernel, BlenderPredictor, FlowMemory
from twin_core.online.convolution import StreamingConvolver
from twin_core.online.diverter import DiverterOutput, OosDecider
from twin_core.online.funnel import FlagEvent, FunnelFlagger
from twin_core.online.inlet import (
    FeederSample,
    InletAligner,
    InletStream,
    InletTick,
    TracerInjector,
    composition_pct,
    event_record,
    tracer_pulse,
)
from twin_core.online.merge import WatermarkMerger
from twin_core.online.oos import OosCore
from twin_core.online.rtd import PulseOutcome, RtdCore, RtdResult, analyze_segment
from twin_core.online.tracer import TracerPulseDetector, TracerSegment

__all__ = [
    "BlenderKernel",
    "BlenderPredictor",
    "DiverterOutput",
    "Episode",
    "EpisodeEvent",
    "FeederSample",
    "FlagEvent",
    "FlowMemory",
    "FunnelFlagger",
    "HysteresisTracker",
    "InletAligner",
    "InletStream",
    "InletTick",
    "OosCore",
    "OosDecider",
    "PulseOutcome",
    "RtdCore",
    "RtdResult",
    "StreamingConvolver",
    "TracerInjector",
    "TracerPulseDetector",
    "TracerSegment",
    "WatermarkMerger",
    "analyze_segment",
    "composition_pct",
    "episode_id",
    "event_record",
    "tracer_pulse",
]
