"""The PASST loop and its offline engines: the math layer's top, no MAVLink, no run storage.

* :mod:`~passt_mav.loop.passt`: the PASST loop itself (``PasstLoop``: plan a leg, update the
  estimate with its samples; ``LoopOptions``, ``FieldSampler``, ``Samples``).
* :mod:`~passt_mav.loop.legstep`: the between-leg step on a vehicle (``LegStep``, ``FleetStep``),
  shared by the controller (:mod:`passt_mav.vehicle`) and the replay (:mod:`passt_mav.analysis`).
* :mod:`~passt_mav.loop.engine`: the offline engine (``run_trials``, ``run_offline``, the fleet's
  keep-out rule).
* :mod:`~passt_mav.loop.campaign`: the offline campaign (``run_campaign``) under ``passt-mav evaluate``,
  ``passt-mav paper`` and ``benchmarks/``.
* :mod:`~passt_mav.loop.measurement`: the measurement rules (pairing, reboots, truth, RMSE, columns)
  that the live collector, the log readers, the loop and the report follow.

Layers (kept by ``tests/test_layers.py``): nothing here imports the MAVLink client, the run storage
(:mod:`passt_mav.runs`), the vehicle side or anything above it. Submodules are imported explicitly:
``import passt_mav.loop`` imports none of them (no torch, no sklearn).
"""
