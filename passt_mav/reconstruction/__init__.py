"""GP reconstruction of a grid snapshot from scattered current samples."""

from passt_mav.reconstruction.gp import GPReconstructor

__all__ = ["GPReconstructor"]
