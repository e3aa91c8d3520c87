"""GP reconstruction of a grid snapshot from scattered current samples."""

from passt_mav.reconstruction.background import model_background
from passt_mav.reconstruction.gp import GPReconstructor

__all__ = ["GPReconstructor", "model_background"]
