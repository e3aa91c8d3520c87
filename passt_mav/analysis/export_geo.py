"""GeoJSON, KML and CSV exports of a run directory (``passt-mav export --format geojson|kml|csv``).

What a GIS or a spreadsheet shows of a mission:

* **tracks**: one line per boat through its samples' positions, in time order;
* **planned paths**: one line per leg through the centres of the planned grid cells
  (``legs/NNN/path.json``), from the leg's start cell; the ``leg`` property counts from 1 (``legs/000`` is leg 1);
* **waypoints**: one point per uploaded waypoint (``leg.json`` ``waypoints``, MAVLink seq);
* **geofence**: the mission region grown by ``geofence_margin_m`` (:meth:`geo.RegionGrid.geofence`),
  one polygon.

GeoJSON follows RFC 7946 (WGS84 ``[lon, lat]``, exterior ring counter-clockwise and closed); each
feature's ``properties.kind`` is ``track``, ``planned_path``, ``waypoint`` or ``geofence``. KML 2.2
has one Folder per kind with one Placemark per feature (coordinates ``lon,lat,0``), and a line
style per boat. The CSV has one row per sample: ``time_utc`` (ISO-8601, ms, Z: the field's UTC of
the sample where the field has a UTC origin, else the vehicle's; the same clock as ``samples.nc``,
see :func:`passt_mav.analysis.export.sample_table`), ``lat_deg``, ``lon_deg`` (WGS84), ``u_m_s``, ``v_m_s``
(m/s east/north), ``boat`` (from 0), ``leg`` (numbered from 1 as the console and the report count them:
``legs/000`` is leg 1; ``outside`` for a reading outside any leg), ``vehicle_utc`` (the vehicle's own UTC of the reading) and
``field_time`` (field units, s since the field's time origin for a geographic field; empty where
unknown), sorted by boat then time.
"""

from __future__ import annotations

import datetime as _dt
import io
import json
from typing import Any

import numpy as np

__all__ = ["CSV_COLUMNS", "features", "geojson_text", "kml_text", "csv_text"]

#: the CSV's columns, units in their names (a spreadsheet shows no attributes)
CSV_COLUMNS = ["time_utc", "lat_deg", "lon_deg", "u_m_s", "v_m_s", "boat", "leg", "vehicle_utc", "field_time"]

_KML_NS = "http://www.opengis.net/kml/2.2"
#: KML line colours per boat (aabbggrr)
_COLOURS = ("ff1f77b4", "ff0e7fff", "ff2ca02c", "ff2827d6", "ffbd6794", "ff4b568c", "ffc277e3", "ff7f7f7f")


def _k(tag: str) -> str:
    """A KML 2.2 element name (ElementTree's ``{namespace}tag``)."""
    return f"{{{_KML_NS}}}{tag}"


def _pos(lat, lon) -> list[list[float]]:
    return [[round(float(b), 7), round(float(a), 7)] for a, b in zip(np.atleast_1d(lat), np.atleast_1d(lon))]


def features(run) -> list[dict[str, Any]]:
    """GeoJSON Feature dicts of a run (:class:`passt_mav.analysis.export.RunData`): tracks per boat,
    planned path per leg, waypoints, geofence (module docstring)."""
    from passt_mav.analysis.export import sample_table

    out: list[dict[str, Any]] = []
    if run.samples:
        c = sample_table(run)
        for b in np.unique(c["boat"]):
            k = c["boat"] == b
            pts = _pos(c["lat"][k], c["lon"][k])
            geom = (
                {"type": "LineString", "coordinates": pts}
                if len(pts) >= 2
                else {"type": "Point", "coordinates": pts[0]}
            )
            out.append(_feature(geom, kind="track", boat=int(b), n_samples=int(k.sum())))
    g = run.grid
    for rec in run.legs:
        i, boat = int(rec.get("index", -1)), int(rec.get("boat", 0) or 0)
        path = np.asarray(rec.get("path") or [], int).reshape(-1, 2)
        if len(path) >= 2:
            lat, lon = g.cell_to_latlon(path[:, 0], path[:, 1])
            out.append(
                _feature(
                    {"type": "LineString", "coordinates": _pos(lat, lon)},
                    kind="planned_path",
                    leg=i + 1,
                    boat=boat,
                    cells=path.tolist(),
                    status=str(rec.get("status", "")),
                )
            )
        seqs = rec.get("waypoint_seqs") or []
        for j, wp in enumerate(rec.get("waypoints") or []):
            out.append(
                _feature(
                    {"type": "Point", "coordinates": _pos(wp[0], wp[1])[0]},
                    kind="waypoint",
                    leg=i + 1,
                    boat=boat,
                    seq=int(seqs[j]) if j < len(seqs) else j + 1,
                )
            )
    ring = g.geofence(run.margin_m)
    coords = _pos(ring[:, 0], ring[:, 1])
    out.append(
        _feature({"type": "Polygon", "coordinates": [coords + [coords[0]]]}, kind="geofence", margin_m=run.margin_m)
    )
    return out


