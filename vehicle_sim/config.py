"""Simulator configuration (frozen dataclasses; all times are simulated seconds)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from vehicle_sim.boat import BoatParams

__all__ = ["SimConfig", "LinkConfig"]


@dataclass(frozen=True)
class LinkConfig:
    """Impairment of one link; times in simulated seconds.

    Attributes:
        loss: probability that a frame is lost, applied independently each way.
        latency_s: one-way delay added to every frame.
        baud: serial rate to emulate (bits/s, 10 bits per byte as on a UART); 0 =
            unlimited. Frames are serialised one after another at ``baud/10``
            bytes per simulated second; a frame that would wait more than
            ``max_queue_s`` in the radio's buffer is dropped, like a full radio.
        drops: scheduled outages ``((start_s, duration_s), ...)`` on the simulator's clock (seconds
            since it started): nothing passes either way during them.
        arm_drops: outages ``((start_s, duration_s), ...)`` counted from the vehicle's first arming
            (the start of its mission, whatever the wall time the clock ran before a client got there).
        drops_break_link: a drop also ends the links it interrupts: a link open when a drop began stays
            silent after it until it is closed (a modem that lost its session), so a ground station hears
            the vehicle again only once it has noticed the loss and reconnected; a link opened later
            passes frames once the drop is over. Injected drops are then seen by the ground station
            however late it looks (``passt-mav demo --inject-link-drop``).
        seed: seed of the loss generator (each link adds its index).
        max_queue_s: radio buffer size, expressed as seconds of backlog.
        buffer_bytes: radio transmit buffer in bytes (0 = only ``max_queue_s``): a frame that does not
            fit in what is left of it is dropped (:func:`vehicle_sim.radio.queue_frame`).
    """

    loss: float = 0.0
    latency_s: float = 0.0
    baud: int = 0
    drops: tuple[tuple[float, float], ...] = ()
    arm_drops: tuple[tuple[float, float], ...] = ()
    drops_break_link: bool = False
    seed: int = 0
    max_queue_s: float = 2.0
    buffer_bytes: int = 0

    @classmethod
    def radio(
        cls,
        baud: int = 57600,
        *,
        latency_s: float = 0.1,
        loss: float = 0.03,
        buffer_bytes: int = 2048,
        seed: int = 0,
        **kw,
    ) -> LinkConfig:
        """A SiK-like telemetry radio (:mod:`vehicle_sim.radio`): ``baud``, 100 ms one way, 3 % loss, 2 kB buffer."""
        return cls(loss=loss, latency_s=latency_s, baud=baud, buffer_bytes=buffer_bytes, seed=seed, **kw)

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss < 1.0:
            raise ValueError(f"loss must be in [0, 1), got {self.loss}")
        if self.latency_s < 0 or self.baud < 0:
            raise ValueError("latency and baud must be >= 0")


@dataclass(frozen=True)
class SimConfig:
    """Everything the simulated autopilot needs besides the field and home.

    Boot timeline (defaults observed on Rover 4.7 SITL): INITIALISING until
    ``init_s``, then MANUAL; GPS detected at ``gps_s`` (GLOBAL_POSITION_INT reads
    lat/lon 0 before); arming refused until ``arm_ready_s`` ("Arm: System not
    initialised"); the EKF uses GPS (absolute position, EKF flags 167 -> 831) at
    ``ekf_gps_s``; mission uploads answered NO_SPACE until ``storage_ready_s``.

    Attributes:
        sysid, compid: our MAVLink identity.
        physics_dt: largest integration step, simulated seconds.
        mission_capacity: items per mission type (0 mission incl. home, 1 fence, 2 rally).
        mission_request_interval_s: the vehicle's own pace between item requests
            (ArduPilot asks for about 48 items per second).
        mission_rerequest_s / mission_timeout_s: re-request after this much silence;
            cancel the upload after this much.
        current_rate_hz: rate of the CUR_U/CUR_V current-sensor readings (0 = off).
        current_noise_std: Gaussian noise (m/s) added to each reading component.
        seed: seed of the sensor noise.
        boat: hull/controller limits and the navigation law.
        params: initial parameter overrides (name -> value).
        gps_noise_m: std (m, per axis) of the error of reported positions (0 = exact); a
            first-order Gauss-Markov process seeded from ``seed``; the boat navigates on
            its true position.
        gps_noise_tau_s: correlation time of that error, simulated seconds.
        utc_clock: SYSTEM_TIME carries UTC (``epoch0`` + simulated time) once GPS is
            detected; False: ``time_unix_usec`` stays 0 (a vehicle without a clock).
        start_armed: arm at once when ready (tests).
        tlog: path of a telemetry log of everything sent and received, or None.
        signing_key: 32-byte secret: sign everything, drop unsigned input.
        battery_wh: battery capacity for the (simple) BATTERY_STATUS model.
    """

    sysid: int = 1
    compid: int = 1
    physics_dt: float = 0.05
    init_s: float = 1.0
    gps_s: float = 9.0
    arm_ready_s: float = 25.0
    ekf_gps_s: float = 42.0
    storage_ready_s: float = 2.0
    mission_capacity: tuple[int, int, int] = (700, 84, 20)
    mission_request_interval_s: float = 1.0 / 48.0
    mission_rerequest_s: float = 1.0
    mission_timeout_s: float = 8.0
    current_rate_hz: float = 1.0
    current_noise_std: float = 0.0
    seed: int = 0
    gps_noise_m: float = 0.0
    gps_noise_tau_s: float = 60.0
    utc_clock: bool = True
    boat: BoatParams = field(default_factory=BoatParams)
    params: tuple[tuple[str, float], ...] = ()
    tlog: str | None = None
    signing_key: bytes | None = None
    battery_wh: float = 100.0

    @classmethod
    def fast(cls, **kw) -> SimConfig:
        """A config whose boot timeline is compressed (tests): ready after ~2 s."""
        base = dict(init_s=0.2, gps_s=0.5, arm_ready_s=1.0, ekf_gps_s=1.5, storage_ready_s=0.3)
        base.update(kw)
        return cls(**base)

    def replace(self, **kw) -> SimConfig:
        return replace(self, **kw)
