import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def pytest_configure(config):
    """The tests test this checkout. Its folder core/ is imported as `quakescan` only through an
    install (an editable one by .ci/setup): a virtual environment set up in another checkout,
    or a wheel, would be tested instead, silently, as the folder no longer shadows the name."""
    import importlib.util

    spec = importlib.util.find_spec("quakescan")
    found = Path(spec.origin).resolve().parent if spec is not None and spec.origin else None
    if found != ROOT / "core":
        raise pytest.UsageError(f"`quakescan` is {found or 'not installed'}, not this checkout's {ROOT / 'core'}: "
                                f"run `bash .ci/setup` here and test with {ROOT / '.venv/bin/python'}")


@pytest.fixture(scope="session", autouse=True)
def private_model_cache(tmp_path_factory):
    """The tests' models are kept in a cache of their own (`quakescan.learning.model_cache`),
    never in the user's: the commands the tests run in subprocesses inherit it too."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("QUAKESCAN_CACHE_DIR", str(tmp_path_factory.mktemp("quakescan-cache")))
        yield


@pytest.fixture
def shared_data():
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture
def one_native_thread():
    """OpenMP/BLAS limited to one thread: for tiny fits and predictions, where thread
    start-up and, on a shared machine, threads waiting for a core cost more than the work
    (boosting and sigmoid calibration 10-20x slower on 2 busy cores)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        yield
