"""A land vehicle's trajectory for GNSS/INS alignment runs: still start, accelerations, S-turns, stops.

What: position, velocity and acceleration of the IMU reference point in local East-North-Up
metres, attitude (heading ψ, pitch θ, roll γ per docs/CONVENTIONS.md, C_b^n = Rz(−ψ)Rx(θ)Ry(γ))
with its Euler rates and the body rate ω_nb^b, all as vectorized functions of device time t.

Why this shape: the World turns this into ω_ib^b and f^b, and a filter checks them against GNSS,
so every quantity must be the exact derivative of the one before it. The speed is a sum of
septic smooth-steps (v is C³), the yaw rate a sum of sin⁴ bumps (ψ̇ C³; a step or bump wholly
before or after the times asked for adds nothing or its closed-form total, so a short batch costs
the few it overlaps), so position, heading
and the suspension pitch/roll that follow the accelerations are all at least C². Velocity and
acceleration are closed-form; position is the integral of velocity, tabulated once with
5-point Gauss–Legendre per 50 ms cell and completed within a cell by the same rule, so
d(position)/dt equals velocity to ~1e-12 m/s. The vehicle moves on a flat road without side
slip (velocity along the heading); the body pitches with longitudinal and rolls with lateral
acceleration (a suspension, small angles) plus road roughness — those rates make the vertical
lever arm observable.

firmware_sim imports nothing from northfinder: everything here is written from the conventions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from firmware_sim.physics import earth
from firmware_sim.physics.world import PlatformKinematics, Site

_GL_X, _GL_W = np.polynomial.legendre.leggauss(5)


def _smoothstep(u):
    """Septic smooth-step S(u) = 35u⁴ − 84u⁵ + 70u⁶ − 20u⁷ on [0, 1]: S′, S″, S‴ vanish at both
    ends, so a speed built from it is C³ and the pitch that follows the acceleration is C²."""
    u = np.clip(u, 0.0, 1.0)
    return u**4 * (35.0 - 84.0 * u + 70.0 * u**2 - 20.0 * u**3)


def _smoothstep_d1(u):
    u = np.clip(u, 0.0, 1.0)
    return 140.0 * u**3 * (1.0 - u) ** 3


def _smoothstep_d2(u):
    u = np.clip(u, 0.0, 1.0)
    return 420.0 * u**2 * (1.0 - u) ** 2 * (1.0 - 2.0 * u)


def _smoothstep_d3(u):
    u = np.clip(u, 0.0, 1.0)
    return 840.0 * u * (1.0 - u) * (1.0 - 5.0 * u + 5.0 * u * u)


@dataclass(frozen=True)
class SpeedChange:
    """Speed goes from its current value to `to_m_s` over [start_s, start_s + duration_s]."""

    start_s: float
    duration_s: float
    to_m_s: float


@dataclass(frozen=True)
class Turn:
    """A yaw-rate bump ψ̇ = peak·sin⁴(πu), u = (t − start)/duration; heading change = 3/8·peak·duration.

    Positive `peak_rad_s` turns right (heading increases, clockwise from north).
    """

    start_s: float
    duration_s: float
    peak_rad_s: float


def s_turn(start_s: float, half_duration_s: float, peak_rad_s: float) -> tuple[Turn, Turn]:
    """Left-then-right (or right-then-left) pair of equal bumps: net heading change zero."""
    second = Turn(start_s + half_duration_s, half_duration_s, -peak_rad_s)
    return Turn(start_s, half_duration_s, peak_rad_s), second


def default_schedule() -> tuple[list[SpeedChange], list[Turn]]:
    """The 300 s drive: 10 s still, accelerations to 10–15 m/s, S-turns, a 90° turn, two stops."""
    speeds = [
        SpeedChange(10.0, 8.0, 10.0),
        SpeedChange(60.0, 8.0, 0.0),  # stop 68–75 s
        SpeedChange(75.0, 10.0, 15.0),
        SpeedChange(140.0, 10.0, 5.0),
        SpeedChange(160.0, 10.0, 12.0),
        SpeedChange(230.0, 10.0, 0.0),  # stop 240–250 s
        SpeedChange(250.0, 10.0, 10.0),
        SpeedChange(290.0, 8.0, 0.0),  # still from 298 s
    ]
    turns = [
        *s_turn(22.0, 6.0, 0.25),
        *s_turn(40.0, 6.0, -0.2),
        *s_turn(90.0, 6.0, 0.15),
        *s_turn(110.0, 6.0, -0.15),
        *s_turn(125.0, 6.0, 0.12),
        Turn(150.0, 10.0, np.pi / 2.0 / (0.375 * 10.0)),  # 90° right at 5 m/s
        *s_turn(175.0, 6.0, -0.18),
        *s_turn(195.0, 6.0, 0.18),
        *s_turn(215.0, 6.0, -0.15),
        *s_turn(262.0, 6.0, 0.2),
        *s_turn(278.0, 6.0, -0.2),
    ]
    return speeds, turns


@dataclass
class VehicleTrajectory:
    """A vehicle driving on a flat road; all methods take a device-time array t_s (seconds).

    Parameters: initial heading [deg], start position in local ENU [m], the speed and turn
    schedule, and the suspension gains: pitch per longitudinal acceleration and roll per
    lateral acceleration [rad per m/s²] (nose up when accelerating, body rolls out of a turn).
    Road roughness: `road_pitch` / `road_roll` are (amplitude_deg, frequency_hz, phase_deg)
    sinusoids of body pitch/roll scaled by speed / road_ref_speed_m_s, so they vanish when stopped.
    """

    heading0_deg: float = 30.0
    start_enu_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    speeds: list[SpeedChange] = field(default_factory=lambda: default_schedule()[0])
    turns: list[Turn] = field(default_factory=lambda: default_schedule()[1])
    pitch_per_accel_rad: float = 0.01
    roll_per_accel_rad: float = 0.01
    road_pitch: tuple[tuple[float, float, float], ...] = ((0.3, 1.3, 0.0), (0.15, 2.1, 40.0))
    road_roll: tuple[tuple[float, float, float], ...] = ((0.4, 0.9, 20.0), (0.2, 1.7, 70.0))
    road_ref_speed_m_s: float = 10.0
    duration_s: float = 300.0
    _cell_s: float = 0.05

    def __post_init__(self) -> None:
        v = 0.0
        self._dv = []
        for sc in self.speeds:
            self._dv.append((sc.start_s, sc.duration_s, sc.to_m_s - v))
            v = sc.to_m_s
        if min((s.to_m_s for s in self.speeds), default=0.0) < 0:
            raise ValueError("vehicle speeds must be >= 0 (it drives forward)")
        # Position table at cell edges over [0, duration + margin].
        n_cells = int(np.ceil((self.duration_s + 10.0) / self._cell_s))
        edges = np.arange(n_cells + 1) * self._cell_s
        steps = self._integrate_velocity(edges[:-1], np.full(n_cells, self._cell_s))
        self._table = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)]) + np.asarray(self.start_enu_m, float)

    # -- speed and heading -----------------------------------------------------------------------
    def speed_m_s(self, t_s, *, jerk: bool = False):
        """Speed v, v̇, v̈ along the heading (and v⃛ with jerk=True)."""
        t = np.asarray(t_s, dtype=float)
        v, vd, vdd, vddd = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)
        t_lo, t_hi = (float(t.min()), float(t.max())) if t.size else (0.0, 0.0)
        for t0, dur, dv in self._dv:
            if t_hi <= t0:  # not begun anywhere in t
                continue
            if t_lo >= t0 + dur:  # over everywhere in t: S(1) = 1, its derivatives 0
                v = v + dv
                continue
            u = (t - t0) / dur
            v = v + dv * _smoothstep(u)
            vd = vd + dv * _smoothstep_d1(u) / dur
            vdd = vdd + dv * _smoothstep_d2(u) / dur**2
            if jerk:
                vddd = vddd + dv * _smoothstep_d3(u) / dur**3
        return (v, vd, vdd, vddd) if jerk else (v, vd, vdd)

    def heading_rad(self, t_s, *, jerk: bool = False):
        """Heading ψ (unwrapped, clockwise from north), ψ̇, ψ̈ (and ψ⃛ with jerk=True).

        ψ̇ = A sin⁴(πu) = A(3/8 − cos 2πu/2 + cos 4πu/8): C³, so the roll that follows v·ψ̇ is C²."""
        t = np.asarray(t_s, dtype=float)
        psi = np.full_like(t, np.deg2rad(self.heading0_deg))
        rate, acc, jrk = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)
        t_lo, t_hi = (float(t.min()), float(t.max())) if t.size else (0.0, 0.0)
        for tr in self.turns:
            if t_hi <= tr.start_s:  # not begun anywhere in t
                continue
            if t_lo >= tr.start_s + tr.duration_s:  # over everywhere in t: ψ += 3/8·A·T, rates 0
                psi = psi + tr.peak_rad_s * tr.duration_s * 0.375
                continue
            u = np.clip((t - tr.start_s) / tr.duration_s, 0.0, 1.0)
            a, k = tr.peak_rad_s, np.pi / tr.duration_s
            sn, cs = np.sin(np.pi * u), np.cos(np.pi * u)
            psi = psi + a * tr.duration_s * (0.375 * u - np.sin(2 * np.pi * u) / (4 * np.pi)
                                             + np.sin(4 * np.pi * u) / (32 * np.pi))
            rate = rate + a * sn**4
            acc = acc + a * 4.0 * k * sn**3 * cs
            if jerk:
                jrk = jrk + a * 4.0 * k * k * sn**2 * (3.0 * cs**2 - sn**2)
        return (psi, rate, acc, jrk) if jerk else (psi, rate, acc)

    # -- translational ---------------------------------------------------------------------------
    def velocity_enu_m_s(self, t_s) -> np.ndarray:
        """v^n [N, 3]: speed along the heading, horizontal road."""
        v, _, _ = self.speed_m_s(t_s)
        psi, _, _ = self.heading_rad(t_s)
        return np.stack([v * np.sin(psi), v * np.cos(psi), np.zeros_like(v)], axis=-1)

    def acceleration_enu_m_s2(self, t_s) -> np.ndarray:
        """a^n = v̇·[sin ψ, cos ψ, 0] + v·ψ̇·[cos ψ, −sin ψ, 0]."""
        v, vd, _ = self.speed_m_s(t_s)
        psi, rate, _ = self.heading_rad(t_s)
        s, c = np.sin(psi), np.cos(psi)
        return np.stack([vd * s + v * rate * c, vd * c - v * rate * s, np.zeros_like(v)], axis=-1)

    def _integrate_velocity(self, t0, h) -> np.ndarray:
        """∫_{t0}^{t0+h} v^n dt by 5-point Gauss–Legendre (vectorized over t0, h)."""
        t0 = np.asarray(t0, float)[:, None]
        h = np.asarray(h, float)[:, None]
        nodes = t0 + 0.5 * h * (_GL_X[None, :] + 1.0)
        vel = self.velocity_enu_m_s(nodes.ravel()).reshape(nodes.shape + (3,))
        return 0.5 * h * np.einsum("k,nkj->nj", _GL_W, vel)

    def position_enu_m(self, t_s) -> np.ndarray:
        """p^n [N, 3] in local ENU metres: the tabulated integral plus the partial cell."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        idx = np.clip(np.floor(t / self._cell_s).astype(int), 0, len(self._table) - 2)
        t_cell = idx * self._cell_s
        pos = self._table[idx] + self._integrate_velocity(t_cell, t - t_cell)
        return pos.reshape(np.shape(t_s) + (3,))

    # -- attitude --------------------------------------------------------------------------------
    def euler_rad(self, t_s):
        """(ψ, θ, γ), their rates and second derivatives: pitch θ = k_p·v̇ (nose up when speeding up),
        roll γ = −k_r·v·ψ̇ (the lateral acceleration v·ψ̇ points right in a right turn; the body
        rolls out of the turn, left side down)."""
        v, vd, vdd, vddd = self.speed_m_s(t_s, jerk=True)
        psi, rate, acc, jrk = self.heading_rad(t_s, jerk=True)
        kp, kr = self.pitch_per_accel_rad, self.roll_per_accel_rad
        pitch = np.array([kp * vd, kp * vdd, kp * vddd])
        roll = -kr * np.array([v * rate, vd * rate + v * acc, vdd * rate + 2 * vd * acc + v * jrk])
        t = np.asarray(t_s, dtype=float)
        pitch = pitch + self._road(t, self.road_pitch, v, vd, vdd)
        roll = roll + self._road(t, self.road_roll, v, vd, vdd)
        return (psi, pitch[0], roll[0]), (rate, pitch[1], roll[1]), (acc, pitch[2], roll[2])

    def _road(self, t, terms, v, vd, vdd) -> np.ndarray:
        """Σ A·s(t)·sin(ωt + φ) with s = v/v_ref, and its first two derivatives (product rule)."""
        s, sd, sdd = v / self.road_ref_speed_m_s, vd / self.road_ref_speed_m_s, vdd / self.road_ref_speed_m_s
        out = np.zeros((3,) + np.shape(t))
        for amp_deg, f_hz, ph_deg in terms:
            a, w = np.deg2rad(amp_deg), 2 * np.pi * f_hz
            sn, cs = np.sin(w * t + np.deg2rad(ph_deg)), np.cos(w * t + np.deg2rad(ph_deg))
            out[0] += a * s * sn
            out[1] += a * (sd * sn + s * w * cs)
            out[2] += a * (sdd * sn + 2 * sd * w * cs - s * w * w * sn)
        return out

    def attitude(self, t_s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(C_b^n [N,3,3], ω_nb^b [N,3] rad/s, ω̇_nb^b [N,3] rad/s²) with C_b^n = Rz(−ψ)Rx(θ)Ry(γ)."""
        (psi, th, ga), (psid, thd, gad), (psidd, thdd, gadd) = self.euler_rad(t_s)
        return earth.zxy_rotation(-psi, th, ga, -psid, thd, gad, -psidd, thdd, gadd)

    def c_bn(self, t_s) -> np.ndarray:
        """C_b^n = Rz(−ψ)Rx(θ)Ry(γ) [N, 3, 3]."""
        return self.attitude(t_s)[0]

    def omega_nb_b_rad_s(self, t_s) -> np.ndarray:
        """ω_nb^b [N, 3]: the body rate relative to the local-level frame."""
        return self.attitude(t_s)[1]

    # -- the World's platform hook (firmware_sim.physics.world.PlatformMotion) -------------------
    is_static: bool = field(default=False, init=False)

    def kinematics(self, t_s, site: Site) -> PlatformKinematics:
        """The vehicle as the World's moving platform: attitude, rates, ENU velocity/acceleration,
        latitude and height from the local ENU position about the site (curvilinear, as the
        GNSS receiver reports it)."""
        t = np.asarray(t_s, dtype=float)
        c, w, wd = self.attitude(t)
        pos = self.position_enu_m(t)
        lat0 = np.deg2rad(site.latitude_deg)
        r_m, _ = earth.radii_m(lat0)
        lat = lat0 + pos[..., 1] / (r_m + site.height_m)
        return PlatformKinematics(
            c,
            w,
            wd,
            self.velocity_enu_m_s(t),
            self.acceleration_enu_m_s2(t),
            lat,
            site.height_m + pos[..., 2],
        )

    # -- GNSS antenna ----------------------------------------------------------------------------
    def antenna_enu(self, t_s, lever_arm_b_m) -> tuple[np.ndarray, np.ndarray]:
        """Position [N,3] and velocity [N,3] in local ENU of a point at lever arm r^b from the IMU:
        p + C_b^n r and v + C_b^n(ω_nb^b × r)."""
        r = np.asarray(lever_arm_b_m, dtype=float)
        c, w, _ = self.attitude(t_s)
        pos = self.position_enu_m(t_s) + np.einsum("...ij,j->...i", c, r)
        vel = self.velocity_enu_m_s(t_s) + np.einsum("...ij,...j->...i", c, np.cross(w, r))
        return pos, vel


@dataclass
class SimulatedDrive:
    """One simulated drive: IMU increments (measured), GNSS fixes of the antenna (noisy), truth."""

    rate_hz: float
    dtheta_rad: np.ndarray
    dv_m_s: np.ndarray
    gnss_t_s: np.ndarray
    gnss_pos_enu_m: np.ndarray
    gnss_vel_enu_m_s: np.ndarray
    gnss_pos_std_m: tuple[float, float, float]
    gnss_vel_std_m_s: tuple[float, float, float]
    lever_arm_b_m: tuple[float, float, float]
    site: Site
    trajectory: VehicleTrajectory


def simulate_drive(
    trajectory: VehicleTrajectory | None = None,
    *,
    site: Site | None = None,
    grade: str = "kvh1760",
    seed: int = 0,
    rate_hz: float = 250.0,
    gnss_rate_hz: float = 10.0,
    lever_arm_b_m: tuple[float, float, float] = (0.5, 1.5, 1.2),
    gnss_pos_std_m: tuple[float, float, float] = (0.5, 0.5, 1.0),
    gnss_vel_std_m_s: tuple[float, float, float] = (0.05, 0.05, 0.05),
) -> SimulatedDrive:
    """The World's truth for the vehicle (IMU at the platform reference point, no turntable),
    the grade's GyroModel/AccelModel, and white-noise GNSS fixes of the antenna at gnss_rate_hz."""
    from firmware_sim.physics.sensors import AccelModel, GyroModel, accel_errors, gyro_errors
    from firmware_sim.physics.table import TableMotion
    from firmware_sim.physics.world import World

    traj = trajectory or VehicleTrajectory()
    site = site or Site(40.0, 100.0)
    world = World(site, traj, TableMotion(power_on_deg=0.0, ringing_amplitude_deg=None))
    n = int(round(traj.duration_s * rate_hz))
    dth, dv = world.increments(0.0, n, 1.0 / rate_hz)
    seeds = np.random.SeedSequence(seed).spawn(3)
    dth = GyroModel(gyro_errors(grade), rate_hz, np.random.default_rng(seeds[0])).apply(dth, dv)
    dv = AccelModel(accel_errors(grade), rate_hz, np.random.default_rng(seeds[1])).apply(dv)
    t_g = np.arange(1, int(np.floor(traj.duration_s * gnss_rate_hz)) + 1) / gnss_rate_hz
    pos, vel = traj.antenna_enu(t_g, lever_arm_b_m)
    rng = np.random.default_rng(seeds[2])
    pos = pos + rng.standard_normal(pos.shape) * np.asarray(gnss_pos_std_m)
    vel = vel + rng.standard_normal(vel.shape) * np.asarray(gnss_vel_std_m_s)
    return SimulatedDrive(
        rate_hz,
        dth,
        dv,
        t_g,
        pos,
        vel,
        tuple(gnss_pos_std_m),
        tuple(gnss_vel_std_m_s),
        tuple(lever_arm_b_m),
        site,
        traj,
    )
