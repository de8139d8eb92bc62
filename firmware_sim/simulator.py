"""The bench: one world, its devices on ptys and CAN, and one loop thread that drives them.

Each tick the loop reads the device clock once, services the ports that have input, then lets
every device emit what it owes up to that device time. It sleeps in `select` between ticks
(a few ms of wall time), waking at once when a client writes, so no core spins. Between ticks it
also tops up every pty whose client has read: a pty holds ~20 kB, less than a tick's IMU bytes
at a high time scale, and bytes left waiting for the next tick reach the client late.

Scenarios (`SimConfig.scenario`): `bench` — SMC100 turntable, KVH IMU, CAN accelerometer on a
still (or swaying) platform; `ship` — the KVH IMU alone on a `SwayingPlatform`, at a lever arm
from the centre of rotation; `vehicle` — the KVH IMU and an NMEA GNSS receiver on the
`VehicleTrajectory`, whose device time waits at 0 until a client has the IMU or GNSS port open, so
that the client reads the vehicle's still start whatever the host's timing. `TruthLog` writes the
world's truth as JSON lines for the device times a client needs (docs/simulator.md), with the
events that tie a client's frames to device time.
"""

from __future__ import annotations

import json
import logging
import math
import select
import threading
import time
from dataclasses import asdict
from typing import Any, TextIO

import numpy as np

from firmware_sim.arrivals import ArrivalStamper
from firmware_sim.clock import DeviceClock
from firmware_sim.config import (
    STAGE_RIPPLE_PCT,
    STAGE_RIPPLE_PERIOD_DEG,
    STAGE_WOBBLE_URAD,
    SWAY_AXES,
    ConfigError,
    SimConfig,
    gnss_start,
)
from firmware_sim.devices.base import Device
from firmware_sim.physics import earth
from firmware_sim.pty import PtyPort

__all__ = ["SimConfig", "Simulator"]

log = logging.getLogger("firmware_sim.simulator")

TICK_WALL_S = 0.005
"""Longest wall time between two ticks; input wakes the loop earlier."""
TICK_DEVICE_S = 0.1
"""…and longest device time: above 20× the ticks come closer (0.83 ms of wall time at 120×), so
that a sample waits for its tick no longer in device time than ~0.1 s — at a 5 ms tick a client's
reply to a sample came 0.6 device s late at 120×, and a dwell's end reached the stage that late."""
CONNECT_GRACE_WALL_S = 0.05
"""A new IMU client gets its first frame this long (wall) after the IMU sees it: pyserial flushes
its input right after opening, and a frame delivered before that flush would be lost unseen. The
vehicle's device time starts this long after a client has opened a data port (`holds_for_client`)."""
TRUTH_BATCH_WALL_S = 0.1
"""The truth log computes and writes its samples in batches about this far apart (wall)."""

# independent random streams, one per purpose, from the one seed (SeedSequence.spawn order);
# new purposes go at the end so that the existing streams, and so the bench's bytes, never change
(_STREAM_GYRO, _STREAM_IMU_ACCEL, _STREAM_CAN_ACCEL, _STREAM_IMU_FAULTS, _STREAM_CAN_FAULTS,
 _STREAM_GNSS, _STREAM_GNSS_FAULTS, _STREAM_SWAY_PHASES, _STREAM_IMU_INVALID, _STREAM_IMU_LINK,
 _STREAM_GNSS_LINK) = range(11)
N_STREAMS = 11


