"""The close-loop on a recorded run, from its messages to the report (``twin close-loop``).

:func:`check_recording` turns the decoded messages of a recording into the run's arrays with the
twin's one message-to-array adapter (``twin_core.closeloop.record.LineRecord``, on the sensor's
sampling grid, flows keyed by feeder id), checks the declared model against the NIR readings
(``twin_core.closeloop.report.close_loop``: residual -> candidate effects -> held-out test ->
augmented model), optionally with the NIR noise estimated from the record's quiet samples
(``twin_core.closeloop.noise``), and returns the report (``schemas.closeloop.CloseLoopReport``
fields) with the figures written where asked (``twin_core.closeloop.plots``).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal

from schemas.line import LineConfig
from twin_core.closeloop.identify import IdentifyOptions
from twin_core.closeloop.plots import closeloop_figures
from twin_core.closeloop.record import LineRecord
from twin_core.closeloop.report import close_loop
from twin_core.plant.model import LineModel

__all__ = ["check_recording"]


def _declared_noise(config: LineConfig) -> dict[str, Any]:
    n = config.sensor.noise
    return {
        "source": "declared",
        "white_sd": n.white_sd,
        "pink_sd": n.pink_sd,
        "proportional_rel": n.proportional_rel,
    }


def check_recording(
    messages: Iterable[tuple[str, Any]],
    config: LineConfig,
    options: IdentifyOptions,
    *,
    noise: Literal["declared", "estimate"] = "declared",
    recording: str = "recording",
    figures_dir: str | Path | None = None,
) -> dict[str, Any]:
    """The close-loop report of a recorded run (see the module docstring).

    Args:
        messages: (key, decoded message) pairs of the recording, in plant-time order.
        config: the declared line (its tracers are used when the record announces none).
        options: identification options (candidates, max effects, alpha, split, ...).
        noise: the NIR noise of the decisions: ``declared`` (config) or ``estimate``d from the
            record's quiet samples.
        recording: the recording's name in the report.
        figures_dir: where to write the PNG figures (listed in the report's ``figures``).
    """
    sensor = config.sensor
    record = LineRecord.from_messages(
        messages, config.components, sensor.sample_period_s, sensor.component
    )
    data = record.run_data(Path(recording).name)
    if not data.inputs.tracers:
        data.inputs.tracers = list(config.tracers)
    model = LineModel(config)
    noise_report = _declared_noise(config)
    if noise == "estimate":
        from twin_core.closeloop.noise import with_estimated_noise

        model, est = with_estimated_noise(data, model)
        noise_report = {"source": "estimated", **est.to_dict()}
    result = close_loop(data, model, options, recording=recording)
    report = result.to_dict()
    report["noise"] = noise_report
    if figures_dir is not None:
        out = Path(figures_dir)
        out.mkdir(parents=True, exist_ok=True)
        report["figures"] = []
        for name, fig in closeloop_figures(result).items():
            fig.savefig(out / name, dpi=110)
            report["figures"].append(str(out / name))
    return report
