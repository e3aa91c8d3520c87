"""Flow fields: the ``FlowField`` container, NetCDF I/O, generators and importers."""

from passt_mav.fields.field import FieldError, FlowField, load_field

__all__ = ["FieldError", "FlowField", "load_field"]
