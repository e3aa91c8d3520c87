"""The checks every field passes on its way in, whichever door it comes through (docs/import-checks.md).

Doors: ``passt-mav data import`` (a model/radar file regridded), ``vehicle-sim --field``, a mission's
``field.source`` (``run``, ``plan``, ``replay``, ``demo``), ``evaluate --data`` and ``model train --data``.
Each raises a :class:`~passt_mav.errors.FieldError` (one line, exit code 2 on the command line) before
anything is written or connected.

* **The project's own attributes** of a field file (:func:`grid_attr`, :func:`provenance_attr`,
  :func:`time_origin_attr`): ``passt_grid`` and ``passt_provenance`` must be JSON (a grid with all its
  keys, a mapping), the time axis' ``units`` ``seconds since ISO-TIME`` or a non-dimensional ``1``. A
  damaged one is one line naming the attribute and the file.
* **Size** (:func:`check_size`): a field's ``(time, 2, rows, cols)`` float32 array must fit in
  :func:`max_field_bytes` (half this machine's memory, at most 16 GiB) and its grid in
  :data:`MAX_GRID_CELLS`; the line says the size and the limit.
* **Plausibility** (:func:`check_field`): some data (not NaN everywhere), no infinite value (a missing
  value is NaN), no speed beyond :data:`ABSURD_SPEED` (in the field's units; the hint names the units that
  would make the speeds plausible, as ``data import`` does, :func:`~passt_mav.fields.importers.speed_check`),
  and a time series (at least two snapshots) where one is needed (a simulator, a mission, an evaluation,
  training). Speeds above a surface current's (:data:`~passt_mav.fields.importers.MAX_SPEED`) but below
  :data:`ABSURD_SPEED` are refused by ``data import`` and warned about by the other doors
  (:func:`~passt_mav.fields.datasets.speed_warning`).
"""

from __future__ import annotations

import json
import math
import os
from typing import Any

import numpy as np

from passt_mav.errors import FieldError

__all__ = [
    "ABSURD_SPEED",
    "MAX_GRID_CELLS",
    "max_field_bytes",
    "check_size",
    "check_grid_cells",
    "check_field",
    "grid_attr",
    "provenance_attr",
    "time_origin_attr",
]

#: speeds (field units: m/s, or the cylinder's inflow = 1) beyond which no flow a boat samples exists: a field
#: with any finite value this fast was written wrong (a fill value taken for data, units 1000x off, garbage)
ABSURD_SPEED = 1000.0
#: cells of a region grid: 4 million (2000x2000); the loop's planners and GP work on tens of cells a side
MAX_GRID_CELLS = 4_000_000
_GIB = 1024**3


