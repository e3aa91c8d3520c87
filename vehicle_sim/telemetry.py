"""The simulated autopilot's telemetry messages, built from its state: one function per MAVLink message
(``heartbeat(ap)``, ``global_position_int(ap)``, ...), each taking the :class:`vehicle_sim.autopilot.Autopilot`
and returning the pymavlink message (or None where the autopilot sends none yet, as LOCAL_POSITION_NED
before the EKF has an origin). :func:`build` picks one by message name.

Units as MAVLink has them: positions in degE7, altitudes in mm, velocities in cm/s (north, east, down),
headings in centidegrees (GLOBAL_POSITION_INT, GPS_RAW_INT) or degrees (VFR_HUD, NAV_CONTROLLER_OUTPUT),
times in ms since boot (``time_boot_ms``) or us; the boat's own state is in local metres (x east, y north)
and radians (heading clockwise from north). Values follow Rover 4.x (shared/ARDUPILOT_ROVER.md).
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from vehicle_sim.modes import MANUAL_INPUT, MODES, NEEDS_POSITION

__all__ = ["BUILDERS", "build", "battery"]

M = mavlink2


def build(ap, name: str):
    """The message ``name`` (a MAVLink message name, e.g. ``"HEARTBEAT"``) as ``ap`` would send it now, or
    None where it builds none (an unknown name, or one it does not send yet)."""
    fn = BUILDERS.get(name)
    return fn(ap) if fn is not None else None


def heartbeat(ap):
    base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if ap.armed:
        base |= M.MAV_MODE_FLAG_SAFETY_ARMED
    if ap.mode in MANUAL_INPUT:
        base |= M.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    if ap.mode in NEEDS_POSITION:
        base |= M.MAV_MODE_FLAG_GUIDED_ENABLED
    if ap.mode != MODES["MANUAL"]:
        base |= M.MAV_MODE_FLAG_STABILIZE_ENABLED
    if ap.mode == MODES["INITIALISING"]:
        status = M.MAV_STATE_BOOT
    elif ap.failsafe:
        status = M.MAV_STATE_CRITICAL
    else:
        status = M.MAV_STATE_ACTIVE if ap.armed else M.MAV_STATE_STANDBY
    return M.MAVLink_heartbeat_message(M.MAV_TYPE_SURFACE_BOAT, M.MAV_AUTOPILOT_ARDUPILOTMEGA, base, ap.mode, status, 3)


def sys_status(ap):
    sensors = (
        M.MAV_SYS_STATUS_SENSOR_3D_GYRO
        | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
        | M.MAV_SYS_STATUS_SENSOR_3D_MAG
        | M.MAV_SYS_STATUS_SENSOR_GPS
        | M.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
        | M.MAV_SYS_STATUS_AHRS
        | M.MAV_SYS_STATUS_SENSOR_BATTERY
    )
    health = sensors if ap.gps_ok else sensors & ~M.MAV_SYS_STATUS_SENSOR_GPS
    volt, amps, pct = battery(ap)
    return M.MAVLink_sys_status_message(
        sensors, sensors, health, 100, int(volt * 1000), int(amps * 100), pct, 0, 0, 0, 0, 0, 0
    )


def battery(ap) -> tuple[float, float, int]:
    """(volts, amps, percent remaining) of the boat's battery from the energy used so far (Wh)."""
    frac = max(0.0, 1.0 - ap.energy_wh / ap.cfg.battery_wh)
    amps = (5.0 + 40.0 * (ap.boat.speed / 2.0) ** 2) / 12.0
    return 11.1 + 1.5 * frac, amps, int(round(100 * frac))


def battery_status(ap):
    volt, amps, pct = battery(ap)
    cells = [int(volt * 1000)] + [65535] * 9
    mah = int(ap.energy_wh / 12.0 * 1000)
    return M.MAVLink_battery_status_message(
        0,
        M.MAV_BATTERY_FUNCTION_ALL,
        M.MAV_BATTERY_TYPE_LIPO,
        32767,
        cells,
        int(amps * 100),
        mah,
        int(ap.energy_wh * 36),
        pct,
    )


def gps_raw_int(ap):
    if not ap.gps_ok:
        return M.MAVLink_gps_raw_int_message(int(ap.t * 1e6), M.GPS_FIX_TYPE_NO_GPS, 0, 0, 0, 65535, 65535, 0, 65535, 0)
    lat, lon = ap.reported_position()
    b = ap.boat
    gs = math.hypot(b.ground_ve, b.ground_vn)
    cog = (math.degrees(math.atan2(b.ground_ve, b.ground_vn)) % 360.0) if gs > 0.05 else 0.0
    return M.MAVLink_gps_raw_int_message(
        int(ap.t * 1e6),
        M.GPS_FIX_TYPE_3D_FIX,
        int(round(lat * 1e7)),
        int(round(lon * 1e7)),
        int(ap.home_alt * 1000),
        121,
        200,
        int(gs * 100),
        int(cog * 100) % 36000,
        10,
    )


