"""The simulated world: site, platform motion, table, and the truth an ideal IMU would sense.

Frames per docs/CONVENTIONS.md: n = ENU, p = the table's stator (C_p^n = Rz(−ψ)Rx(θ)Ry(γ)),
b = the table top (C_b^p = Rz(α)). The platform's reference point is on the table axis; a
sensor sits at a lever arm r^b from it, fixed in b.

    ω_ib^b = C_p^b (C_n^p ω_in^n + ω_np^p) + α̇ e_z,           ω_in^n = ω_ie^n + ω_en^n
    f^b    = C_p^b C_n^p (v̇^n + (2ω_ie^n + ω_en^n) × v^n − g^n) + ω̇_ib^b × r + ω_ib^b × (ω_ib^b × r)

A stage with wobble (TableMotion.wobble) tilts the top by a small rotation vector w(α) in p:
C_b^p = exp([w×])·Rz(α), so C_p^b v = Rz(α)ᵀ(v − w × v + ½ w × (w × v)) and the top gains the
rate ẇ = (dw/dα)·α̇ (in b: Rz(α)ᵀẇ; w·ẇ ≲ 1e-10 rad/s dropped). Every sensor, the truth log and
the still fast path go through this one place. Neglected with a lever arm: the wobble's angular
acceleration (≤ k²·a·α̇² ~ 1e-5 rad/s², < 0.1 µg per 0.1 m).

with g^n = [0, 0, −γ(L, h)] (normal gravity, centrifugal part included) and v̇^n the rate of
change of the ENU velocity components (the navigation equation v̇^n = C_b^n f^b − (2ω_ie +
ω_en) × v^n + g^n solved for f). Neglected, documented: the rate of change of ω_in^n in ω̇
(≤ 1e-9 rad/s² for a car) and the gravity gradient over the lever arm (3e-6 s⁻²·r, < 0.4 µg per m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from firmware_sim.physics import earth
from firmware_sim.physics.table import TableMotion

DEG = math.pi / 180.0
# 3-point Gauss–Legendre on [0, 1]: exact for polynomials up to degree 5 on each interval
_GL_X = 0.5 + 0.5 * np.array([-math.sqrt(0.6), 0.0, math.sqrt(0.6)])
_GL_W = np.array([5.0, 8.0, 5.0]) / 18.0
STILL_ROWS_KEPT = 8
"""Rest rows kept (World.increments): a few sensors at the table's present angle."""


@dataclass(frozen=True)
class Site:
    """Where the bench stands: geodetic latitude [deg] and ellipsoidal height [m]."""

    latitude_deg: float = 40.0
    height_m: float = 0.0

    def __post_init__(self) -> None:
        if not -90.0 <= float(self.latitude_deg) <= 90.0:
            raise ValueError(f"site latitude_deg = {self.latitude_deg}: geodetic, in [-90, 90]")
        if not -12_000.0 <= float(self.height_m) <= 100_000.0:
            raise ValueError(f"site height_m = {self.height_m}: give an ellipsoidal height in metres")

    @property
    def gravity_m_s2(self) -> float:
        """WGS-84 normal gravity here."""
        return float(earth.normal_gravity_m_s2(self.latitude_deg, self.height_m))


@dataclass
class PlatformKinematics:
    """Motion of the platform's reference point and frame at N sample times.

    Attitude and rates are relative to the local-level frame n (ENU) at the current position;
    vel/acc are the ENU velocity components and their time derivative. latitude/height None
    means "the site's".
    """

    c_pn: np.ndarray  # [N,3,3] C_p^n
    omega_np_p: np.ndarray  # [N,3] rate of p relative to n, in p [rad/s]
    omega_dot_np_p: np.ndarray  # [N,3] its time derivative [rad/s²]
    vel_enu_m_s: np.ndarray  # [N,3]
    acc_enu_m_s2: np.ndarray  # [N,3]
    latitude_rad: np.ndarray | None = None  # [N]
    height_m: np.ndarray | None = None  # [N]


@runtime_checkable
class PlatformMotion(Protocol):
    """Anything that moves the platform: a swaying base, a vehicle trajectory (GNSS helper)."""

    is_static: bool

    def kinematics(self, t_s: np.ndarray, site: Site) -> PlatformKinematics:
        """The platform's motion at the device times t_s [N]."""
        ...