def build_world(cfg: SimConfig, phase_seed: Any = None) -> Any:
    """The physics' World for this config (site, platform attitude or trajectory, table, disturbance).

    `phase_seed`: where the ship's sway phases come from when the config gives none (by default
    the seed's own stream, as the simulator uses it).
    """
    from firmware_sim.physics.table import TableMotion
    from firmware_sim.physics.world import Site, StaticPlatform, SwayingPlatform, World

    site = Site(cfg.latitude_deg, cfg.height_m)
    if cfg.scenario != "bench":
        # no turntable: b is the platform (α = 0, no ringing)
        still = TableMotion(power_on_deg=0.0, ringing_amplitude_deg=None)
        if cfg.scenario == "vehicle":
            from firmware_sim.physics.vehicle import VehicleTrajectory

            platform: Any = VehicleTrajectory(heading0_deg=cfg.heading_deg)
        elif cfg.sway:
            if phase_seed is None:
                phase_seed = np.random.SeedSequence(cfg.seed).spawn(N_STREAMS)[_STREAM_SWAY_PHASES]
            terms = _sway_terms(cfg.sway, np.random.default_rng(phase_seed))
            platform = SwayingPlatform(cfg.heading_deg, cfg.pitch_deg, cfg.roll_deg, **terms)
        else:
            platform = StaticPlatform(cfg.heading_deg, cfg.pitch_deg, cfg.roll_deg)
        world = World(site, platform, still)
        if cfg.faults.disturbance is not None:
            world.add_disturbance(*cfg.faults.disturbance)
        return world

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
        ("ripple_pct", "stage_ripple_pct"),
        ("ripple_period_deg", "stage_ripple_period_deg"),
        ("wobble_urad", "stage_wobble_urad"),
    ):
        value = getattr(cfg, name)
        if value is not None:
            table_kw[key] = value
    # the bench's stage ripples and wobbles unless told otherwise (the physics' default is ideal)
    table_kw.setdefault("ripple_pct", STAGE_RIPPLE_PCT)
    table_kw.setdefault("ripple_period_deg", STAGE_RIPPLE_PERIOD_DEG)
    table_kw.setdefault("wobble_urad", STAGE_WOBBLE_URAD)
    table = TableMotion(**table_kw)
    if cfg.sway:
        platform = SwayingPlatform(cfg.heading_deg, cfg.pitch_deg, cfg.roll_deg, **_sway_terms(cfg.sway))
    else:
        platform = StaticPlatform(cfg.heading_deg, cfg.pitch_deg, cfg.roll_deg)
    world = World(site, platform, table)
    if cfg.faults.disturbance is not None:
        world.add_disturbance(*cfg.faults.disturbance)
    return world


def gyro_overrides(errors: Any, cfg: SimConfig) -> Any:
    """The grade's GyroErrors with the config's motion keys applied (None keeps the preset)."""
    changes: dict[str, Any] = {}
    if cfg.gyro_sf_asymmetry_ppm is not None:
        changes["sf_asymmetry_ppm"] = cfg.gyro_sf_asymmetry_ppm
    if cfg.gyro_g_sensitivity_dph_g is not None:
        changes["g_sensitivity_dph_g"] = cfg.gyro_g_sensitivity_dph_g
    if cfg.gyro_misalignment_rad is not None:
        dx, dy = np.broadcast_to(np.asarray(cfg.gyro_misalignment_rad, dtype=float), (2,))
        mis = list(errors.misalignment_urad)
        mis[1], mis[3] = dx * 1e6, dy * 1e6  # (xy, xz, yx, yz, zx, zy): x and y toward z
        changes["misalignment_urad"] = tuple(mis)
    return errors.with_(**changes) if changes else errors


def _sway_terms(spec: dict[str, Any],
                phase_rng: np.random.Generator | None = None) -> dict[str, tuple[Any, ...]]:
    """`{roll = [[2.0, 8.0], [0.5, 3.1, 40]], heave = [{amplitude = 0.3, period_s = 6}]}` → Sinusoids.

    Each term: [amplitude, period_s] or [amplitude, period_s, phase_deg], or a table with those
    keys; amplitudes in degrees (roll, pitch, yaw) or metres (surge, sway, heave). A term without
    a phase gets 0 (bench) or, with `phase_rng` (ship), a phase uniform in [0°, 360°), drawn
    axis by axis in SWAY_AXES order and term by term.
    """
    from firmware_sim.physics.world import Sinusoid

    out: dict[str, tuple[Any, ...]] = {}
    for axis in sorted(spec, key=lambda a: SWAY_AXES.index(a) if a in SWAY_AXES else len(SWAY_AXES)):
        terms = spec[axis]
        if axis not in SWAY_AXES:
            raise ConfigError(f"sway.{axis}: unknown axis; use {', '.join(SWAY_AXES)}")
        if not isinstance(terms, list | tuple):
            raise ConfigError(f"sway.{axis}: give a list of [amplitude, period_s(, phase_deg)]")
        built = []
        for term in terms:
            try:
                if isinstance(term, dict):
                    values = [term["amplitude"], term["period_s"]]
                    if "phase_deg" in term:
                        values.append(term["phase_deg"])
                else:
                    values = list(term)
                if len(values) == 2 and phase_rng is not None:
                    values.append(phase_rng.uniform(0.0, 360.0))
                built.append(Sinusoid(*(float(v) for v in values)))
            except (KeyError, TypeError, ValueError):
                raise ConfigError(
                    f"sway.{axis}: term {term!r} is not [amplitude, period_s(, phase_deg)]") from None
            if not built[-1].period_s > 0.0:
                raise ConfigError(f"sway.{axis}: period_s must be > 0 in {term!r}")
        out[axis] = tuple(built)
    return out


