"""The autopilot's geofence, as ArduPilot Rover's (AC_Fence, Rover's ``fence_check``, GCS_MAVLink's
``send_fence_status``).

Parameters (Rover's names and defaults): ``FENCE_ENABLE`` (0: off), ``FENCE_TYPE`` (bitmask: 2 circle about home,
4 inclusion polygons; default 6), ``FENCE_RADIUS`` (m, the circle; default 300), ``FENCE_ACTION`` (what a new breach
does while armed: 0 report only, 1 RTL (HOLD if refused), 2 HOLD; default 1). The polygons are the stored fence
list (mission type 1): runs of ``MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION`` items, ``param1`` vertices each.

:meth:`Fence.check` runs every step while enabled: a fence type the boat is outside of is a breach (the first
breach sets ``breach_time``, ms since boot; every new breach of a type counts one in ``breach_count``); a type the
boat is back inside of clears. FENCE_STATUS (:meth:`Fence.status`) is in the extended status stream while the fence
is enabled, and sent at once on a new breach. The count and time start again at each boot.
"""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as M

__all__ = ["Fence", "TYPE_CIRCLE", "TYPE_POLYGON", "PARAMS"]

TYPE_CIRCLE, TYPE_POLYGON = 2, 4
#: name -> (default, MAV_PARAM_TYPE), Rover's
PARAMS = {
    "FENCE_ENABLE": (0, M.MAV_PARAM_TYPE_INT8),
    "FENCE_TYPE": (6, M.MAV_PARAM_TYPE_INT8),
    "FENCE_RADIUS": (300.0, M.MAV_PARAM_TYPE_REAL32),
    "FENCE_ACTION": (1, M.MAV_PARAM_TYPE_INT8),
}


def _inside(x: float, y: float, poly: list[tuple[float, float]]) -> bool:
    """Whether (x, y) lies inside polygon ``poly`` (vertices (x, y), m, local frame): even-odd ray casting (written
    out: a few lines where a geometry library would be a new dependency of the simulator)."""
    inside = False
    for (x1, y1), (x2, y2) in zip(poly, poly[1:] + poly[:1]):
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside


class Fence:
    """One autopilot's fence state (module docstring): ``breaches`` (bitmask of the types breached now),
    ``breach_count`` and ``breach_time_ms`` (since boot)."""

    def __init__(self):
        #: (fence list version, its polygons in the autopilot's local frame, which is fixed at its construction):
        #: :meth:`check` runs every step, and the vertices' projection (pyproj) need only be redone when the
        #: stored list changes
        self._polys: tuple[int, list[list[tuple[float, float]]]] | None = None
        self.reset()

    def reset(self) -> None:
        """A boot: nothing breached, nothing counted."""
        self.breaches = 0
        self.breach_count = 0
        self.breach_time_ms = 0

    @staticmethod
    def enabled(ap) -> bool:
        return int(ap.p("FENCE_ENABLE")) != 0

    def polygons(self, ap) -> list[list[tuple[float, float]]]:
        """The stored inclusion polygons, vertices in the autopilot's local frame (x east, y north, m); computed
        again only when the fence list changed (``MissionStore.version``)."""
        key = ap.store.version[1]
        if self._polys is not None and self._polys[0] == key:
            return self._polys[1]
        out, items, k = [], ap.store.items[1], 0
        while k < len(items):
            it = items[k]
            n = int(it.param1)
            if it.command != M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION or n < 3 or k + n > len(items):
                k += 1
                continue
            out.append([ap.frame.to_xy(v.x / 1e7, v.y / 1e7) for v in items[k : k + n]])
            k += n
        self._polys = (key, out)
        return out

    def outside(self, ap) -> int:
        """The fence types (bitmask) the boat is outside of now."""
        kinds = int(ap.p("FENCE_TYPE"))
        x, y = ap.boat.x, ap.boat.y
        out = 0
        if kinds & TYPE_CIRCLE and ap.home_set:
            hx, hy = ap.frame.to_xy(*ap.home_latlon)
            if ((x - hx) ** 2 + (y - hy) ** 2) ** 0.5 > float(ap.p("FENCE_RADIUS")):
                out |= TYPE_CIRCLE
        if kinds & TYPE_POLYGON:
            polys = self.polygons(ap)
            if polys and not any(_inside(x, y, p) for p in polys):
                out |= TYPE_POLYGON
        return out

    def check(self, ap) -> int:
        """One check (enabled or not): the breaches new since the last one (bitmask); cleared types forgotten."""
        now = self.outside(ap) if self.enabled(ap) else 0
        new = now & ~self.breaches
        if new:
            if not self.breaches:
                self.breach_time_ms = ap.time_boot_ms
            self.breach_count = min(self.breach_count + new.bit_count(), 65500)
        self.breaches = now
        return new

    def status(self, ap):
        """FENCE_STATUS now, None while the fence is disabled (ArduPilot sends none then)."""
        if not self.enabled(ap):
            return None
        kind = M.FENCE_BREACH_BOUNDARY if self.breaches & (TYPE_CIRCLE | TYPE_POLYGON) else M.FENCE_BREACH_NONE
        return M.MAVLink_fence_status_message(
            int(self.breaches != 0), self.breach_count, kind, self.breach_time_ms, M.FENCE_MITIGATE_NONE
        )