@dataclass(frozen=True)
class StaticPlatform:
    """A platform that never moves: heading, pitch, roll in degrees."""

    heading_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    is_static: bool = field(default=True, init=False)

    @property
    def c_pn(self) -> np.ndarray:
        return earth.c_pn(self.heading_deg * DEG, self.pitch_deg * DEG, self.roll_deg * DEG)

    def kinematics(self, t_s: np.ndarray, site: Site) -> PlatformKinematics:
        t = np.asarray(t_s, dtype=float)
        z = np.zeros(t.shape + (3,))
        return PlatformKinematics(np.broadcast_to(self.c_pn, t.shape + (3, 3)), z, z, z, z)


@dataclass(frozen=True)
class Sinusoid:
    """amplitude·sin(2π t / period + phase): amplitude in deg (angles) or m (translations)."""

    amplitude: float
    period_s: float
    phase_deg: float = 0.0

    def eval(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w = 2.0 * math.pi / self.period_s
        arg = w * t + self.phase_deg * DEG
        s, c = np.sin(arg), np.cos(arg)
        return self.amplitude * s, self.amplitude * w * c, -self.amplitude * w * w * s


def _sum(terms: tuple[Sinusoid, ...], t: np.ndarray, scale: float = 1.0):
    out = [np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)]
    for term in terms:
        for i, v in enumerate(term.eval(t)):
            out[i] = out[i] + scale * v
    return out


@dataclass(frozen=True)
class SwayingPlatform:
    """A ship-like base: mean attitude plus sums of sinusoids on roll, pitch, yaw (deg) and on
    surge, sway, heave (m; surge along the mean heading, sway to its right, heave up)."""

    heading_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    roll: tuple[Sinusoid, ...] = ()
    pitch: tuple[Sinusoid, ...] = ()
    yaw: tuple[Sinusoid, ...] = ()
    surge: tuple[Sinusoid, ...] = ()
    sway: tuple[Sinusoid, ...] = ()
    heave: tuple[Sinusoid, ...] = ()
    is_static: bool = field(default=False, init=False)

    def attitude(self, t_s):
        """(ψ, θ, γ) and their first and second derivatives [rad, rad/s, rad/s²]."""
        t = np.asarray(t_s, dtype=float)
        yaw = _sum(self.yaw, t, DEG)
        pit = _sum(self.pitch, t, DEG)
        rol = _sum(self.roll, t, DEG)
        yaw[0] = yaw[0] + self.heading_deg * DEG
        pit[0] = pit[0] + self.pitch_deg * DEG
        rol[0] = rol[0] + self.roll_deg * DEG
        return yaw, pit, rol

    def kinematics(self, t_s: np.ndarray, site: Site) -> PlatformKinematics:
        t = np.asarray(t_s, dtype=float)
        (psi, psid, psidd), (th, thd, thdd), (ga, gad, gadd) = self.attitude(t)
        c, w, wd = earth.zxy_rotation(-psi, th, ga, -psid, thd, gad, -psidd, thdd, gadd)
        h0 = self.heading_deg * DEG
        dirs = (
            (self.surge, np.array([math.sin(h0), math.cos(h0), 0.0])),
            (self.sway, np.array([math.cos(h0), -math.sin(h0), 0.0])),
            (self.heave, np.array([0.0, 0.0, 1.0])),
        )
        pos = np.zeros(t.shape + (3,))
        vel = np.zeros(t.shape + (3,))
        acc = np.zeros(t.shape + (3,))
        for terms, u in dirs:
            if terms:
                p, v, a = _sum(terms, t)
                pos += p[..., None] * u
                vel += v[..., None] * u
                acc += a[..., None] * u
        r_m, _ = earth.radii_m(site.latitude_deg * DEG)
        lat = site.latitude_deg * DEG + pos[..., 1] / (r_m + site.height_m)
        return PlatformKinematics(c, w, wd, vel, acc, lat, site.height_m + pos[..., 2])