def platform_position_enu_m(platform: Any, t: np.ndarray) -> np.ndarray:
    """ENU position [N,3] of the platform's reference point about the site: a trajectory's own,
    a swaying base's surge/sway/heave (as `SwayingPlatform.kinematics` moves it), else 0."""
    t = np.asarray(t, dtype=float)
    if hasattr(platform, "position_enu_m"):
        return np.asarray(platform.position_enu_m(t), dtype=float).reshape(len(t), 3)
    pos = np.zeros((len(t), 3))
    h0 = math.radians(getattr(platform, "heading_deg", 0.0))
    directions = (("surge", (math.sin(h0), math.cos(h0), 0.0)), ("sway", (math.cos(h0), -math.sin(h0), 0.0)),
                  ("heave", (0.0, 0.0, 1.0)))
    for name, u in directions:
        for term in getattr(platform, name, ()):
            pos += term.eval(t)[0][:, None] * np.asarray(u)
    return pos


def euler_deg(c_bn: np.ndarray) -> np.ndarray:
    """(heading [0, 360), pitch, roll) in degrees [N,3] of C_b^n = Rz(−ψ)Rx(θ)Ry(γ) (CONVENTIONS.md):
    C[0,1] = sin ψ cos θ, C[1,1] = cos ψ cos θ, C[2,1] = sin θ, C[2,0] = −cos θ sin γ,
    C[2,2] = cos θ cos γ."""
    psi = np.degrees(np.arctan2(c_bn[:, 0, 1], c_bn[:, 1, 1])) % 360.0
    theta = np.degrees(np.arcsin(np.clip(c_bn[:, 2, 1], -1.0, 1.0)))
    gamma = np.degrees(np.arctan2(-c_bn[:, 2, 0], c_bn[:, 2, 2]))
    return np.stack([psi, theta, gamma], axis=-1)


