"""geo.track.Track: a vehicle's position between fixes (the rule every sample's position follows)."""

from __future__ import annotations

import pytest
from pyproj import Geod

from geo.track import Track

GEOD = Geod(ellps="WGS84")


def _boat(t_ms, lat0=-33.9, lon0=151.3, speed=4.0, heading=135.0):
    """A boat on a straight course at constant speed from (lat0, lon0) at t = 0 (exact, geodesic)."""
    lon, lat, _ = GEOD.fwd(lon0, lat0, heading, speed * t_ms / 1000.0)
    return lat, lon


def test_interpolated_positions_lie_on_the_exact_track_of_a_boat_at_constant_velocity():
    tr = Track(max_gap_ms=3000)
    for t in (0, 1000, 2000, 4500):  # fixes 1 s apart, then a 2.5 s gap (a lost fix or two)
        tr.add(t, *_boat(t))
    for t in (0, 1, 250, 999, 1000, 1500, 2001, 3000, 4499, 4500):
        p = tr.at(t)
        lat, lon = _boat(t)
        assert GEOD.inv(p.lon, p.lat, lon, lat)[2] < 1e-3  # metres: a rhumb of 10 m is a geodesic to 1 mm
        assert p.gap_ms == (0 if t in (0, 1000, 2000, 4500) else 1000 if t < 2000 else 2500)
    # outside the fixes, or in a gap over the bound: no position
    assert tr.at(-1) is None and tr.at(4501) is None
    assert Track(max_gap_ms=2000).at(0) is None
    short = Track(max_gap_ms=2000)
    for t in (0, 1000, 2000, 4500):
        short.add(t, *_boat(t))
    assert short.at(1500) is not None and short.at(3000) is None and short.at(4500).gap_ms == 0


def test_out_of_order_fixes_replacement_and_the_antimeridian():
    tr = Track(1000)
    tr.add(1000, 10.0, 179.9998)
    tr.add(0, 10.0, 179.9990)
    tr.add(500, 99.0, 99.0)
    tr.add(500, 10.0, 179.9994)  # the same time again: replaces
    assert len(tr) == 3 and tr.at(250) == pytest.approx((10.0, 179.9992, 500))
    tr.add(1500, 10.0, -179.9998)  # across the antimeridian: 0.0004 deg east, not 359.9996 west
    p = tr.at(1250)
    assert p.lon == pytest.approx(-180.0, abs=1e-9) or p.lon == pytest.approx(180.0, abs=1e-9)
    assert tr.at(1375).lon == pytest.approx(-179.9999, abs=1e-9)


def test_may_bracket_says_whether_a_later_fix_could_still_place_a_reading():
    tr = Track(2000)
    assert tr.may_bracket(100, now_ms=100) and not tr.may_bracket(100, now_ms=101)  # no fix before: only an exact one
    tr.add(1000, 1.0, 2.0)
    assert tr.may_bracket(1500, now_ms=3000) and not tr.may_bracket(1500, now_ms=3001)
    tr.add(2000, 1.0, 2.0)
    assert not tr.may_bracket(1500, now_ms=2000)  # the fix after it is here: at() decides
    tr.forget_before(1900)
    assert len(tr) == 2 and tr.at(1500) is not None  # the newest fix before the cut is kept
    tr.forget_before(2500)
    assert len(tr) == 1
    with pytest.raises(ValueError):
        Track(0)
