"""Runs: the run directory, the crash-safe sample store, log readers and the report.

* :class:`RunDir` (``rundir``): the layout of a run directory on disk.
* :class:`SampleStore` (``store``): SQLite (WAL) store of current samples.
* :func:`read_tlog`, :func:`read_dataflash` (``tlog``): rebuild samples, track,
  uploads and legs from MAVLink ``.tlog`` / ArduPilot ``.bin`` logs.
* :func:`write_report`, :func:`load_run` (``report``): the self-contained HTML report.

Submodules are imported on demand: ``import passt_mav.runs`` stays light.
"""

from __future__ import annotations

__all__ = ["RunDir", "SampleStore", "Sample", "read_tlog", "read_dataflash", "load_run", "write_report"]

_WHERE = {
    "RunDir": "rundir", "SampleStore": "store", "Sample": "store", "read_tlog": "tlog",
    "read_dataflash": "tlog", "load_run": "report", "write_report": "report",
}


def __getattr__(name: str):
    if name in _WHERE:
        import importlib

        return getattr(importlib.import_module(f"passt_mav.runs.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'passt_mav.runs' has no attribute {name!r}")