def _feature(geometry: dict, **props: Any) -> dict[str, Any]:
    return {"type": "Feature", "geometry": geometry, "properties": props}


def _counts(feats) -> dict[str, int]:
    kinds = [f["properties"]["kind"] for f in feats]
    return {k: kinds.count(k) for k in ("track", "planned_path", "waypoint", "geofence")}


def geojson_text(run) -> tuple[str, dict]:
    """(RFC 7946 FeatureCollection as text, feature counts per kind)."""
    feats = features(run)
    fc = {"type": "FeatureCollection", "name": f"passt_mav run {run.name}", "features": feats}
    return json.dumps(fc, separators=(",", ":")) + "\n", {"features": _counts(feats)}


def kml_text(run) -> tuple[str, dict]:
    """(KML 2.2 document as text, placemark counts per kind): one Folder per kind (module docstring)."""
    import xml.etree.ElementTree as ET

    ET.register_namespace("", _KML_NS)
    kml = ET.Element(_k("kml"))
    doc = ET.SubElement(kml, _k("Document"))
    ET.SubElement(doc, _k("name")).text = f"passt_mav run {run.name}"
    for b in range(max(run.n_boats, 1)):
        st = ET.SubElement(doc, _k("Style"), id=f"boat{b}")
        ls = ET.SubElement(st, _k("LineStyle"))
        ET.SubElement(ls, _k("color")).text = _COLOURS[b % len(_COLOURS)]
        ET.SubElement(ls, _k("width")).text = "3"
    feats = features(run)
    titles = {"track": "Tracks", "planned_path": "Planned paths", "waypoint": "Waypoints", "geofence": "Geofence"}
    for kind, title in titles.items():
        folder = ET.SubElement(doc, _k("Folder"))
        ET.SubElement(folder, _k("name")).text = title
        for f in (f for f in feats if f["properties"]["kind"] == kind):
            _placemark(ET, folder, f)
    ET.indent(kml)
    text = ET.tostring(kml, encoding="unicode", xml_declaration=False)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + text + "\n", {"placemarks": _counts(feats)}


def _placemark(ET, folder, f: dict) -> None:
    """One KML Placemark (name, description, style, geometry) for a GeoJSON feature."""
    p, g = f["properties"], f["geometry"]
    pm = ET.SubElement(folder, _k("Placemark"))
    name = {
        "track": f"boat {p.get('boat')} track",
        "planned_path": f"leg {p.get('leg')} planned path",
        "waypoint": f"leg {p.get('leg')} waypoint seq {p.get('seq')}",
        "geofence": "geofence",
    }[p["kind"]]
    ET.SubElement(pm, _k("name")).text = name
    ET.SubElement(pm, _k("description")).text = json.dumps({k: v for k, v in p.items() if k != "cells"})
    if "boat" in p and g["type"] == "LineString":
        ET.SubElement(pm, _k("styleUrl")).text = f"#boat{p['boat']}"

    def coords(parent, pts) -> None:
        ET.SubElement(parent, _k("coordinates")).text = " ".join(f"{x:.7f},{y:.7f},0" for x, y in pts)

    if g["type"] == "Point":
        coords(ET.SubElement(pm, _k("Point")), [g["coordinates"]])
    elif g["type"] == "LineString":
        ls = ET.SubElement(pm, _k("LineString"))
        ET.SubElement(ls, _k("tessellate")).text = "1"
        coords(ls, g["coordinates"])
    else:
        poly = ET.SubElement(pm, _k("Polygon"))
        ring = ET.SubElement(ET.SubElement(poly, _k("outerBoundaryIs")), _k("LinearRing"))
        coords(ring, g["coordinates"][0])


def _iso_ms(epoch_s: float) -> str:
    """UNIX seconds -> ISO-8601 UTC with milliseconds and a ``Z``."""
    return _dt.datetime.fromtimestamp(float(epoch_s), _dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def csv_text(run) -> tuple[str, dict]:
    """(CSV of samples as text, row count): time_utc, lat_deg, lon_deg, u_m_s, v_m_s, boat, leg, vehicle_utc, field_time
    (module docstring)."""
    import csv

    from passt_mav.analysis.export import sample_table
    from passt_mav.loop.measurement import leg_number

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    n = 0
    if run.samples:
        c = sample_table(run)
        rows = zip(c["utc"], c["lat"], c["lon"], c["u"], c["v"], c["boat"], c["leg"], c["vehicle_utc"], c["field_time"])
        for t, la, lo, u, v, b, leg, tv, tf in rows:
            ft = f"{tf:.3f}" if np.isfinite(tf) else ""
            w.writerow(
                [
                    _iso_ms(t),
                    f"{la:.7f}",
                    f"{lo:.7f}",
                    f"{u:.6f}",
                    f"{v:.6f}",
                    int(b),
                    leg_number(int(leg)),
                    _iso_ms(tv),
                    ft,
                ]
            )
            n += 1
    return buf.getvalue(), {"rows": n}
