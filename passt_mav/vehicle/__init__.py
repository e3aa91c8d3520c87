"""The vehicle side of a leg: the mission controller, above the MAVLink client and the run storage.

* :mod:`~passt_mav.vehicle.controller`: one boat's PASST loop flown over MAVLink (``MissionController``)
  and its records.
* :mod:`~passt_mav.vehicle.fleet_controller`: a fleet's boats composed on one shared state
  (``FleetController``).
* :mod:`~passt_mav.vehicle.session`: what the controller does to the vehicle (``VehicleSession``: swap,
  fly, reconnects, reboots, a pilot, another ground station) and its journal.
* :mod:`~passt_mav.vehicle.clock`: one boat's clock, vehicle time -> field time (``RunClock``).
* :mod:`~passt_mav.vehicle.live_record`: what the controller tells the live view.

Layers (kept by ``tests/test_layers.py``): this package may import what lies below it (the math, the
loop :mod:`passt_mav.loop`, the MAVLink client :mod:`passt_mav.mavlink`, the run storage
:mod:`passt_mav.runs`), never what is built on top (analysis, view, commands, CLI). Submodules are imported explicitly: ``import
passt_mav.vehicle`` imports none of them (no pymavlink, no torch).
"""
