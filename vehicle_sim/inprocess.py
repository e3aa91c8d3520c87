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
    conn = sim.connect_inprocess().mavlink_connection(autostep=0.05)
    conn.wait_heartbeat()          # steps the simulator while it waits

Time: with ``autostep=dt`` every poll that finds no data advances the simulator
by ``dt`` simulated seconds (deterministic lockstep, as fast as the CPU allows);
with ``autostep=None`` the simulator must be advanced elsewhere (``sim.step`` or
``sim.serve`` in a thread) and ``select`` just sleeps briefly.
"""

from __future__ import annotations

import time

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

__all__ = ["InProcessMavfile"]


class InProcessMavfile(mavutil.mavfile):
    """``mavutil.mavfile`` on an in-process endpoint (MAVLink 2, ardupilotmega).

    Args:
        endpoint: from :meth:`Simulator.connect_inprocess`.
        source_system, source_component: the GCS identity (255/0 like MAVProxy... 190 like MAVSDK).
        autostep: simulated seconds to advance per idle poll (lockstep), or None.
    """

    def __init__(self, endpoint, source_system: int = 255, source_component: int = 0, autostep: float | None = None):
        self.endpoint = endpoint
        self.autostep = autostep
        super().__init__(None, "inprocess", source_system=source_system, source_component=source_component, input=False)
        # talk MAVLink 2 from the first byte, whatever mavutil's global dialect is
        self.mav = mavlink2.MAVLink(self, srcSystem=source_system, srcComponent=source_component, use_native=False)
        self.mav.robust_parsing = True
        self.WIRE_PROTOCOL_VERSION = "2.0"
        self.first_byte = False

    def recv(self, n=None) -> bytes:
        data = self.endpoint.read(n)
        if not data and self.autostep:
            self.endpoint.sim.step(self.autostep)
            data = self.endpoint.read(n)
        return data

    def write(self, buf) -> int:
        return self.endpoint.write(bytes(buf))

    def select(self, timeout: float) -> bool:
        if self.autostep:
            return True  # recv() advances the clock itself
        time.sleep(min(timeout, 0.005))
        return True

    def close(self) -> None:
        self.endpoint.close()
