"""Resumable result files of the benchmarks: one CSV row per finished run, appended and flushed
as runs finish, so an interrupted benchmark resumes where it stopped."""

from __future__ import annotations

import csv
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any


def read_rows(path: Path) -> list[dict[str, str]]:
    """The rows already in ``path`` (none when it does not exist); creates its folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists():
        return []
    with path.open() as f:
        return list(csv.DictReader(f))


@contextmanager
def row_appender(path: Path, fields: list[str], done: list[dict[str, str]]) -> Iterator[Any]:
    """``append(row)``: writes ``row`` to ``path`` (header first on a new file), flushes, and adds
    it to ``done`` as the strings a re-read would give."""
    new_file = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        if new_file:
            writer.writeheader()

        def append(row: Mapping[str, Any]) -> None:
            writer.writerow(row)
            f.flush()
            done.append({k: str(v) for k, v in row.items()})

        yield append
