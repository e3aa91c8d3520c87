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
