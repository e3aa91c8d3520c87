"""One unit rule for the speeds and RMSEs people read.

The loop works in the field's own velocity units (the cylinder wake is non-dimensional, inflow = 1;
geographic fields are in m/s). Everything a person reads -- the console's leg lines and final line,
the report, the live view, the exports -- is in m/s wherever the field has a velocity scale: a
mission always has one (``field.velocity_scale``, m/s per field velocity unit, 1 for geographic
fields), so a run's figures are in m/s, labelled ``m/s``. A field read without a mission (``evaluate``,
``paper``, ``model evaluate``) has a scale only when its units are m/s; otherwise its figures stay in
field units and say so (``field units``).

Samples a vehicle reports are in m/s already: they are never scaled.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["FIELD_UNITS", "MPS", "SpeedUnit", "run_speed_unit", "speed_unit"]

#: the label of a speed in m/s
MPS = "m/s"
#: the label of a speed in a field's own units when the field has no velocity scale
FIELD_UNITS = "field units"


@dataclass(frozen=True)
class SpeedUnit:
    """How a speed or RMSE in field velocity units is shown: times ``per_field_unit``, labelled ``label``.

    ``per_field_unit``: m/s per field velocity unit when ``label`` is ``"m/s"``; 1 when the figures
    stay in field units (``label`` ``"field units"``)."""

    per_field_unit: float = 1.0
    label: str = MPS

    def __call__(self, x: float | None) -> float | None:
        """``x`` (field units) in this unit; None stays None."""
        return None if x is None else float(x) * self.per_field_unit

    def text(self, x: float | None, spec: str = ".4f") -> str:
        """``x`` (field units) as ``"0.0422 m/s"``; ``"n/a"`` for None."""
        y = self(x)
        return "n/a" if y is None else f"{y:{spec}} {self.label}"

    def as_dict(self) -> dict[str, Any]:
        """JSON-able: ``label`` and ``per_field_unit`` (what the live view serves)."""
        return {"label": self.label, "per_field_unit": self.per_field_unit}


def speed_unit(velocity_scale: float | None = None, field_units: str | None = None) -> SpeedUnit:
    """The unit for a field: m/s times ``velocity_scale`` when a mission gives one; m/s for a field in
    m/s (``"m s-1"``); otherwise field units, unscaled."""
    if velocity_scale is not None:
        return SpeedUnit(float(velocity_scale), MPS)
    if field_units in ("m s-1", "m/s", "m.s-1"):
        return SpeedUnit(1.0, MPS)
    return SpeedUnit(1.0, FIELD_UNITS)


def run_speed_unit(summary: dict | None = None, meta: dict | None = None, field_units: str | None = None) -> SpeedUnit:
    """The unit of a run directory's figures: its mission's ``field.velocity_scale`` (from ``summary.json``'s
    ``config``, else ``meta``'s ``velocity_scale``: ``live/meta.json``, or a mission file's ``field`` section);
    a run that records neither falls back to ``field_units`` (:func:`speed_unit`)."""
    vs = None
    cfg = (summary or {}).get("config")
    if isinstance(cfg, dict) and isinstance(cfg.get("field"), dict):
        vs = cfg["field"].get("velocity_scale")
    if vs is None and meta:
        vs = meta.get("velocity_scale")
    return speed_unit(None if vs is None else float(vs), field_units)
