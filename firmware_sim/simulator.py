"""The bench: one world, its devices on ptys and CAN, and one loop thread that drives them.

Each tick the loop reads the device clock once, services the ports that have input, then lets
every device emit what it owes up to that device time. It sleeps in `select` between ticks
(a few ms of wall time), waking at once when a client writes, so no core spins.
"""

from __future__ import annotations

import logging
import select
import threading
import time
from typing import Any

import numpy as np

from firmware_sim.clock import DeviceClock
from firmware_sim.config import SimConfig
from firmware_sim.devices.base import Device
from firmware_sim.pty import PtyPort

__all__ = ["SimConfig", "Simulator"]

log = logging.getLogger("firmware_sim.simulator")

TICK_WALL_S = 0.005
"""Longest wall time between two ticks; input wakes the loop earlier."""
CLIENT_STALL_WALL_S = 1.0
"""A connected IMU client may stop reading for this long (wall) before bytes are dropped."""

# independent random streams, one per purpose, from the one seed (SeedSequence.spawn order)
_STREAM_GYRO, _STREAM_IMU_ACCEL, _STREAM_CAN_ACCEL, _STREAM_IMU_FAULTS, _STREAM_CAN_FAULTS = range(5)


def build_world(cfg: SimConfig) -> Any:
    """The physics' World for this config (site, platform attitude, sway, table, disturbance)."""
    from firmware_sim.physics.table import TableMotion
    from firmware_sim.physics.world import Site, StaticPlatform, SwayingPlatform, World

    table_kw: dict[str, Any] = {}
    for key, name in (
        ("power_on_deg", "stage_power_on_deg"),
        ("speed_deg_s", "stage_speed_dps"),
        ("accel_deg_s2", "stage_accel_dps2"),
        ("home_speed_deg_s", "stage_home_speed_dps"),
        ("ringing_amplitude_deg", "stage_ringing_deg"),
        ("ringing_freq_hz", "stage_ringing_hz"),
        ("ringing_decay_s", "stage_ringing_decay_s"),
        ("encoder_step_deg", "encoder_step_deg"),
    ):
        value = getattr(cfg, name)
        if value is not None:
            table_kw[key] = value
    table = TableMotion(**table_kw)
    site = Site(cfg.latitude_deg, cfg.height_m)
    if cfg.sway:
        platform: Any = SwayingPlatform(cfg.heading_deg, cfg.pitch_deg, cfg.roll_deg, **_sway_terms(cfg.sway))
    else:
        platform = StaticPlatform(cfg.heading_deg, cfg.pitch_deg, cfg.roll_deg)
    world = World(site, platform, table)
    if cfg.faults.disturbance is not None:
        world.add_disturbance(*cfg.faults.disturbance)
    return world


SWAY_AXES = ("roll", "pitch", "yaw", "surge", "sway", "heave")


def _sway_terms(spec: dict[str, Any]) -> dict[str, tuple[Any, ...]]:
    """`{roll = [[2.0, 8.0], [0.5, 3.1, 40]], heave = [{amplitude = 0.3, period_s = 6}]}` → Sinusoids.

    Each term: [amplitude, period_s] or [amplitude, period_s, phase_deg], or a table with those
    keys; amplitudes in degrees (roll, pitch, yaw) or metres (surge, sway, heave).
    """
    from firmware_sim.config import ConfigError
    from firmware_sim.physics.world import Sinusoid

    out: dict[str, tuple[Any, ...]] = {}
    for axis, terms in spec.items():
        if axis not in SWAY_AXES:
            raise ConfigError(f"sway.{axis}: unknown axis; use {', '.join(SWAY_AXES)}")
        if not isinstance(terms, list):
            raise ConfigError(f"sway.{axis}: give a list of [amplitude, period_s(, phase_deg)]")
        built = []
        for term in terms:
            try:
                if isinstance(term, dict):
                    built.append(Sinusoid(float(term["amplitude"]), float(term["period_s"]),
                                          float(term.get("phase_deg", 0.0))))
                else:
                    built.append(Sinusoid(*(float(v) for v in term)))
            except (KeyError, TypeError, ValueError):
                raise ConfigError(
                    f"sway.{axis}: term {term!r} is not [amplitude, period_s(, phase_deg)]") from None
            if not built[-1].period_s > 0.0:
                raise ConfigError(f"sway.{axis}: period_s must be > 0 in {term!r}")
        out[axis] = tuple(built)
    return out


