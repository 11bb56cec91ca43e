"""Shared pytest configuration.

Each pytest-xdist worker gets its own numba cache directory: two processes compiling the same
cached function into one ``__pycache__`` at once can leave a corrupt cache entry on a fresh
clone. Set before any test module imports numba.
"""

import os
from pathlib import Path

import pytest

os.environ.setdefault(
    "NUMBA_CACHE_DIR",
    str(
        Path(__file__).resolve().parent.parent
        / ".numba_cache"
        / os.environ.get("PYTEST_XDIST_WORKER", "main")
    ),
)
os.environ.setdefault("MPLBACKEND", "Agg")
# small dense products: threaded BLAS on a 2-core machine shared by two workers is far slower
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import matplotlib  # noqa: E402

matplotlib.use("Agg")


@pytest.fixture
def one_numba_thread():
    """One numba thread for the test, restored afterwards: the engine's parallel loops are slow
    on a shared, oversubscribed 2-core machine, and results do not depend on the thread count
    (``test_results_do_not_depend_on_thread_count``)."""
    import numba

    old = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(old)
