"""WaypointMission: ArduPilot items (seq-0 home), QGC WPL 110 and QGroundControl .plan files.

Independent checks: pymavlink's own WPL reader/writer (``mavwp.MAVWPLoader``), a
.plan written by hand with the fields QGroundControl writes (dev guide "Plan File
Format"), and matplotlib's point-in-polygon for the geofence property.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import geo
from passt_mav.errors import MissionFileError
from passt_mav.mission import MissionItem, WaypointMission

HOME = (40.1, -63.2, 1.5)


@pytest.fixture
def mission(na_grid):
    path = [(3, 3), (4, 4), (5, 5), (5, 6), (5, 7), (6, 7), (7, 7), (7, 6)]
    return WaypointMission.from_path(na_grid, path, home=HOME, speed=2.5, wp_radius_m=4.0, fence_margin_m=250.0)


# -- items ----------------------------------------------------------------------------


def test_items_follow_the_seq0_home_rule(mission, na_grid):
    items = mission.items()
    h = items[0]
    assert (h.seq, h.frame, h.command) == (0, 0, 16)
    assert (h.lat, h.lon, h.alt) == HOME
    sp = items[1]
    assert (sp.seq, sp.command, sp.frame, sp.param2) == (1, 178, 2, 2.5)
    wps = items[2:]
    assert [it.seq for it in wps] == list(range(2, 2 + len(wps))) == mission.waypoint_seqs()
    assert all(it.command == 16 and it.frame == 3 and it.param2 == 4.0 and it.mission_type == 0 for it in wps)
    cells = np.array([(3, 3), (5, 5), (5, 7), (7, 7), (7, 6)])
    np.testing.assert_allclose(
        [(it.lat, it.lon) for it in wps],
        np.column_stack([na_grid.lats[cells[:, 0]], na_grid.lons[cells[:, 1]]]),
        atol=1e-12,
    )


def test_without_speed_waypoints_start_at_seq_1_and_home_placeholder_is_first_waypoint(na_grid):
    m = WaypointMission.from_path(na_grid, [(0, 0), (0, 1), (1, 2)], fence_margin_m=None)
    items = m.items()
    assert [(it.seq, it.command, it.frame) for it in items] == [(0, 16, 0), (1, 16, 3), (2, 16, 3), (3, 16, 3)]
    assert (items[0].lat, items[0].lon) == (items[1].lat, items[1].lon)
    assert m.fence_items() == []


def test_fence_items_and_from_items_round_trip(mission):
    fence = mission.fence_items()
    k = len(mission.fence)
    assert k >= 3 and len(fence) == k
    assert all(it.command == 5001 and it.mission_type == 1 and it.param1 == k for it in fence)
    assert [it.seq for it in fence] == list(range(k))
    back = WaypointMission.from_items(mission.items() + fence)
    assert back.same_as(mission)
    # through the wire's int32 degE7 quantisation, still the same mission
    q = [MissionItem(**{**it.__dict__, "lat": it.x_int / 1e7, "lon": it.y_int / 1e7}) for it in mission.items() + fence]
    assert WaypointMission.from_items(q).same_as(mission)


# -- QGC WPL 110 ------------------------------------------------------------------------


def test_wpl_round_trip_and_layout(mission, tmp_path):
    p = mission.to_wpl(tmp_path / "leg.waypoints")
    lines = p.read_text().splitlines()
    assert lines[0] == "QGC WPL 110"
    rows = [ln.split("\t") for ln in lines[1:]]
    assert all(len(r) == 12 for r in rows)
    assert rows[0][:4] == ["0", "1", "0", "16"] and float(rows[0][8]) == HOME[0] and float(rows[0][9]) == HOME[1]
    assert [int(r[0]) for r in rows] == list(range(len(rows)))
    assert all(r[2:4] == ["3", "16"] for r in rows[2:])
    back = WaypointMission.from_wpl(p)
    mission.fence = None  # WPL carries no fence
    assert back.same_as(mission)


def test_wpl_agrees_with_pymavlink_mavwp(mission, tmp_path):
    from pymavlink import mavwp

    p = mission.to_wpl(tmp_path / "ours.waypoints")
    loader = mavwp.MAVWPLoader()
    assert loader.load(str(p)) == len(mission.items())
    for it in mission.items():
        w = loader.wp(it.seq)
        assert (w.seq, w.frame, w.command) == (it.seq, it.frame, it.command)
        assert w.x == pytest.approx(it.lat, abs=1e-12) and w.y == pytest.approx(it.lon, abs=1e-12)
    # and a file pymavlink wrote (6 decimals) reads back as the same mission to 1e-6 deg
    loader.save(str(tmp_path / "theirs.waypoints"))
    back = WaypointMission.from_wpl(tmp_path / "theirs.waypoints")
    mission.fence = None
    assert back.same_as(mission, deg_tol=1e-6)


# -- QGroundControl .plan ---------------------------------------------------------------


def test_plan_round_trip_and_schema(mission, tmp_path):
    p = mission.to_plan(tmp_path / "leg.plan")
    d = json.loads(p.read_text())
    assert d["fileType"] == "Plan" and d["version"] == 1 and d["groundStation"] == "QGroundControl"
    m = d["mission"]
    assert (m["version"], m["firmwareType"], m["vehicleType"]) == (2, 3, 11)
    assert m["plannedHomePosition"] == list(HOME)
    assert len(m["items"]) == len(mission.items()) - 1  # home is not an item
    for i, it in enumerate(m["items"], start=1):
        assert it["type"] == "SimpleItem" and it["doJumpId"] == i and len(it["params"]) == 7
    wp = m["items"][1]
    assert (wp["command"], wp["frame"]) == (16, 3) and wp["params"][4:6] == mission.waypoints[0].tolist()
    assert d["geoFence"]["version"] == 2 and d["geoFence"]["circles"] == []
    (poly,) = d["geoFence"]["polygons"]
    assert poly["inclusion"] is True and poly["version"] == 1 and poly["polygon"] == mission.fence.tolist()
    assert d["rallyPoints"] == {"version": 2, "points": []}
    assert WaypointMission.from_plan(p).same_as(mission)


def test_plan_as_written_by_qgroundcontrol_imports(tmp_path):
    # Field for field what QGC 4.x saves for a rover mission: takeoff-less, two waypoints,
    # a speed change, an inclusion polygon; yaw (param4) NaN is written as null.
    qgc = {
        "fileType": "Plan",
        "geoFence": {
            "circles": [],
            "polygons": [
                {
                    "inclusion": True,
                    "polygon": [[40.10, -63.30], [40.10, -63.00], [40.30, -63.00], [40.30, -63.30]],
                    "version": 1,
                }
            ],
            "version": 2,
        },
        "groundStation": "QGroundControl",
        "mission": {
            "cruiseSpeed": 3,
            "firmwareType": 3,
            "globalPlanAltitudeMode": 1,
            "hoverSpeed": 5,
            "items": [
                {
                    "autoContinue": True,
                    "command": 178,
                    "doJumpId": 1,
                    "frame": 2,
                    "params": [1, 3, -1, 0, 0, 0, 0],
                    "type": "SimpleItem",
                },
                {
                    "AMSLAltAboveTerrain": None,
                    "Altitude": 0,
                    "AltitudeMode": 1,
                    "autoContinue": True,
                    "command": 16,
                    "doJumpId": 2,
                    "frame": 3,
                    "params": [0, 0, 0, None, 40.2012345, -63.1054321, 0],
                    "type": "SimpleItem",
                },
                {
                    "AMSLAltAboveTerrain": None,
                    "Altitude": 0,
                    "AltitudeMode": 1,
                    "autoContinue": True,
                    "command": 16,
                    "doJumpId": 3,
                    "frame": 3,
                    "params": [0, 0, 0, None, 40.2254321, -63.0812345, 0],
                    "type": "SimpleItem",
                },
            ],
            "plannedHomePosition": [40.2, -63.1, 12.3],
            "vehicleType": 11,
            "version": 2,
        },
        "rallyPoints": {"points": [], "version": 2},
        "version": 1,
    }
    p = tmp_path / "qgc.plan"
    p.write_text(json.dumps(qgc, indent=4))
    m = WaypointMission.from_plan(p)
    np.testing.assert_array_equal(m.waypoints, [[40.2012345, -63.1054321], [40.2254321, -63.0812345]])
    assert m.home == (40.2, -63.1, 12.3) and m.speed == 3 and m.alt == 0
    np.testing.assert_array_equal(m.fence, qgc["geoFence"]["polygons"][0]["polygon"])
    # what we would upload: home placeholder, the speed change, the two waypoints
    assert [(it.seq, it.command) for it in m.items()] == [(0, 16), (1, 178), (2, 16), (3, 16)]


def _qgc_min(items, **extra):
    return {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "QGroundControl",
        "mission": {
            "version": 2,
            "firmwareType": 3,
            "vehicleType": 11,
            "plannedHomePosition": [40, -63, 0],
            "items": items,
        },
        **extra,
    }


_WP = {
    "autoContinue": True,
    "command": 16,
    "doJumpId": 1,
    "frame": 3,
    "params": [0, 0, 0, None, 40.1, -63.1, 0],
    "type": "SimpleItem",
}


@pytest.mark.parametrize(
    "name, text, match",
    [
        ("a.waypoints", "QGC WPL 100\n0\t1\t0\t16\t0\t0\t0\t0\t40\t-63\t0\t1\n", "unsupported WPL version"),
        ("b.waypoints", "hello\n", "not a QGC WPL file"),
        ("c.waypoints", "QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t40\t-63\t0\n", "line 2: expected 12 fields"),
        ("d.waypoints", "QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t40\tx\t0\t1\n", "line 2"),
        ("e.waypoints", "QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t40\t-63\t0\t1\n", "no waypoints"),
        (
            "f.waypoints",
            "QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t40\t-63\t0\t1\n1\t0\t3\t22\t0\t0\t0\t0\t40\t-63\t5\t1\n",
            "command 22",
        ),
        (
            "g.waypoints",
            "QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t40\t-63\t0\t1\n2\t0\t3\t16\t0\t0\t0\t0\t40\t-63\t0\t1\n",
            "seqs must run",
        ),
        (
            "h.waypoints",
            "QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t40\t-63\t0\t1\n1\t0\t3\t16\t0\t0\t0\t0\t95\t-63\t0\t1\n",
            "out of range",
        ),
        ("a.plan", "{not json", "not valid JSON"),
        ("b.plan", json.dumps({"fileType": "Mission"}), "not a QGroundControl plan"),
        ("c.plan", json.dumps(_qgc_min([{"type": "ComplexItem", "complexItemType": "survey"}])), "ComplexItem"),
        ("d.plan", json.dumps(_qgc_min([{**_WP, "params": [0, 0, 0]}])), "params needs 7"),
        ("e.plan", json.dumps(_qgc_min([{k: v for k, v in _WP.items() if k != "command"}])), "missing key 'command'"),
        (
            "f.plan",
            json.dumps(_qgc_min([_WP], geoFence={"version": 2, "circles": [{"radius": 5}], "polygons": []})),
            "circles",
        ),
    ],
)
def test_bad_files_raise_one_line_mission_file_error(tmp_path, name, text, match):
    p = tmp_path / name
    p.write_text(text)
    reader = WaypointMission.from_wpl if name.endswith(".waypoints") else WaypointMission.from_plan
    with pytest.raises(MissionFileError, match=match) as exc:
        reader(p)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(str(p))


def test_missing_file_raises(tmp_path):
    with pytest.raises(MissionFileError, match="no such file"):
        WaypointMission.from_wpl(tmp_path / "nope.waypoints")


# -- every waypoint lies inside the geofence (property) -----------------------------------


@st.composite
def grid_and_path(draw):
    rows, cols = draw(st.integers(2, 40)), draw(st.integers(2, 40))
    if draw(st.booleans()):
        south = draw(st.floats(-70, 69))
        west = draw(st.floats(-179, 170))
        g = geo.RegionGrid(
            south, west, south + draw(st.floats(0.01, 1.0)), west + draw(st.floats(0.01, 1.0)), rows, cols
        )
    else:
        g = geo.MetricRegionGrid(
            0.0,
            draw(st.floats(1.0, 50.0)),
            0.0,
            draw(st.floats(1.0, 50.0)),
            rows,
            cols,
            anchor_lat=draw(st.floats(-70, 70)),
            anchor_lon=draw(st.floats(-179, 179)),
            rotation_deg=draw(st.floats(-180, 180)),
            scale=draw(st.floats(0.5, 500.0)),
        )
    r, c = draw(st.integers(0, rows - 1)), draw(st.integers(0, cols - 1))
    path = [(r, c)]
    moves = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]
    for m in draw(st.lists(st.sampled_from(moves), min_size=0, max_size=80)):
        nr, nc = path[-1][0] + m[0], path[-1][1] + m[1]
        if 0 <= nr < rows and 0 <= nc < cols:
            path.append((nr, nc))
    return g, np.array(path)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(gp=grid_and_path(), margin=st.floats(0.0, 1000.0))
def test_every_waypoint_lies_inside_the_geofence(gp, margin):
    from matplotlib.path import Path as MplPath

    g, path = gp
    m = WaypointMission.from_path(g, path, fence_margin_m=margin)
    poly = MplPath(m.fence[:, ::-1])  # (lon, lat): x, y
    inside = poly.contains_points(m.waypoints[:, ::-1])
    assert inside.all(), f"{(~inside).sum()} waypoint(s) outside the fence"
    assert np.all(g.contains(m.waypoints[:, 0], m.waypoints[:, 1]))
    # the waypoints are exactly the path's turn points
    cells = np.asarray(m.meta["cells"])
    assert tuple(cells[0]) == tuple(path[0]) and tuple(cells[-1]) == tuple(path[-1])
    # and survive the fence/mission item round trip
    back = WaypointMission.from_items(m.items() + m.fence_items())
    np.testing.assert_allclose(back.waypoints, m.waypoints, atol=1e-12)
    np.testing.assert_allclose(back.fence, m.fence, atol=1e-12)