class Simulator:
    """`with Simulator(SimConfig(...)) as endpoints:` — the bench runs in a thread of this process.

    `endpoints` is the dict the command prints: turntable and imu pty paths, and the CAN
    accelerometer's interface/channel/bitrate/node_id.
    """

    def __init__(self, config: SimConfig | None = None, **overrides: Any) -> None:
        if config is None:
            config = SimConfig(**overrides)
        elif overrides:
            from dataclasses import replace

            config = replace(config, **overrides)
        self.config = config
        self.clock = DeviceClock(config.time_scale)
        self.devices: list[Device] = []
        self.world: Any = None
        self.turntable: Any = None
        self.imu: Any = None
        self.accelerometer: Any = None
        self.can_adapter: Any = None
        self._buses: list[Any] = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.failed = threading.Event()
        self.error: BaseException | None = None
        self.ticks = 0
        self._endpoints: dict[str, Any] | None = None

    # -- building ---------------------------------------------------------------------------
    def _models(self, stream: np.random.SeedSequence, kind: str, rate_hz: float) -> Any:
        from firmware_sim.physics import sensors

        presets = sensors.GYRO_PRESETS if kind == "gyro" else sensors.ACCEL_PRESETS
        model_cls = sensors.GyroModel if kind == "gyro" else sensors.AccelModel
        try:
            errors = presets[self.config.grade]
        except KeyError:
            from firmware_sim.config import ConfigError

            raise ConfigError(f"grade = {self.config.grade!r}: use one of {', '.join(presets)}") from None
        return model_cls(errors, rate_hz, np.random.default_rng(stream))

    def _build(self) -> None:
        from firmware_sim.devices.kvh import KvhImu
        from firmware_sim.devices.smc100 import Smc100

        cfg = self.config
        streams = np.random.SeedSequence(cfg.seed).spawn(5)
        self.world = build_world(cfg)
        self.turntable = Smc100(self.world, address=cfg.stage_address, stall_move=cfg.faults.stage_stall)
        self.devices.append(self.turntable)

        def make_imu_models(rate_hz: float) -> tuple[Any, Any]:
            # the same streams at every rate: a rate change rebuilds the models with the same
            # constant errors (the unit is the same unit)
            gyro = self._models(streams[_STREAM_GYRO], "gyro", rate_hz)
            accel = self._models(streams[_STREAM_IMU_ACCEL], "accel", rate_hz)
            return gyro, accel

        self.imu = KvhImu(
            self.world, rate_hz=cfg.imu_rate_hz, variant=cfg.imu_variant, rot_format=cfg.imu_rot_format,
            rot_units=cfg.imu_rot_units, lever_arm_b_m=cfg.imu_lever_arm_m,
            temperature_c=cfg.imu_temperature_c, make_models=make_imu_models, faults=cfg.faults,
            fault_seed=streams[_STREAM_IMU_FAULTS],
            backlog_bytes=max(64 * 1024, int(36 * 1000 * cfg.time_scale * CLIENT_STALL_WALL_S)),
        )
        self.devices.append(self.imu)
        if cfg.accel_enabled:
            self._build_can(streams)

    def _build_can(self, streams: list[np.random.SeedSequence]) -> None:
        import can

        from firmware_sim.devices.canopen_accel import CanAccelNode

        cfg = self.config
        if cfg.can_interface == "slcan":
            from firmware_sim.devices.slcan_adapter import SlcanAdapter

            channel = f"firmware_sim-{id(self):x}"
            node_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
            self._buses.append(node_bus)
            adapter_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
            self._buses.append(adapter_bus)
            self.can_adapter = SlcanAdapter(adapter_bus)
        elif cfg.can_interface == "virtual":
            node_bus = can.Bus(interface="virtual", channel=cfg.can_channel, receive_own_messages=False)
            self._buses.append(node_bus)
        else:
            node_bus = can.Bus(interface="socketcan", channel=cfg.can_channel)
            self._buses.append(node_bus)
        accel_model = self._models(streams[_STREAM_CAN_ACCEL], "accel", cfg.accel_rate_hz)
        self.accelerometer = CanAccelNode(
            node_bus, self.world, accel_model, node_id=cfg.can_node_id, rate_hz=cfg.accel_rate_hz,
            lever_arm_b_m=cfg.accel_lever_arm_m, faults=cfg.faults.for_accel(),
            temperature_c=cfg.imu_temperature_c, rng=np.random.default_rng(streams[_STREAM_CAN_FAULTS]),
        )
        if self.can_adapter is not None:
            self.devices.append(self.can_adapter)
        self.devices.append(self.accelerometer)

    # -- endpoints --------------------------------------------------------------------------
    @property
    def endpoints(self) -> dict[str, Any]:
        """{"turntable": path, "imu": path, "can": {...}} as in docs/ARCHITECTURE.md."""
        cfg = self.config
        out: dict[str, Any] = {"turntable": self.turntable.endpoint(), "imu": self.imu.endpoint()}
        if self.accelerometer is not None:
            if self.can_adapter is not None:
                can_ep = dict(self.can_adapter.endpoint())
            else:
                can_ep = {"interface": cfg.can_interface, "channel": cfg.can_channel}
            can_ep.update({"bitrate": cfg.can_bitrate, "node_id": cfg.can_node_id})
            out["can"] = can_ep
        return out

    # -- running ----------------------------------------------------------------------------
    def start(self) -> dict[str, Any]:
        """Open every port, start the loop thread at device time 0; return the endpoints."""
        if self._thread is not None:
            raise RuntimeError("simulator already started")
        try:
            self._build()
        except BaseException:
            self._close_all()
            raise
        self._endpoints = self.endpoints
        self._thread = threading.Thread(target=self._run, name="firmware_sim-loop", daemon=True)
        self._thread.start()
        log.info("bench running: %s", self._endpoints)
        return self._endpoints

    def _ports(self) -> list[PtyPort]:
        return [p for d in self.devices if isinstance(p := getattr(d, "port", None), PtyPort)]

    def _device_may_run(self, device: Device) -> bool:
        # behind the slcan adapter the node powers on when the client first opens the channel,
        # so that its boot-up heartbeat reaches someone (a bench is powered after it is cabled)
        if device is self.accelerometer and self.can_adapter is not None:
            if not self._can_powered:
                self._can_powered = bool(self.can_adapter.is_open)
            return self._can_powered
        return True

    def _run(self) -> None:
        self._can_powered = False
        try:
            # The sensor models' filters need scipy.signal, which takes 0.5-2 s to import: load it
            # here, after the endpoints are out and before device time starts, so that the first
            # samples are not a burst of catch-up (the devices are "booting" meanwhile).
            import scipy.signal  # noqa: F401

            self.clock.start()
            while not self._stop.is_set():
                by_fd = {fd: d for d in self.devices if (fd := d.fileno()) is not None}
                wfds = [p.fileno() for p in self._ports() if p.pending and not p.closed and p.connected]
                readable, _, _ = select.select(list(by_fd), wfds, [], TICK_WALL_S)
                t = self.clock.now()
                for fd in readable:
                    device = by_fd[fd]
                    if device.fileno() == fd:
                        device.on_readable(t)
                for device in self.devices:
                    if self._device_may_run(device):
                        device.advance(t)
                for port in self._ports():
                    port.flush()
                self.ticks += 1
        except BaseException as exc:  # report, do not die silently in a thread
            log.exception("simulator loop failed")
            self.error = exc
            self.failed.set()

    def now(self) -> float:
        """Device seconds since start."""
        return self.clock.now()

    def stop(self) -> None:
        """End the loop and release every pty, bus and temporary file. Idempotent."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self._close_all()

    def _close_all(self) -> None:
        for device in self.devices:
            try:
                device.close()
            except Exception:  # noqa: BLE001 - closing must go on for the others
                log.exception("closing %s", getattr(device, "name", device))
        for bus in self._buses:
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001
                log.exception("shutting down a CAN bus")
        self._buses.clear()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until the loop fails (True) or the timeout passes (False)."""
        return self.failed.wait(timeout_s)

    def __enter__(self) -> dict[str, Any]:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def run_for(self, device_s: float) -> None:
        """Sleep the calling thread for `device_s` of device time (a test helper)."""
        time.sleep(self.clock.wall_s(device_s))
