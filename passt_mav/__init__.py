"""passt_mav: PASST adaptive sampling on ArduPilot boats over MAVLink.

Light at import time: subpackages (fields, models, planning, reconstruction,
mavlink, mission, runs) are imported explicitly by the caller.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]