def max_field_bytes() -> int:
    """Bytes a field's float32 ``(time, 2, rows, cols)`` array may take: half this machine's physical memory,
    at most 16 GiB (8 GiB where the memory is not known)."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):
        total = 16 * _GIB
    return int(min(total // 2, 16 * _GIB))


def _size(n: float) -> str:
    for unit, k in (("TiB", 1024**4), ("GiB", _GIB), ("MiB", 1024**2), ("KiB", 1024)):
        if n >= k:
            return f"{n / k:.3g} {unit}"
    return f"{int(n)} B"


def check_grid_cells(rows: int, cols: int, where: str) -> None:
    """A grid of ``rows`` x ``cols`` cells within :data:`MAX_GRID_CELLS` (and one snapshot of it within
    :func:`max_field_bytes`), else a :class:`FieldError` naming ``where``, the size and the limit."""
    cells = int(rows) * int(cols)
    if cells > MAX_GRID_CELLS:
        raise FieldError(
            f"{where}: grid too large: {rows}x{cols} = {cells:,} cells (one snapshot {_size(8.0 * cells)}), "
            f"over the limit of {MAX_GRID_CELLS:,} cells; choose a coarser grid"
        )


def check_size(shape: tuple[int, ...], where: str) -> None:
    """A field of ``shape`` ``(time, 2, rows, cols)`` (or ``(time, rows, cols)`` per component) fits in memory:
    its grid within :data:`MAX_GRID_CELLS`, its float32 array within :func:`max_field_bytes`; else a
    :class:`FieldError` naming ``where``, the size and the limit."""
    shape = tuple(int(x) for x in shape)
    if len(shape) >= 2:
        check_grid_cells(shape[-2], shape[-1], where)
    n = 4.0 * math.prod(shape) * (2 if len(shape) == 3 else 1)
    limit = max_field_bytes()
    if n > limit:
        t = shape[0] if shape else 1
        raise FieldError(
            f"{where}: field too large for memory: {t} snapshots of {shape[-2]}x{shape[-1]} cells need {_size(n)}, "
            f"over the limit of {_size(limit)} (half this machine's memory, at most 16 GiB); "
            "take a shorter time window or a coarser grid"
        )


def _hint(units: str | None) -> str:
    return f"{units}? use --units {units} with passt-mav data import" if units else "check the file's values and units"


def check_field(field, source: str, *, series: bool = False) -> None:
    """Plausibility of ``field`` (a :class:`~passt_mav.fields.FlowField`) named ``source`` in the message:
    size, some data, no infinite value, no speed beyond :data:`ABSURD_SPEED`, and with ``series`` at least
    two snapshots. Raises :class:`FieldError` (one line) on the first problem."""
    check_size(field.shape, f"the field {source}")
    data = field.data
    if series and field.n_times < 2:
        raise FieldError(
            f"the field {source} has a single snapshot; a time series (at least 2 snapshots) is needed: "
            "import a longer window (passt-mav data import --hours)"
        )
    finite = np.isfinite(data)
    inf = np.isinf(data)
    if inf.any():
        n = int(inf.sum())
        raise FieldError(
            f"the field {source} has {n:,} infinite value(s) (a missing value is NaN); check the file's values "
            "and fill values (passt-mav data import treats magnitudes >= 1e10 as missing)"
        )
    if not finite.any():
        raise FieldError(f"the field {source} holds no data: every value is NaN (land or missing everywhere)")
    with np.errstate(over="ignore", invalid="ignore"):
        sp = np.hypot(data[:, 0].astype(np.float64), data[:, 1].astype(np.float64))
    sp = sp[np.isfinite(sp)]
    top = float(sp.max()) if sp.size else 0.0
    if top > ABSURD_SPEED:
        from passt_mav.fields.importers import speed_check

        fast = speed_check(field)  # a field in m/s: the units data import would suggest
        units = fast[1] if fast is not None else None
        raise FieldError(
            f"the field {source} has speeds no flow has: median {float(np.median(sp)):.3g}, max {top:.3g} "
            f"{field.units} over the valid cells (any above {ABSURD_SPEED:g} is refused); {_hint(units)}"
        )


# -- the project's own NetCDF attributes ---------------------------------------------------------------------------
def _json_attr(value: Any, name: str, path) -> Any:
    if not isinstance(value, (str, bytes)):
        raise FieldError(f"{path}: attribute {name} is damaged (a {type(value).__name__}, not JSON text)")
    try:
        return json.loads(value)
    except (ValueError, RecursionError) as exc:
        why = str(exc).splitlines()[0] if isinstance(exc, ValueError) else "nested too deep"
        raise FieldError(f"{path}: attribute {name} is damaged (not JSON: {why})") from None


def grid_attr(value: Any, path):
    """The grid of a field file from its ``passt_grid`` attribute ``value`` (:func:`geo.grid_from_dict`); a damaged
    one is a :class:`FieldError` naming the attribute and ``path``."""
    import geo

    d = _json_attr(value, "passt_grid", path)
    if not isinstance(d, dict):
        raise FieldError(f"{path}: attribute passt_grid is damaged (a JSON {type(d).__name__}, not an object)")
    try:
        grid = geo.grid_from_dict(d)
    except (TypeError, ValueError, KeyError, OverflowError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if isinstance(exc, TypeError):
            msg = msg.split("() ", 1)[-1]  # "RegionGrid.__init__() missing 6 ..." -> "missing 6 ..."
        raise FieldError(f"{path}: attribute passt_grid is damaged ({msg})") from None
    return grid


def provenance_attr(value: Any, path) -> dict:
    """The provenance mapping of a field file from its ``passt_provenance`` attribute (None: ``{}``)."""
    if value is None:
        return {}
    d = _json_attr(value, "passt_provenance", path)
    if not isinstance(d, dict):
        raise FieldError(f"{path}: attribute passt_provenance is damaged (a JSON {type(d).__name__}, not an object)")
    return d


def time_origin_attr(units: Any, path) -> str | None:
    """The ISO UTC origin of a field file's time axis from its ``units`` attribute (``seconds since ...``), None
    for non-dimensional time (``1``, or no units)."""
    from passt_mav.fields.field import parse_iso

    if units is None:
        return None
    if not isinstance(units, str):
        raise FieldError(f"{path}: attribute time:units is damaged (a {type(units).__name__}, not text)")
    u = units.strip()
    if not u.startswith("seconds since"):
        if u in ("1", ""):
            return None
        raise FieldError(
            f"{path}: attribute time:units is damaged ({u[:60]!r}; a field file's time is 'seconds since ISO-TIME' or '1')"
        )
    text = u[len("seconds since") :].strip()
    try:
        return parse_iso(text).strftime("%Y-%m-%dT%H:%M:%SZ")
    except (ValueError, OverflowError):
        raise FieldError(
            f"{path}: attribute time:units is damaged (time origin {text[:40]!r} is not an ISO time)"
        ) from None