def global_position_int(ap):
    b = ap.boat
    hdg = int(round(math.degrees(b.heading) % 360.0 * 100)) % 36000
    if not ap.gps_ok:
        return M.MAVLink_global_position_int_message(ap.time_boot_ms, 0, 0, 0, 0, 0, 0, 0, hdg)
    lat, lon = ap.reported_position()
    return M.MAVLink_global_position_int_message(
        ap.time_boot_ms,
        int(round(lat * 1e7)),
        int(round(lon * 1e7)),
        int(ap.home_alt * 1000),
        0,
        int(round(b.ground_vn * 100)),
        int(round(b.ground_ve * 100)),
        0,
        hdg,
    )


def attitude(ap):
    b = ap.boat
    return M.MAVLink_attitude_message(ap.time_boot_ms, 0.0, 0.0, b.heading, 0.0, 0.0, b.turn_rate)


def vfr_hud(ap):
    b = ap.boat
    gs = math.hypot(b.ground_ve, b.ground_vn)
    thr = int(min(100, round(100 * b.speed / max(ap.cfg.boat.max_speed, 1e-6))))
    return M.MAVLink_vfr_hud_message(b.speed, gs, int(round(math.degrees(b.heading))) % 360, thr, ap.home_alt, 0.0)


def system_time(ap):
    # UTC comes from the GPS (0 before a fix, as on Rover) and runs on through reboots
    unix = int((ap.epoch0 + ap.clock) * 1e6) if ap.gps_ok and ap.cfg.utc_clock else 0
    return M.MAVLink_system_time_message(unix, ap.time_boot_ms)


def timesync(ap):
    return M.MAVLink_timesync_message(0, int(ap.t * 1e9))


def mission_current(ap):
    total = ap.mission_total()
    seq = ap.mission_index if ap.store.count(0) > 1 else 0
    if ap.mission_state == "complete":
        seq = total
    return M.MAVLink_mission_current_message(seq, total, ap.mission_state_code(), 1 if ap.mode == MODES["AUTO"] else 0)


def ekf_status_report(ap):
    if ap.mode == MODES["INITIALISING"]:
        flags = 0
    elif ap.ekf_abs:
        flags = 831
    else:
        flags = 167
    return M.MAVLink_ekf_status_report_message(flags, 0.02, 0.02, 0.02, 0.02, 0.0, 0.0)


def nav_controller_output(ap):
    b = ap.boat
    if ap.mode == MODES["AUTO"] and ap.active_item is not None:
        tx, ty = ap.item_xy(ap.active_item)
        brg = int(round(math.degrees(math.atan2(tx - b.x, ty - b.y)))) % 360
        dist = int(min(65535, math.hypot(tx - b.x, ty - b.y)))
    else:
        brg, dist = int(round(math.degrees(b.heading))) % 360, 0
    return M.MAVLink_nav_controller_output_message(
        0.0, 0.0, int(round(math.degrees(b.heading))), brg, dist, 0.0, 0.0, 0.0
    )


def local_position_ned(ap):
    if not ap.ekf_abs:
        return None  # no EKF origin yet
    b = ap.boat
    hx, hy = ap.frame.to_xy(*ap.home_latlon)
    return M.MAVLink_local_position_ned_message(ap.time_boot_ms, b.y - hy, b.x - hx, 0.0, b.ground_vn, b.ground_ve, 0.0)


def power_status(ap):
    return M.MAVLink_power_status_message(5000, 0, M.MAV_POWER_STATUS_BRICK_VALID)


def meminfo(ap):
    return M.MAVLink_meminfo_message(0, 65535, 131072)


def home_position(ap):
    lat, lon, alt = ap.home()
    return M.MAVLink_home_position_message(
        int(round(lat * 1e7)),
        int(round(lon * 1e7)),
        int(alt * 1000),
        0.0,
        0.0,
        0.0,
        [1.0, 0.0, 0.0, 0.0],
        0.0,
        0.0,
        0.0,
        int(ap.t * 1e6),
    )


def autopilot_version(ap):
    caps = (
        M.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
        | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
        | M.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
        | M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        | M.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
        | M.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
    )
    # 4.7.0-dev: major<<24 | minor<<16 | patch<<8 | type (0 = dev)
    return M.MAVLink_autopilot_version_message(
        caps, (4 << 24) | (7 << 16), 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, ap.sysid, [0] * 18
    )


def fence_status(ap):
    """FENCE_STATUS (:meth:`vehicle_sim.fence.Fence.status`), None while the fence is disabled."""
    return ap.fence.status(ap)


#: MAVLink message name -> its builder
BUILDERS = {
    "HEARTBEAT": heartbeat,
    "SYS_STATUS": sys_status,
    "BATTERY_STATUS": battery_status,
    "GPS_RAW_INT": gps_raw_int,
    "GLOBAL_POSITION_INT": global_position_int,
    "ATTITUDE": attitude,
    "VFR_HUD": vfr_hud,
    "SYSTEM_TIME": system_time,
    "TIMESYNC": timesync,
    "MISSION_CURRENT": mission_current,
    "EKF_STATUS_REPORT": ekf_status_report,
    "NAV_CONTROLLER_OUTPUT": nav_controller_output,
    "LOCAL_POSITION_NED": local_position_ned,
    "POWER_STATUS": power_status,
    "MEMINFO": meminfo,
    "HOME_POSITION": home_position,
    "AUTOPILOT_VERSION": autopilot_version,
    "FENCE_STATUS": fence_status,
}
