"""Flow fields: the ``FlowField`` container, NetCDF I/O, generators and importers.

Attributes are loaded lazily (PEP 562) so that importing a stdlib-only submodule
such as ``passt_mav.fields.cylinder_cli`` while the command line builds its
parsers does not pull in numpy.
"""

__all__ = ["FieldError", "FlowField", "load_field"]


def __getattr__(name: str):
    if name in __all__:
        from passt_mav.fields import field

        return getattr(field, name)
    raise AttributeError(f"module 'passt_mav.fields' has no attribute {name!r}")