class TruthLog(Device):
    """The world's truth as JSON lines (docs/simulator.md): a header, then truth samples every
    1/truth_rate_hz of device time and the devices' events (client connects, k ↔ t anchors), in
    device-time order, flushed batch by batch (about every TRUTH_BATCH_WALL_S of wall time).

    Why: for a simulated run the simulator is the ground truth, and northfinder, which cannot
    import firmware_sim, needs the truth at the device time of its result.
    """

    name = "truth"
    FORMAT = "firmware_sim truth log"
    VERSION = 1

    def __init__(self, path: str, sim: Simulator, *, batch_device_s: float) -> None:
        try:
            self._fh: TextIO = open(path, "w", encoding="utf-8")  # noqa: SIM115 - closed in close()
        except OSError as exc:
            raise ConfigError(f"truth_log = {path!r}: cannot write it ({exc.strerror}); "
                              "give a path in a writable directory") from None
        self.path = str(path)
        self.sim = sim
        self.rate_hz = float(sim.config.truth_rate_hz)
        self.batch_device_s = max(float(batch_device_s), 1.0 / self.rate_hz)
        self._next_i = 0  # next truth sample, at device time i / rate_hz
        self._written_until_s = -math.inf
        self._events: list[tuple[float, str]] = []
        self._lock = threading.Lock()
        self.closed = False
        self.rows_written = 0

    # -- what a row holds ---------------------------------------------------------------------
    def fields(self) -> list[str]:
        out = ["t_device_s", "heading_deg", "pitch_deg", "roll_deg", "imu_pos_enu_m", "imu_vel_enu_m_s"]
        if self.sim.config.scenario == "bench":
            out += ["platform_heading_deg", "platform_pitch_deg", "platform_roll_deg", "table_deg",
                    "table_encoder_deg"]
        if self.sim.gnss is not None:
            out += ["antenna_pos_enu_m", "antenna_vel_enu_m_s"]
        return out

    def truth(self, t_s: np.ndarray) -> dict[str, np.ndarray]:
        """Every field of `fields()` at device times t_s [N], vectorized."""
        world = self.sim.world
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        plat = world.platform
        if hasattr(plat, "attitude") and hasattr(plat, "velocity_enu_m_s") and not world.disturbances:
            c_pn, w_np, _ = plat.attitude(t)  # a trajectory: C_p^n and ω_np^p directly (cheaper)
            vel_ref = plat.velocity_enu_m_s(t)
        else:
            c_pn, w_np, _ = world.attitude(t)
            vel_ref = np.broadcast_to(plat.kinematics(t, world.site).vel_enu_m_s, (len(t), 3))
        pos_ref = platform_position_enu_m(plat, t)
        alpha, c_bp, w_pb = world.table_frame(t)  # Rz(α) and α̇ e_z, with the stage's wobble
        c_pn = np.broadcast_to(c_pn, (len(t), 3, 3))
        c_bn = c_pn @ c_bp
        w_nb = earth.transpose_apply(c_bp, np.broadcast_to(w_np, (len(t), 3))) + w_pb

        def point(r_b: Any) -> tuple[np.ndarray, np.ndarray]:
            r = np.asarray(r_b, dtype=float)
            return (pos_ref + np.einsum("nij,j->ni", c_bn, r),
                    vel_ref + np.einsum("nij,nj->ni", c_bn, earth.cross(w_nb, r)))

        hpr = euler_deg(c_bn)
        out = {"t_device_s": t, "heading_deg": hpr[:, 0], "pitch_deg": hpr[:, 1], "roll_deg": hpr[:, 2]}
        out["imu_pos_enu_m"], out["imu_vel_enu_m_s"] = point(self.sim.imu.lever_arm_b_m)
        if self.sim.config.scenario == "bench":
            php = euler_deg(c_pn)
            out.update(platform_heading_deg=php[:, 0], platform_pitch_deg=php[:, 1],
                       platform_roll_deg=php[:, 2], table_deg=np.degrees(alpha),
                       table_encoder_deg=np.degrees(world.table.encoder_rad(t)))
        if self.sim.gnss is not None:
            out["antenna_pos_enu_m"], out["antenna_vel_enu_m_s"] = point(self.sim.gnss.lever_arm_b_m)
        return out

    # -- writing ------------------------------------------------------------------------------
    def write_header(self, endpoints: dict[str, Any]) -> None:
        """The first line: format, scenario, seed, the whole config, endpoints, what rows hold."""
        cfg = self.sim.config
        header: dict[str, Any] = {
            "type": "header", "format": self.FORMAT, "version": self.VERSION, "scenario": cfg.scenario,
            "seed": cfg.seed, "config": asdict(cfg), "endpoints": endpoints, "truth_rate_hz": self.rate_hz,
            "fields": self.fields(),
            "imu": {"rate_hz": self.sim.imu.rate_hz, "axes": self.sim.imu.axes,
                    "lever_arm_b_m": np.asarray(self.sim.imu.lever_arm_b_m).tolist(),
                    "sample_k": "k = 1, 2, ... since power-on; sequence (k - 1) mod 128; "
                                "device time of its interval's end t = k / rate_hz until an imu_grid event"},
            "enu_origin": {"latitude_deg": cfg.latitude_deg, "longitude_deg": cfg.longitude_deg,
                           "height_m": cfg.height_m},
        }
        sway = {name: [[term.amplitude, term.period_s, term.phase_deg] for term in terms]
                for name in SWAY_AXES if (terms := getattr(self.sim.world.platform, name, ()))}
        if sway:
            header["sway"] = sway
        if self.sim.gnss is not None:
            header["gnss"] = {"rate_hz": self.sim.gnss.rate_hz,
                              "lever_arm_b_m": self.sim.gnss.lever_arm_b_m.tolist(),
                              "start_utc": endpoints.get("gnss_start_utc")}
        with self._lock:
            self._fh.write(json.dumps(header, default=str) + "\n")
            self._fh.flush()

    def event(self, name: str, t_device_s: float, fields: dict[str, Any]) -> None:
        """Queue an event; it is written in device-time order with the next batch of samples."""
        line = json.dumps({"type": "event", "event": name, "t_device_s": float(t_device_s), **fields})
        with self._lock:
            self._events.append((float(t_device_s), line))

    def advance(self, t_device_s: float) -> None:
        if t_device_s - self._written_until_s >= self.batch_device_s:
            self._write_until(t_device_s)

    def _write_until(self, t_end_s: float) -> None:
        with self._lock:
            if self.closed:
                return
            i_end = math.floor(t_end_s * self.rate_hz + 1e-9)
            lines: list[tuple[float, int, str]] = []
            if i_end >= self._next_i:
                t = np.arange(self._next_i, i_end + 1) / self.rate_hz
                cols = {k: v.tolist() for k, v in self.truth(t).items()}
                names = list(cols)
                for j, tj in enumerate(t.tolist()):
                    row = {"type": "truth", **{k: cols[k][j] for k in names}}
                    lines.append((tj, 0, json.dumps(row)))
                self.rows_written += len(t)
                self._next_i = i_end + 1
            lines += [(te, 1, line) for te, line in self._events if te <= t_end_s]
            self._events = [(te, line) for te, line in self._events if te > t_end_s]
            lines.sort(key=lambda x: (x[0], x[1]))
            if lines:
                self._fh.write("".join(line + "\n" for _, _, line in lines))
                self._fh.flush()
            self._written_until_s = t_end_s

    def close(self) -> None:
        """Write what is due up to the loop's last tick, an `end` event, and close. Idempotent."""
        if self.closed:
            return
        t_last = self.sim.last_t
        self.event("end", t_last, {"rows": self.rows_written + max(0, math.floor(t_last * self.rate_hz + 1e-9)
                                                                  + 1 - self._next_i)})
        self._write_until(max(t_last, max((te for te, _ in self._events), default=t_last)))
        with self._lock:
            self.closed = True
            self._fh.close()


