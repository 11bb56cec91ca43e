"""Campaign run functions for the worker tests (importable by pool workers)."""

from __future__ import annotations

import os
import time
from pathlib import Path


def sleepy_run(params: dict, seed: int) -> dict:
    """Write this worker's pid to ``$CAMPAIGN_TEST_PID_DIR/<seed>.pid``, then sleep
    ``params["sleep_s"]``; returns ``{"slept": sleep_s}``."""
    Path(os.environ["CAMPAIGN_TEST_PID_DIR"], f"{seed}.pid").write_text(str(os.getpid()))
    time.sleep(float(params["sleep_s"]))
    return {"slept": float(params["sleep_s"])}
