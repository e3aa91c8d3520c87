"""A pymavlink ``mavutil`` connection over an in-process simulator link.

``mavutil.mavfile`` is pymavlink's base class for every transport (``mavtcp``,
``mavudp``, ``mavserial``, ...): a subclass supplies ``recv(n)``, ``write(buf)``,
``close()`` and optionally ``select(timeout)``; everything else
(``recv_match``, ``wait_heartbeat``, ``mav.*_send``, ``setup_signing``, message
bookkeeping) comes from the base. :class:`InProcessMavfile` is such a subclass
on an :class:`vehicle_sim.sim.InProcessEndpoint`, so code written against
``mavutil.mavlink_connection("tcp:...")`` runs unchanged against the simulator
without sockets::

    sim = Simulator(field, home=(lat, lon), config=SimConfig.fast())
    sim.serve([], lockstep=True)   # or speedup=...: the serving thread runs the clock
    conn = sim.connect_inprocess().mavlink_connection()
    conn.mav.command_long_send(1, 1, STEP_COMMAND, 0, 2.0, 0, 0, 0, 0, 0, 0)  # run 2 s
    conn.wait_heartbeat()

Time: the connection never advances the simulator itself. Served in lockstep
(:meth:`Simulator.serve` with ``lockstep=True``), the serving thread runs the clock
only for the steps a GCS asks for (COMMAND_LONG :data:`vehicle_sim.sim.STEP_COMMAND`,
acknowledged once they have run, after everything the vehicle sent meanwhile): time
follows the GCS, whatever the machine's load. Served at a ``speedup``, it follows the
wall clock; unserved, whoever holds the simulator calls ``sim.step``. ``select`` waits
until the simulator has delivered bytes (or the timeout), so a reader wakes as soon as
a step's answer is there.
"""

from __future__ import annotations

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

__all__ = ["InProcessMavfile"]


class InProcessMavfile(mavutil.mavfile):
    """``mavutil.mavfile`` on an in-process endpoint (MAVLink 2, ardupilotmega).

    Args:
        endpoint: from :meth:`Simulator.connect_inprocess` (``read``, ``write``, ``wait_readable``, ``close``).
        source_system, source_component: the GCS identity (255/0 like MAVProxy... 190 like MAVSDK).
    """

    def __init__(self, endpoint, source_system: int = 255, source_component: int = 0):
        self.endpoint = endpoint
        super().__init__(None, "inprocess", source_system=source_system, source_component=source_component, input=False)
        # talk MAVLink 2 from the first byte, whatever mavutil's global dialect is
        self.mav = mavlink2.MAVLink(self, srcSystem=source_system, srcComponent=source_component, use_native=False)
        self.mav.robust_parsing = True
        self.WIRE_PROTOCOL_VERSION = "2.0"
        self.first_byte = False

    def recv(self, n=None) -> bytes:
        return self.endpoint.read(n)

    def write(self, buf) -> int:
        return self.endpoint.write(bytes(buf))

    def select(self, timeout: float) -> bool:
        return self.endpoint.wait_readable(timeout)

    def close(self) -> None:
        self.endpoint.close()
