"""Grid paths -> lat/lon waypoints.

A *grid path* (DESIGN.md data contract) is an integer array ``(L+1, 2)`` of
``(row, col)`` cells (row 0 = southern edge, col 0 = western edge) in which every
step goes to one of the 8 neighbours. A boat does not need a waypoint in every
cell: along a straight run (the same step repeated) it steers the same line, so
the run collapses into its end points. :func:`path_to_waypoints` keeps the first
cell, every turn point and the last cell, at cell centres.

Decisions documented here:

* Consecutive identical cells (a "stay" step) are **dropped** by
  :func:`validate_path`: they carry no motion, and a stay would otherwise split a
  straight run. The returned path is then shorter than the input.
* A path of one cell is valid (a one-waypoint mission).
* Values must be integers: an integer dtype, or floats that are exactly
  integral (e.g. read back from JSON); NaN, fractions and booleans are rejected.

Works for any grid with ``rows``, ``cols`` and ``cell_to_latlon`` -
:class:`geo.RegionGrid` and :class:`geo.MetricRegionGrid`.
"""

from __future__ import annotations

import numpy as np

from geo.region import GeoError

__all__ = ["validate_path", "waypoint_cells", "waypoint_indices", "path_to_waypoints"]


def validate_path(grid, path) -> np.ndarray:
    """Check ``path`` against ``grid`` and return it as int64 ``(L+1, 2)`` (row, col).

    Raises :class:`geo.GeoError` naming the first problem: wrong shape, empty,
    non-integer values, a cell outside the ``rows x cols`` grid, or a step that is
    not to an 8-neighbour. Consecutive duplicate cells are dropped (see module doc).
    """
    try:
        a = np.asarray(path)
    except (TypeError, ValueError) as exc:  # ragged nested lists
        raise GeoError(f"grid path is not a rectangular (L+1, 2) array: {exc}") from None
    if a.ndim != 2 or a.shape[1] != 2:
        raise GeoError(f"grid path must have shape (L+1, 2) of (row, col), got shape {a.shape}")
    if a.shape[0] == 0:
        raise GeoError("grid path is empty (needs at least one cell)")
    if a.dtype == bool or not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise GeoError(f"grid path must hold integer (row, col) cells, got dtype {a.dtype}")
    if np.issubdtype(a.dtype, np.floating):
        bad = ~np.isfinite(a) | (a != np.round(a))
        if bad.any():
            i = int(np.argwhere(bad)[0, 0])
            raise GeoError(f"grid path cell {i} is not an integer (row, col): {a[i].tolist()}")
    p = a.astype(np.int64)
    out = (p[:, 0] < 0) | (p[:, 0] >= grid.rows) | (p[:, 1] < 0) | (p[:, 1] >= grid.cols)
    if out.any():
        i = int(np.argmax(out))
        raise GeoError(f"grid path cell {i} {tuple(p[i].tolist())} lies outside the {grid.rows}x{grid.cols} grid")
    if len(p) > 1:
        step = np.diff(p, axis=0)
        keep = np.concatenate([[True], np.any(step != 0, axis=1)])
        p = p[keep]
        step = np.diff(p, axis=0)
        jump = np.abs(step).max(axis=1) > 1 if len(step) else np.zeros(0, bool)
        if jump.any():
            i = int(np.argmax(jump))
            raise GeoError(
                f"grid path step {i} goes from {tuple(p[i].tolist())} to {tuple(p[i + 1].tolist())}, "
                "which is not an 8-neighbour"
            )
    return p


def waypoint_indices(grid, path) -> tuple[np.ndarray, np.ndarray]:
    """``(p, idx)``: the validated path ``p`` (:func:`validate_path`, ``(L+1, 2)`` int64) and the indices into it
    of the cells kept as waypoints (first, each turn point, last; ``(n,)`` int64). ``p[: idx[k] + 1]`` is the
    path whose waypoints are the first ``k + 1``.

    A cell is a turn point when the step into it differs from the step out of it.
    """
    p = validate_path(grid, path)
    if len(p) <= 2:
        return p, np.arange(len(p), dtype=np.int64)
    step = np.diff(p, axis=0)
    turn = np.any(step[1:] != step[:-1], axis=1)  # at interior cells 1..L-1
    return p, np.flatnonzero(np.concatenate([[True], turn, [True]])).astype(np.int64)


def waypoint_cells(grid, path) -> np.ndarray:
    """The cells of ``path`` kept as waypoints (:func:`waypoint_indices`): int64 ``(n, 2)``."""
    p, idx = waypoint_indices(grid, path)
    return p[idx]


def path_to_waypoints(grid, path) -> np.ndarray:
    """Grid path -> waypoints ``(n, 2)`` float64 ``[lat, lon]`` degrees at cell centres.

    Straight runs collapse into one leg (see :func:`waypoint_cells`); invalid paths
    raise :class:`geo.GeoError`.
    """
    cells = waypoint_cells(grid, path)
    lat, lon = grid.cell_to_latlon(cells[:, 0], cells[:, 1])
    return np.column_stack([np.asarray(lat, float).reshape(-1), np.asarray(lon, float).reshape(-1)])