class Simulator:
    """`with Simulator(SimConfig(...)) as endpoints:` — the bench runs in a thread of this process.

    `endpoints` is the dict the command prints: for the bench the turntable and imu pty paths and
    the CAN accelerometer's interface/channel/bitrate/node_id; for the ship the imu; for the
    vehicle the imu, the gnss pty and the UTC of device time 0 in its sentences.
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
        self.gnss: Any = None
        self.truth: TruthLog | None = None
        self._buses: list[Any] = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.failed = threading.Event()
        self.error: BaseException | None = None
        self.ticks = 0
        self.last_t = 0.0
        """Device time of the loop's last tick."""
        self._clock_running = False
        self._client_seen_wall_s: float | None = None
        """Wall time since which a client has had a data port open (held scenarios; None: none has)."""
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
        if kind == "gyro":
            errors = gyro_overrides(errors, self.config)
        return model_cls(errors, rate_hz, np.random.default_rng(stream))

    def _build(self) -> None:
        from firmware_sim.devices.kvh import KvhImu
        from firmware_sim.devices.smc100 import Smc100

        cfg = self.config
        streams = np.random.SeedSequence(cfg.seed).spawn(N_STREAMS)
        self.world = build_world(cfg, streams[_STREAM_SWAY_PHASES])
        if cfg.truth_log:  # first, so that a bad path is refused before any port opens
            self.truth = TruthLog(cfg.truth_log, self, batch_device_s=TRUTH_BATCH_WALL_S * cfg.time_scale)
        if cfg.scenario == "bench":
            self.turntable = self._build_apt() if cfg.stage_model == "apt" else Smc100(
                                    self.world, address=cfg.stage_address, stall_move=cfg.faults.stage_stall,
                                    on_event=self.truth.event if self.truth is not None else None)
            self.devices.append(self.turntable)

        def make_imu_models(rate_hz: float) -> tuple[Any, Any]:
            # the same streams at every rate: a rate change rebuilds the models with the same
            # constant errors (the unit is the same unit)
            gyro = self._models(streams[_STREAM_GYRO], "gyro", rate_hz)
            accel = self._models(streams[_STREAM_IMU_ACCEL], "accel", rate_hz)
            return gyro, accel

        self.imu = self._build_stim(streams, make_imu_models) if cfg.imu_model == "stim" else KvhImu(
            self.world, rate_hz=cfg.imu_rate_hz, axes=cfg.imu_axes, rot_format=cfg.imu_rot_format,
            rot_units=cfg.imu_rot_units, lever_arm_b_m=cfg.imu_lever_arm_m,
            temperature_c=cfg.imu_temperature_c, make_models=make_imu_models, faults=cfg.faults,
            fault_seed=streams[_STREAM_IMU_FAULTS],
            backlog_bytes=max(64 * 1024, int(36 * 1000 * cfg.time_scale
                                             * (cfg.client_stall_wall_s + cfg.link_hold_ms / 1e3))),
            connect_grace_s=CONNECT_GRACE_WALL_S * cfg.time_scale,
            on_event=self.truth.event if self.truth is not None else None,
            link=self._link("imu", streams[_STREAM_IMU_LINK]), invalid_seed=streams[_STREAM_IMU_INVALID],
        )
        self.devices.append(self.imu)
        if cfg.scenario == "bench" and cfg.accel_enabled:
            self._build_can(streams)
        if cfg.scenario == "vehicle":
            from firmware_sim.devices.gnss import GnssReceiver

            self.gnss = GnssReceiver(
                self.world, rate_hz=cfg.gnss_rate_hz, lever_arm_b_m=cfg.gnss_lever_arm_m,
                rng=np.random.default_rng(streams[_STREAM_GNSS]), faults=cfg.faults,
                fault_seed=streams[_STREAM_GNSS_FAULTS], longitude_deg=cfg.longitude_deg,
                start_utc=gnss_start(cfg), link=self._link("gnss", streams[_STREAM_GNSS_LINK]),
            )
            self.devices.append(self.gnss)
        if self.truth is not None:
            self.devices.append(self.truth)  # last: it logs what the devices did in the same tick

    def _link(self, device: str, stream: np.random.SeedSequence) -> Any:
        """The USB-serial link of the imu or gnss pty (latency, hold), or None when both are off
        (the bytes then go straight to the pty, as before)."""
        from firmware_sim.link import LinkShaper, LinkSpec

        cfg = self.config
        spec = LinkSpec(latency_s=getattr(cfg, f"{device}_link_latency_ms") / 1e3,
                        jitter_s=getattr(cfg, f"{device}_link_jitter_ms") / 1e3,
                        hold_period_s=cfg.link_hold_period_s, hold_wall_s=cfg.link_hold_ms / 1e3,
                        hold_jitter_s=cfg.link_hold_jitter_s)
        if not spec.active:
            return None
        return LinkShaper(spec, np.random.default_rng(stream), name=device,
                          on_event=self.truth.event if self.truth is not None else None)

    # -- the second model of each role (issue 24; docs/PROTOCOLS.md §6–8) -----------------------
    def _build_apt(self) -> Any:
        """A Thorlabs KDC101 + PRM1-Z8 on the same table."""
        from firmware_sim.devices.apt import AptStage

        return AptStage(self.world, stall_move=self.config.faults.stage_stall,
                        on_event=self.truth.event if self.truth is not None else None)

    def _build_stim(self, streams: list[np.random.SeedSequence], make_models: Any) -> Any:
        """A STIM IMU on the same world, with the grade's error models at its rate."""
        from firmware_sim.devices.stim import StimImu

        cfg = self.config
        rate = cfg.imu_rate_hz if cfg.imu_rate_hz in (125, 250, 500, 1000, 2000) else 500
        gyro, accel = make_models(rate)
        stall_s = cfg.client_stall_wall_s + cfg.link_hold_ms / 1e3
        backlog = max(64 * 1024, int(38 * rate * cfg.time_scale * stall_s))  # 38 B per 0x93 datagram
        return StimImu(self.world, gyro, accel, rate_hz=rate, lever_arm_b_m=cfg.imu_lever_arm_m,
                       faults=cfg.faults, fault_seed=streams[_STREAM_IMU_FAULTS],
                       port=PtyPort("imu", backlog_bytes=backlog))

    def _build_cia410(self, node_bus: Any, accel_model: Any, remodel: Any) -> Any:
        """A CiA 410 inclinometer node; its event timer is the accelerometer rate's period."""
        from firmware_sim.devices.cia410 import Cia410Node

        cfg = self.config
        return Cia410Node(node_bus, self.world, accel_model, node_id=cfg.can_node_id,
                          event_ms=int(round(1000.0 / cfg.accel_rate_hz)),
                          lever_arm_b_m=cfg.accel_lever_arm_m, make_model=remodel)

    def _build_can(self, streams: list[np.random.SeedSequence]) -> None:
        import can

        from firmware_sim.can_wire import wire
        from firmware_sim.devices.canopen_accel import CanAccelNode

        cfg = self.config
        if cfg.can_interface == "slcan":
            from firmware_sim.devices.slcan_adapter import SlcanAdapter

            node_bus, adapter_bus = wire(f"firmware_sim-{id(self):x}")
            self._buses += [node_bus, adapter_bus]
            self.can_adapter = SlcanAdapter(adapter_bus)
        elif cfg.can_interface == "virtual":
            node_bus = can.Bus(interface="virtual", channel=cfg.can_channel, receive_own_messages=False)
            self._buses.append(node_bus)
        else:
            node_bus = can.Bus(interface="socketcan", channel=cfg.can_channel)
            self._buses.append(node_bus)
        accel_model = self._models(streams[_STREAM_CAN_ACCEL], "accel", cfg.accel_rate_hz)
        # a rate written over SDO gets a model for that rate, from a new child of the same stream
        remodel = lambda hz: self._models(streams[_STREAM_CAN_ACCEL].spawn(1)[0], "accel", hz)  # noqa: E731
        cia410 = cfg.tilt_model == "cia410"
        self.accelerometer = self._build_cia410(node_bus, accel_model, remodel) if cia410 \
            else CanAccelNode(
            node_bus, self.world, accel_model, node_id=cfg.can_node_id, rate_hz=cfg.accel_rate_hz,
            lever_arm_b_m=cfg.accel_lever_arm_m, faults=cfg.faults.for_accel(),
            temperature_c=cfg.imu_temperature_c, rng=np.random.default_rng(streams[_STREAM_CAN_FAULTS]),
            mapping=cfg.accel_mapping, make_model=remodel,
        )
        self.devices.append(self.accelerometer)
        if self.can_adapter is not None:
            # after the node: what it sends in a tick reaches the wire in that tick, as through a
            # real adapter (before it, every frame waited a tick: 0.6 device s at 120×)
            self.devices.append(self.can_adapter)

    # -- endpoints --------------------------------------------------------------------------
    @property
    def endpoints(self) -> dict[str, Any]:
        """{"turntable": path, "imu": path, "can": {...}} as in docs/ARCHITECTURE.md."""
        cfg = self.config
        out: dict[str, Any] = {}
        if self.turntable is not None:
            out["turntable"] = self.turntable.endpoint()
        out["imu"] = self.imu.endpoint()
        if self.gnss is not None:
            out["gnss"] = self.gnss.endpoint()
            start = gnss_start(cfg)
            fraction = f".{start.microsecond // 10_000:02d}" if start.microsecond else ""
            out["gnss_start_utc"] = start.strftime("%Y-%m-%dT%H:%M:%S") + fraction + "Z"
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
        """Open every port, start the loop thread; return the endpoints.

        Device time starts with the loop, except in a scenario that starts with a motion the client
        must see from its beginning (`holds_for_client`): there it stays at 0 until a client has
        one of the data ports open.
        """
        if self._thread is not None:
            raise RuntimeError("simulator already started")
        try:
            self._build()
        except BaseException:
            self._close_all()
            raise
        self._endpoints = self.endpoints
        if self.truth is not None:
            self.truth.write_header(self._endpoints)
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

    @property
    def holds_for_client(self) -> bool:
        """Whether device time waits at 0 for a client (`_client_ready`): the vehicle only.

        Why: the vehicle stands still for its first 10 s and a GNSS/INS alignment levels the IMU on
        the first 5 s it reads (northfinder's align-gnss refuses a moving start), so where device
        time stands when the client's first sample comes must not depend on how long the host took
        to start the client — 10 s of device time are 0.4 s of wall time at 25×. Either data port
        starts it, so that a client of the receiver alone gets its data; northfinder opens the IMU
        first. The bench and the ship have no such start (and benches and tests that never connect
        must run): their device time starts with the loop.
        """
        return self.config.scenario == "vehicle"

    def _data_ports(self) -> list[PtyPort]:
        """The ports whose data a client of the held scenario reads: the IMU's and the receiver's."""
        return [d.port for d in (self.imu, self.gnss) if isinstance(getattr(d, "port", None), PtyPort)]

    def _client_ready(self) -> bool:
        """A client has had a data port open for CONNECT_GRACE_WALL_S (pyserial flushes its input
        right after opening: what came before would be lost unseen). The devices then power on
        with that client listening: the IMU hands it every sample from k = 1, device time 0 on."""
        now = time.monotonic()
        if not any(port.connected for port in self._data_ports()):
            self._client_seen_wall_s = None
        elif self._client_seen_wall_s is None:
            self._client_seen_wall_s = now
        return self._client_seen_wall_s is not None and now - self._client_seen_wall_s >= CONNECT_GRACE_WALL_S

    def _run(self) -> None:
        self._can_powered = False
        if not self.holds_for_client:
            self.clock.start()
            self._clock_running = True
        stamper: ArrivalStamper[Device] = ArrivalStamper(self.now)
        next_tick = time.monotonic()
        try:
            while not self._stop.is_set():
                stamper.watch({p: d for d in self.devices if (p := d.input_port()) is not None})
                backlogged = {p.fileno(): p for p in self._ports()
                              if p.pending and not p.closed and p.connected}
                wait_s = max(0.0, next_tick - time.monotonic())
                readable, writable, _ = select.select([stamper.fileno()], list(backlogged), [], wait_s)
                if writable and not readable and time.monotonic() < next_tick and \
                        sum(backlogged[fd].flush() for fd in writable):
                    continue  # a client read: its pty topped up at once, the tick still to come
                next_tick = time.monotonic() + min(TICK_WALL_S, self.clock.wall_s(TICK_DEVICE_S))
                if not self._clock_running and self._client_ready():
                    self.clock.start()
                    self._clock_running = True
                t, arrived = stamper.take()  # held: commands are answered at device time 0
                for t_in, device, data in arrived:
                    device.on_input(data, t_in)
                for device in self.devices:
                    if self._clock_running and self._device_may_run(device):
                        device.advance(t)
                stamper.poll()  # what came during the devices' work is stamped now, not when the thread runs
                for port in self._ports():
                    port.flush()
                self.ticks += 1
                self.last_t = t
        except BaseException as exc:  # report, do not die silently in a thread
            log.exception("simulator loop failed")
            self.error = exc
            self.failed.set()
        finally:
            stamper.close()

    def now(self) -> float:
        """Device seconds since start (0 until the loop has started device time; the vehicle: until
        a client has a data port open)."""
        return self.clock.now() if self._clock_running else 0.0

    def stop(self) -> None:
        """End the loop and release every pty, bus and temporary file. Idempotent."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self._close_all()

    def _close_all(self) -> None:
        devices = list(self.devices)
        if self.truth is not None and self.truth not in devices:  # _build failed before adding it
            devices.append(self.truth)
        for device in devices:
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
        deadline = time.monotonic() + 60.0
        while not self._clock_running and time.monotonic() < deadline and not self.failed.is_set():
            time.sleep(0.01)  # device time has not started yet (no loop yet, or held for a client)
        time.sleep(self.clock.wall_s(device_s))
