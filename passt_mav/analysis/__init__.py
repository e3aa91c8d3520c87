"""Analysis: what is built on top of a finished (or running) mission, above the controller.

* :func:`replay` (``replay``): rebuild a run from its telemetry or DataFlash log and re-run
  every between-leg decision offline through :class:`passt_mav.loop.legstep.LegStep`.
* :func:`write_report`, :func:`load_run` (``report``): the self-contained HTML report.
* :func:`lawnmower_counterfactual` (``counterfactual``): what a lawnmower survey would have done.

Layers (kept by ``tests/test_layers.py``): this package may import the controller and
the storage layer (:mod:`passt_mav.runs`); nothing below it imports it.
Submodules are imported on demand: ``import passt_mav.analysis`` stays light.
"""

from __future__ import annotations

__all__ = ["replay", "write_report", "load_run", "lawnmower_counterfactual"]

_WHERE = {
    "replay": "replay",
    "write_report": "report",
    "load_run": "report",
    "lawnmower_counterfactual": "counterfactual",
}


def __getattr__(name: str):
    if name in _WHERE:
        import importlib

        return getattr(importlib.import_module(f"passt_mav.analysis.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'passt_mav.analysis' has no attribute {name!r}")