@dataclass(frozen=True)
class Disturbance:
    """A bump: δ(t) = A·w(t)·sin(2πf(t − t0)), w = ½(1 − cos(2π(t − t0)/D)) on [t0, t0 + D], zero
    outside (f = 0: a plain raised-cosine tilt). It rotates the platform by
    E = Rz(−δ·w_yaw)·Rx(δ·w_pitch)·Ry(δ·w_roll) on its own axes: C_p'^n = C_p^n·E."""

    start_s: float
    duration_s: float
    amplitude_deg: float
    frequency_hz: float = 2.0
    weights_roll_pitch_yaw: tuple[float, float, float] = (1.0, 0.6, 0.3)

    def delta(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        tau = t - self.start_s
        inside = (tau >= 0.0) & (tau <= self.duration_s)
        tau = np.where(inside, tau, 0.0)
        ww = 2.0 * math.pi / self.duration_s
        w, w1, w2 = 0.5 * (1 - np.cos(ww * tau)), 0.5 * ww * np.sin(ww * tau), 0.5 * ww**2 * np.cos(ww * tau)
        if self.frequency_hz > 0.0:
            f = 2.0 * math.pi * self.frequency_hz
            s, s1, s2 = np.sin(f * tau), f * np.cos(f * tau), -(f**2) * np.sin(f * tau)
        else:
            s, s1, s2 = np.ones_like(tau), np.zeros_like(tau), np.zeros_like(tau)
        a = self.amplitude_deg * DEG * inside
        return a * w * s, a * (w1 * s + w * s1), a * (w2 * s + 2 * w1 * s1 + w * s2)

    def touches(self, t_a: float, t_b: float) -> bool:
        return t_b >= self.start_s and t_a <= self.start_s + self.duration_s


def _untilt(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """exp([w×])ᵀ·v to second order in the small rotation vector w (µrad: exact to 1e-16)."""
    wxv = earth.cross(w, v)
    return v - wxv + 0.5 * earth.cross(w, wxv)


class World:
    """Site + platform + table: the truth every simulated sensor reads (one World per bench)."""

    def __init__(
        self,
        site: Site | None = None,
        platform: PlatformMotion | None = None,
        table: TableMotion | None = None,
    ) -> None:
        self.site = site or Site()
        self.platform = platform if platform is not None else StaticPlatform()
        self.table = table if table is not None else TableMotion()
        self.disturbances: list[Disturbance] = []
        self._static_cache: dict | None = None
        self._still_rows: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        """(Δθ, Δv) of one sample at rest, by (α, dt, lever arm): every sensor on the table has its
        own (a single entry thrashed between the IMU and the accelerometer at every tick)."""

    @classmethod
    def static(
        cls,
        latitude_deg: float,
        heading_deg: float = 0.0,
        pitch_deg: float = 0.0,
        roll_deg: float = 0.0,
        *,
        height_m: float = 0.0,
        table: TableMotion | None = None,
    ) -> World:
        """A bench standing still at a site."""
        return cls(Site(latitude_deg, height_m), StaticPlatform(heading_deg, pitch_deg, roll_deg), table)

    def add_disturbance(
        self, start_s: float, duration_s: float, amplitude_deg: float, **kwargs
    ) -> Disturbance:
        """Perturb the platform attitude smoothly over [start_s, start_s + duration_s] (a bump)."""
        if duration_s <= 0.0:
            raise ValueError("disturbance duration_s must be > 0")
        d = Disturbance(float(start_s), float(duration_s), float(amplitude_deg), **kwargs)
        self.disturbances.append(d)
        return d

    # -- platform in p axes -------------------------------------------------------------------
    def _static_p(self) -> dict:
        """ω_ip^p and f^p (reference point) for a static platform; cached."""
        key = (id(self.platform), self.platform, self.site)
        if self._static_cache is None or self._static_cache["key"] != key:
            c = np.asarray(self.platform.kinematics(np.zeros(1), self.site).c_pn[0])
            w_ie = earth.earth_rate_n_rad_s(self.site.latitude_deg * DEG)
            g_n = np.array([0.0, 0.0, -self.site.gravity_m_s2])
            self._static_cache = {"key": key, "w": c.T @ w_ie, "f": c.T @ (-g_n)}
            self._still_rows.clear()
        return self._static_cache

    def attitude(self, t_s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(C_p^n [N,3,3], ω_np^p [N,3], ω̇_np^p [N,3]) of the platform, disturbances included."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        active = [d for d in self.disturbances if d.touches(float(np.min(t)), float(np.max(t)))]
        return self._disturbed(t, self.platform.kinematics(t, self.site), active)

    @staticmethod
    def _disturbed(t: np.ndarray, k: PlatformKinematics, active: list[Disturbance]):
        """Compose the bumps: C' = C·E, ω' = Eᵀω + ω_E, ω̇' = Eᵀω̇ − ω_E × Eᵀω + ω̇_E."""
        shape = t.shape + (3,)
        c = np.broadcast_to(k.c_pn, t.shape + (3, 3))
        w_np = np.broadcast_to(k.omega_np_p, shape)
        wd_np = np.broadcast_to(k.omega_dot_np_p, shape)
        for d in active:
            dl, dl1, dl2 = d.delta(t)
            wr, wp, wy = d.weights_roll_pitch_yaw
            e, w_e, wd_e = earth.zxy_rotation(
                -wy * dl, wp * dl, wr * dl, -wy * dl1, wp * dl1, wr * dl1, -wy * dl2, wp * dl2, wr * dl2
            )
            et_w = earth.transpose_apply(e, w_np)  # Eᵀ ω
            et_wd = earth.transpose_apply(e, wd_np)
            c = c @ e
            w_np = et_w + w_e
            wd_np = et_wd - earth.cross(w_e, et_w) + wd_e
        return c, w_np, wd_np

    def _platform_p(self, t: np.ndarray):
        """(ω_ip^p, ω̇_ip^p, f^p) of the platform's reference point at times t."""
        active = [d for d in self.disturbances if d.touches(float(np.min(t)), float(np.max(t)))]
        if self.platform.is_static and not active:
            s = self._static_p()
            return s["w"], np.zeros(3), s["f"]
        k = self.platform.kinematics(t, self.site)
        c, w_np, wd_np = self._disturbed(t, k, active)
        lat = np.full(t.shape, self.site.latitude_deg * DEG) if k.latitude_rad is None else k.latitude_rad
        h = np.full(t.shape, self.site.height_m) if k.height_m is None else k.height_m
        w_ie = earth.earth_rate_n_rad_s(lat)
        w_en = earth.transport_rate_n_rad_s(k.vel_enu_m_s, lat, h)
        w_in = w_ie + w_en
        g_n = np.zeros(t.shape + (3,))
        g_n[..., 2] = -earth.normal_gravity_m_s2(lat / DEG, h)
        f_n = k.acc_enu_m_s2 + earth.cross(2.0 * w_ie + w_en, k.vel_enu_m_s) - g_n
        cnp_w_in = earth.transpose_apply(c, w_in)  # C_n^p ω_in^n
        w_ip = cnp_w_in + w_np
        wd_ip = -earth.cross(w_np, cnp_w_in) + wd_np
        f_p = earth.transpose_apply(c, f_n)
        return w_ip, wd_ip, f_p

    # -- truth ----------------------------------------------------------------------------------
    def _truth_parts(self, t: np.ndarray, r: np.ndarray):
        """ω_ib^b without the α̇ e_z term, f^b without the α̈ e_z × r term, and the table's (α, α̇, α̈)."""
        w_ip, wd_ip, f_p = self._platform_p(t)
        alpha, ad, add = self.table.kinematics(t)
        shape = t.shape + (3,)
        w_ip, f_p = np.broadcast_to(w_ip, shape), np.broadcast_to(f_p, shape)
        wobble = self.table.wobble(alpha)
        if wobble is not None:
            w_ip, f_p = _untilt(wobble[0], w_ip), _untilt(wobble[0], f_p)
        w_rot = earth.rot_z_transpose_apply(alpha, w_ip)
        if wobble is not None:
            w_rot = w_rot + earth.rot_z_transpose_apply(alpha, wobble[1] * ad[..., None])
        w_b = w_rot.copy()
        w_b[..., 2] += ad
        f_b = earth.rot_z_transpose_apply(alpha, f_p)
        if np.any(r):
            # ω̇_ib^b = C_p^b ω̇_ip^p − α̇ e_z × (C_p^b ω_ip^p) + α̈ e_z  (the last term handled apart)
            wd_b = earth.rot_z_transpose_apply(alpha, np.broadcast_to(wd_ip, shape))
            wd_b[..., 0] += ad * w_rot[..., 1]
            wd_b[..., 1] -= ad * w_rot[..., 0]
            f_b = f_b + earth.cross(wd_b, r) + earth.cross(w_b, earth.cross(w_b, r))
        return w_rot, f_b, (alpha, ad, add)

    def table_frame(self, t_s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(α [N], C_b^p [N,3,3], ω_pb^b [N,3]) of the table top: Rz(α) and α̇ e_z, tilted by the
        stage's wobble when it has one (the truth log's attitude of b)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        alpha, ad, _ = self.table.kinematics(t)
        c_bp = earth.rot_z(alpha)
        w_pb = np.zeros(t.shape + (3,))
        w_pb[..., 2] = ad
        wobble = self.table.wobble(alpha)
        if wobble is not None:
            w, dw = wobble
            ang = np.linalg.norm(w, axis=-1)
            k = np.where((ang > 0)[..., None], w / np.where(ang > 0, ang, 1.0)[..., None], 0.0)
            kx = np.zeros(t.shape + (3, 3))
            kx[..., 0, 1], kx[..., 0, 2], kx[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
            kx[..., 1, 0], kx[..., 2, 0], kx[..., 2, 1] = k[..., 2], -k[..., 1], k[..., 0]
            s, c = np.sin(ang)[..., None, None], (1.0 - np.cos(ang))[..., None, None]
            tilt = np.eye(3) + s * kx + c * (kx @ kx)  # Rodrigues: exp([w×])
            c_bp = tilt @ c_bp
            w_pb = w_pb + earth.rot_z_transpose_apply(alpha, dw * ad[..., None])
        return alpha, c_bp, w_pb

    def truth(self, t_s, lever_arm_b_m=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
        """(ω_ib^b [N,3] rad/s, f^b [N,3] m/s²) at device times t_s for a sensor at the lever arm."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        r = np.asarray(lever_arm_b_m, dtype=float)
        w_rot, f_b, (_, ad, add) = self._truth_parts(t, r)
        w_rot[..., 2] += ad
        return w_rot, f_b + add[..., None] * earth.cross(earth.EZ, r)

    def increments(self, t0_s: float, n: int, dt_s: float, lever_arm_b_m=(0.0, 0.0, 0.0)):
        """(Δθ [n,3] rad, Δv [n,3] m/s): ∫ω_ib^b and ∫f^b over [t0 + k·dt, t0 + (k+1)·dt], k < n.

        3-point Gauss–Legendre per interval for the smooth parts; the table's own terms are
        integrated exactly (∫α̇ = Δα, ∫α̈ = Δα̇), so the profile's acceleration steps cost no error.
        """
        r = np.asarray(lever_arm_b_m, dtype=float)
        t0, dt = float(t0_s), float(dt_s)
        if n <= 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        t1 = t0 + n * dt
        if (
            self.platform.is_static
            and not any(d.touches(t0, t1) for d in self.disturbances)
            and self.table.still_between(t0, t1)
        ):
            alpha = float(self.table.kinematics(np.array([t0]))[0][0])
            self._static_p()  # refreshes the caches if the platform or site was swapped
            key = (alpha, dt, tuple(r.tolist()))
            rows = self._still_rows.get(key)
            if rows is None:
                if len(self._still_rows) >= STILL_ROWS_KEPT:  # the table's old positions
                    self._still_rows.clear()
                w, f = self.truth(np.array([t0]), r)
                rows = self._still_rows[key] = (w * dt, f * dt)
            return np.repeat(rows[0], n, axis=0), np.repeat(rows[1], n, axis=0)
        edges = t0 + dt * np.arange(n + 1)
        nodes = (edges[:-1, None] + dt * _GL_X).ravel()
        w_rot, f_b, _ = self._truth_parts(nodes, r)
        dtheta = (w_rot.reshape(n, 3, 3) * _GL_W[None, :, None]).sum(axis=1) * dt
        dv = (f_b.reshape(n, 3, 3) * _GL_W[None, :, None]).sum(axis=1) * dt
        alpha, ad, _ = self.table.kinematics(edges)
        dtheta[:, 2] += np.diff(alpha)
        if np.any(r):
            dv += np.diff(ad)[:, None] * earth.cross(earth.EZ, r)
        return dtheta, dv
