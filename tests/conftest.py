"""Shared pytest configuration.

DEM trend tests (marker ``dem_trend``) take their scene seeds from the global test seed
``TWIN_TEST_SEED`` (integer >= 0, default 0) through the ``dem_seed`` / ``dem_seeds`` fixtures, so
the same claims can be checked on other samples of the same physics (``make test-seeds``).

Each pytest-xdist worker gets its own numba cache directory: two processes compiling the same
cached function into one ``__pycache__`` at once can leave a corrupt cache entry on a fresh
clone (the workers inherit the controller's environment, so the directory is set in each). The
directory is keyed by a hash of the package's sources: numba checks a cached kernel against its
own file only, so after an edit to a function that kernels of other files inline, a cache keyed
per file would run the old code in the tests. Caches of other source states are removed by the
controlling process. Set before any test module imports numba.
"""

import hashlib
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

_ROOT = Path(__file__).resolve().parent.parent


def _source_key() -> str:
    """A short hash of every Python source of the package (paths and contents)."""
    h = hashlib.sha256()
    for path in sorted((_ROOT / "twin_core").rglob("*.py")):
        h.update(str(path.relative_to(_ROOT)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _numba_cache_dir() -> Path:
    """``.numba_cache/<source hash>/<worker>``; the controller removes the other hashes."""
    base = _ROOT / ".numba_cache"
    key = _source_key()
    if "PYTEST_XDIST_WORKER" not in os.environ and base.is_dir():
        for old in base.iterdir():
            if old.name != key:
                shutil.rmtree(old, ignore_errors=True)
    return base / key / os.environ.get("PYTEST_XDIST_WORKER", "main")


# xdist workers inherit the controller's environment: the controller's directory (under
# .numba_cache) is replaced by the worker's own; a directory the user chose is kept
_inherited = os.environ.get("NUMBA_CACHE_DIR")
if _inherited is None or Path(_inherited).is_relative_to(_ROOT / ".numba_cache"):
    os.environ["NUMBA_CACHE_DIR"] = str(_numba_cache_dir())
os.environ.setdefault("MPLBACKEND", "Agg")
# small dense products: threaded BLAS on a 2-core machine shared by two workers is far slower
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import matplotlib  # noqa: E402

matplotlib.use("Agg")

SEED_ENV = "TWIN_TEST_SEED"


def global_test_seed() -> int:
    """The global test seed: ``$TWIN_TEST_SEED`` as an integer >= 0, 0 when unset."""
    text = os.environ.get(SEED_ENV, "0").strip() or "0"
    try:
        seed = int(text)
    except ValueError:
        seed = -1
    if seed < 0:
        raise pytest.UsageError(f"{SEED_ENV} must be an integer >= 0, got {text!r}")
    return seed


def pytest_configure(config: pytest.Config) -> None:
    global_test_seed()  # a bad value stops the run before collection, with one line


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A test that takes its scene seeds from the global seed carries the ``dem_trend`` marker
    and vice versa, so ``make test-seeds`` reruns exactly the tests whose samples change."""
    seeded = {"dem_seed", "dem_seeds"}
    for item in items:
        uses_seed = bool(seeded & set(getattr(item, "fixturenames", ())))
        if uses_seed != (item.get_closest_marker("dem_trend") is not None):
            raise pytest.UsageError(
                f"{item.nodeid}: the dem_trend marker and the dem_seed/dem_seeds fixtures go "
                "together"
            )


def pytest_report_header(config: pytest.Config) -> str:
    return f"{SEED_ENV}={global_test_seed()} (DEM trend tests' scene seeds)"


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


@pytest.fixture(scope="session")
def dem_seed() -> int:
    """Scene seed (particle placement) of a DEM trend test that runs one sample: the global test
    seed itself."""
    return global_test_seed()


@pytest.fixture(scope="session")
def dem_seeds(dem_seed: int) -> Callable[[int], list[int]]:
    """Scene seeds of an ``n``-member DEM ensemble: ``n s, ..., n s + n - 1`` for global seed
    ``s`` (disjoint sets for different global seeds)."""

    def seeds(n: int) -> list[int]:
        return [dem_seed * n + i for i in range(n)]

    return seeds
