"""Shared fixtures. Helpers for a single subsystem belong in that subsystem's test file."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED_DATA = Path(os.environ.get("PASST_SHARED_DATA", REPO.parent / "shared" / "data"))
HF_RADAR_FILE = "RU_MARA_20180301T000000Z-20180301T120000Z_aggregated.nc"


@pytest.fixture(scope="session")
def hf_radar_path() -> Path:
    """The real MARACOOS HF-radar file from ../shared/data (skips when absent)."""
    p = SHARED_DATA / HF_RADAR_FILE
    if not p.exists():
        pytest.skip(f"real HF-radar file not found at {p} (../shared/data is not beside the checkout)")
    return p


#: test modules (besides the ``sitl`` tests) that run a simulator in wall time: one at a time under xdist
WALL_CLOCK_MODULES = {"test_view_browser"}
#: test modules holding tests of half a minute or more (training, a tutorial flight, reports): started first
LONG_TEST_MODULES = {
    "test_training",
    "test_getting_started",
    "test_counterfactual",
    "test_report",
    "test_run_missions",
    "test_console_browser",
    "test_determinism",
    "test_resilience",
    "test_fleet_controller",
    "test_cylinder",
}
#: test modules whose module-scoped fixtures take seconds to build (a flight, a campaign, a log, a fitted model)
COSTLY_FIXTURE_MODULES = {
    "test_dataflash_legs",
    "test_evaluate",
    "test_export",
    "test_fleet_offline",
    "test_ocean",
    "test_paper",
    "test_plan_cmd",
    "test_prior_blend",
    "test_model_real_files",
    "test_replay",
    "test_tlog",
}


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads the xdist_group marks (--dist loadgroup)
def pytest_collection_modifyitems(config, items):
    """Tests marked ``sitl`` run when the ArduPilot SITL build is beside the checkout, else skip saying why.

    Groups for pytest-xdist (pyproject: ``-n auto --dist loadgroup``), one per test at most:

    * ``wall_clock``: every SITL test, and the headless-browser test of the live view, on one worker,
      one at a time. SITL instances and ports are already safe across processes (tests/sitl.py claims
      an instance by a lock file), but these tests run the firmware or ``passt-mav demo`` in wall time
      at a speed-up, and two at once on a 2-core machine starve each other.
    * the test module's name, for the tests of a module in ``COSTLY_FIXTURE_MODULES`` that use its
      module-scoped fixture: such a fixture (a flown run, a campaign, a recorded log) is built once
      per worker that runs one of its tests, so they stay on one worker instead of building it on
      each. Modules whose module fixtures are cheap (a small synthetic field) are not grouped: their
      tests spread over the workers, which matters for long modules such as test_training.

    Every other test goes to whichever worker is free; the ``wall_clock`` group and the modules in
    ``LONG_TEST_MODULES`` are collected first, so that their minute-long tests start early instead of
    ending the run alone on one worker while the other waits.
    """
    import sitl as sitl_mod  # tests/sitl.py (tests/ is on sys.path)

    _check_left_out_tests_say_why(items)
    reason = sitl_mod.unavailable_reason()

    def late(it) -> bool:
        """Collected after the long ones: the wall-clock group (minutes on one worker) and the long modules
        start first, so that neither ends the run alone on one worker while the other waits."""
        name = getattr(getattr(it, "module", None), "__name__", "")
        return not ("sitl" in it.keywords or name in WALL_CLOCK_MODULES or name in LONG_TEST_MODULES)

    items.sort(key=late)
    for item in items:
        module = getattr(item, "module", None)
        if "sitl" in item.keywords and reason:
            item.add_marker(pytest.mark.skip(reason=reason))
        if "sitl" in item.keywords or (module is not None and module.__name__ in WALL_CLOCK_MODULES):
            item.add_marker(pytest.mark.xdist_group("wall_clock"))
        elif (
            module is not None and module.__name__ in COSTLY_FIXTURE_MODULES and _uses_own_shared_fixture(item, module)
        ):
            item.add_marker(pytest.mark.xdist_group(module.__name__))


#: markers that leave a test out of the default run; each use must say why (``reason=``)
LEFT_OUT_MARKERS = ("long", "slow")


def _check_left_out_tests_say_why(items) -> None:
    """A test marked ``long`` or ``slow`` without ``reason="..."`` stops the collection, naming it: the
    default run is kept short by leaving such tests out, and each one must say what makes it long."""
    bare = sorted(
        {
            f"{it.nodeid} (@pytest.mark.{m.name})"
            for it in items
            for m in it.iter_markers()
            if m.name in LEFT_OUT_MARKERS and not str(m.kwargs.get("reason", "")).strip()
        }
    )
    if bare:
        raise pytest.UsageError(f"marked long/slow without reason=: {', '.join(bare)}")


def _uses_own_shared_fixture(item, module) -> bool:
    """True when the item uses a module- or class-scoped fixture defined in its own test module."""
    info = getattr(item, "_fixtureinfo", None)  # pytest's per-item fixture closure (no public accessor)
    if info is None:
        return False
    for defs in info.name2fixturedefs.values():
        for d in defs:
            code = getattr(d.func, "__code__", None)
            if d.scope in ("module", "class") and code is not None and code.co_filename == module.__file__:
                return True
    return False


@pytest.fixture
def sitl_factory(tmp_path_factory):
    """``start(**options) -> tests/sitl.Sitl``: start ArduRover SITL instances; all are killed at teardown.

    Options: ``speedup`` (default 10), ``home`` (lat, lon), ``params`` (.parm file), ``scripts``
    (folder of .lua), ``sysid``, ``workdir`` (default: a fresh temporary folder). See tests/sitl.py.
    """
    import sitl as sitl_mod

    reason = sitl_mod.unavailable_reason()
    if reason:
        pytest.skip(reason)
    started = []

    def start(workdir=None, **options):
        wd = Path(workdir) if workdir else tmp_path_factory.mktemp("sitl")
        s = sitl_mod.start(wd, **options)
        started.append(s)
        return s

    yield start
    for s in started:
        s.stop()


@pytest.fixture
def sitl(sitl_factory):
    """One ArduRover SITL boat at speedup 10, fresh work directory, free instance (tests/sitl.py)."""
    return sitl_factory()


@pytest.fixture(scope="session")
def na_grid():
    """The paper's 30x30 North Atlantic grid."""
    import geo

    return geo.north_atlantic_grid()


@pytest.fixture(autouse=True, scope="session")
def _few_threads():
    """Two cores are shared by everything on CI: keep torch and the BLAS under numpy/scikit-learn from
    oversubscribing (with pytest-xdist, the cores are split between the workers). Unbounded, each worker's
    OpenBLAS ran a thread per core beside the other worker's and a joblib test's processes, and the threads
    spun waiting for each other, slowing the GP tests many times over."""
    import numpy  # noqa: F401 - loaded first: threadpoolctl limits the pools of the libraries loaded so far
    import scipy.linalg  # noqa: F401 - (scipy's own OpenBLAS)
    import sklearn  # noqa: F401 - (its OpenMP runtime)
    from threadpoolctl import threadpool_limits

    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    n = max(1, min(2, (os.cpu_count() or 1) // workers))
    limits = threadpool_limits(limits=n)
    try:
        import torch

        torch.set_num_threads(n)
    except ImportError:  # pragma: no cover
        pass
    yield
    limits.restore_original_limits()
