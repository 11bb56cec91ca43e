"""The machine a benchmark ran on, for the first line of its report.

Run: ``python benchmarks/machine.py`` prints it; the benchmarks import :func:`describe`.
"""

from __future__ import annotations

import os
import platform


def cpu_model() -> str:
    """CPU model name (``/proc/cpuinfo`` on Linux, else what ``platform`` knows)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def describe() -> str:
    """``machine: <cpu>, <n> CPUs, Python <version>``."""
    return f"machine: {cpu_model()}, {os.cpu_count()} CPUs, Python {platform.python_version()}"


if __name__ == "__main__":
    print(describe())
