"""passt_mav: PASST adaptive sampling on ArduPilot boats over MAVLink.

Light at import time: subpackages (fields, models, planning, reconstruction,
loop, mission, mavlink, runs, vehicle, analysis, view, commands) are imported
explicitly by the caller.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]
