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


def pytest_collection_modifyitems(config, items):
    """Tests marked ``sitl`` run when the ArduPilot SITL build is beside the checkout, else skip saying why."""
    import sitl as sitl_mod  # tests/sitl.py (tests/ is on sys.path)

    reason = sitl_mod.unavailable_reason()
    if reason:
        for item in items:
            if "sitl" in item.keywords:
                item.add_marker(pytest.mark.skip(reason=reason))


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
    """Two cores are shared by everything on CI: keep torch from oversubscribing."""
    try:
        import torch

        torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
    except ImportError:  # pragma: no cover
        pass
    yield
