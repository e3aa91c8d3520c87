"""Regions, grids, projections, grid paths -> waypoints and geofences.

Imports numpy and (lazily) pyproj only.
"""

from geo.path import path_to_waypoints, validate_path, waypoint_cells, waypoint_indices
from geo.region import GeoError, MetricRegionGrid, RegionGrid, geodesic_distance_m, grid_from_dict

__all__ = [
    "GeoError",
    "RegionGrid",
    "MetricRegionGrid",
    "geodesic_distance_m",
    "grid_from_dict",
    "validate_path",
    "waypoint_cells",
    "waypoint_indices",
    "path_to_waypoints",
    "NORTH_ATLANTIC",
    "north_atlantic_grid",
]

#: The paper's North Atlantic region (cell-centre corners, 30 x 30, hourly data).
NORTH_ATLANTIC = dict(south=39.360065, west=-64.24, north=41.130714, east=-61.92004, rows=30, cols=30)


def north_atlantic_grid() -> RegionGrid:
    """The 30x30 North Atlantic grid of the paper (lat 39.360065..41.130714, lon -64.24..-61.92004)."""
    return RegionGrid(**NORTH_ATLANTIC)
