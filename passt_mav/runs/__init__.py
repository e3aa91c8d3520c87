"""Runs, the storage layer: the run directory, the crash-safe sample store and the log readers.

* :class:`RunDir` (``rundir``): the layout of a run directory on disk.
* :class:`RunRecords` (``records``): its records (``summary.json``, ``leg.json``, ``events.jsonl``) read
  through their schema, the one reader that the report, exports, live view and replay share.
* :class:`SampleStore` (``store``): SQLite (WAL) store of current samples.
* :func:`read_tlog`, :func:`read_dataflash` (``tlog``): rebuild samples, track,
  uploads and legs from MAVLink ``.tlog`` / ArduPilot ``.bin`` logs.

The controller (:mod:`passt_mav.vehicle`) writes into these modules; nothing here imports the
controller or the analysis built on top (:mod:`passt_mav.analysis`: replay, report, counterfactual).
Of the MAVLink client it imports only the live sample collector
(:class:`passt_mav.mavlink.samples.SampleCollector`, in ``legs``: a log's messages go through the
collector's rules, so a rebuilt leg has the samples the controller had; importing it loads the
:mod:`passt_mav.mavlink` package, pymavlink included), and pymavlink itself to decode logs; below that,
the track (:mod:`geo.track`), the measurement rules (:mod:`passt_mav.loop.measurement`) and the errors.
``tests/test_layers.py`` keeps it so.

Submodules are imported on demand: ``import passt_mav.runs`` stays light.
"""

from __future__ import annotations

__all__ = ["RunDir", "RunRecords", "SampleStore", "Sample", "read_tlog", "read_dataflash"]

_WHERE = {
    "RunDir": "rundir",
    "RunRecords": "records",
    "SampleStore": "store",
    "Sample": "store",
    "read_tlog": "tlog",
    "read_dataflash": "tlog",
}


def __getattr__(name: str):
    if name in _WHERE:
        import importlib

        return getattr(importlib.import_module(f"passt_mav.runs.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'passt_mav.runs' has no attribute {name!r}")
