"""Turntable north finding: from per-position means to heading, tilt and an honest 1σ.

Public entry point :func:`solve_heading` (one find) and :func:`solve_batch` (many trials with
the same table angles, one pseudo-inverse for all; used by the Monte Carlo). Derivations and
error tables: docs/estimators.md. Paper: turntable-north-seeking-leveling-algorithms (Liu,
Yuan, Zhou 2011), equations cited per function.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from northfinder.constants import DPH, OMEGA_EARTH_RAD_S, STANDARD_GRAVITY_M_S2, normal_gravity_m_s2
from northfinder.errors import InputError
from northfinder.estimators.harmonic import HarmonicFit, fit_harmonic
from northfinder.estimators.methods import METHODS, pitch_roll_from_up
from northfinder.rotations import tilt_and_azimuth

DEFAULT_TILT_LIMIT_DEG = 30.0
DEFAULT_ACCEL_TOLERANCE = 0.05
"""Largest accepted relative difference between |f| and the local gravity."""
MAX_ABS_LATITUDE_DEG = 89.0


@dataclass(frozen=True)
class BatchSolution:
    """Arrays over T trials (degrees, [0, 360) for angles that wrap)."""

    method: str
    heading_deg: np.ndarray
    heading_std_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    tilt_deg: np.ndarray
    tilt_azimuth_deg: np.ndarray
    methods: dict[str, np.ndarray]
    up_p: np.ndarray
    accel_magnitude_g: np.ndarray
    gyro_fit: HarmonicFit
    accel_fit: HarmonicFit


@dataclass(frozen=True)
class HeadingSolution:
    """One north find. Angles in degrees; heading in [0, 360).

    `methods` holds every method's heading (same fit, same tilt); `gyro_fit` / `accel_fit` the
    harmonic fits (gyro coefficients in deg/h, accelerometer in g; parameter names v_x, v_y,
    R_<axis>…); `heading_std_deg` is the 1σ propagated from both fits' covariances
    (`gyro_fit.noise` says whether from given standard errors or from the residuals).
    """

    heading_deg: float
    heading_std_deg: float
    pitch_deg: float
    roll_deg: float
    tilt_deg: float
    tilt_azimuth_deg: float
    method: str
    latitude_deg: float
    n_positions: int
    methods: dict[str, float]
    up_p: tuple[float, float, float]
    accel_magnitude_g: float
    gyro_fit: HarmonicFit = field(repr=False)
    accel_fit: HarmonicFit = field(repr=False)

    @property
    def gyro_residual_rms_dph(self) -> dict[str, float]:
        return {k: float(v[0]) for k, v in self.gyro_fit.residual_rms.items()}

    @property
    def accel_residual_rms_g(self) -> dict[str, float]:
        return {k: float(v[0]) for k, v in self.accel_fit.residual_rms.items()}

    def as_dict(self) -> dict:
        """JSON-ready summary (floats and lists; NaN, e.g. σ at n = 3, becomes None)."""
        g, a = self.gyro_fit, self.accel_fit
        return _json_safe(
            {
                "method": self.method,
                "heading_deg": self.heading_deg,
                "heading_std_deg": self.heading_std_deg,
                "pitch_deg": self.pitch_deg,
                "roll_deg": self.roll_deg,
                "tilt_deg": self.tilt_deg,
                "tilt_azimuth_deg": self.tilt_azimuth_deg,
                "latitude_deg": self.latitude_deg,
                "n_positions": self.n_positions,
                "methods_heading_deg": dict(self.methods),
                "accel_magnitude_g": self.accel_magnitude_g,
                "gyro_fit": {
                    "names": list(g.names),
                    "coefficients_dph": g.coefficients[0].tolist(),
                    "covariance_dph2": g.covariance[0].tolist(),
                    "residual_rms_dph": self.gyro_residual_rms_dph,
                    "noise": g.noise,
                    "dof": g.dof,
                },
                "accel_fit": {
                    "names": list(a.names),
                    "coefficients_g": a.coefficients[0].tolist(),
                    "residual_rms_g": self.accel_residual_rms_g,
                    "noise": a.noise,
                },
            }
        )


def _json_safe(obj):
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _as_batch(x, n: int, name: str) -> tuple[np.ndarray, int]:
    """(T, n, k) array and its axis count k: 1 (b-y), 2 (b-x, b-y) or 3 (x, y, z)."""
    arr = np.asarray(x, dtype=float)
    if arr.ndim >= 2 and arr.shape[-1] in (2, 3) and arr.shape[-2] == n:
        k = arr.shape[-1]
        arr = arr.reshape((-1, n, k))
    elif arr.ndim >= 1 and arr.shape[-1] == n:
        k, arr = 1, arr.reshape((-1, n, 1))
    else:
        raise InputError(
            f"{name}: shape {np.shape(x)} does not match {n} table angles; "
            f"expected ({n},), ({n}, 2) or ({n}, 3)"
        )
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or inf; drop or re-measure those positions")
    return arr, k


def _std_for(std, n: int, k: int, name: str) -> np.ndarray | None:
    if std is None:
        return None
    sd = np.asarray(std, dtype=float)
    want = (n, k) if k > 1 else (n,)
    if sd.shape != want:
        raise InputError(f"{name}: shape {sd.shape}, expected {want} (same as the means)")
    return sd[:, :2] if k > 1 else sd[:, None]


def _up_vector(fx, fy, g_local_g: float) -> np.ndarray:
    """u^p = [f_x, f_y, √(g² − f_x² − f_y²)] / g from the fitted platform specific force (eq 9).

    With a_A = f_y, b_A = −f_x (eq 5) the tilt acos(u_z) is eq 9's asin(√(a_A² + b_A²)/g).

    Only the modulated x/y components enter (their biases are fitted away, eq 5); the b-z
    accelerometer, whose bias cannot be separated, is used only to check |f| and that z is up.
    """
    fz = np.sqrt(np.clip(g_local_g**2 - fx**2 - fy**2, 0.0, None))
    return np.stack(np.broadcast_arrays(fx, fy, fz), axis=-1) / g_local_g


def _heading_std_rad(method, params, cov, g_local_g, omega_h) -> np.ndarray:
    """√(Jᵀ Σ J), J by central differences of the method's heading over (w_x, w_y, f_x, f_y)."""
    steps = np.array([1e-4 * OMEGA_EARTH_RAD_S, 1e-4 * OMEGA_EARTH_RAD_S, 1e-6, 1e-6])
    jac = np.empty(params.shape)
    for j in range(4):
        hi, lo = params.copy(), params.copy()
        hi[..., j] += steps[j]
        lo[..., j] -= steps[j]
        d = METHODS[method](hi[..., 0], hi[..., 1], _up_vector(hi[..., 2], hi[..., 3], g_local_g), omega_h)
        d = d - METHODS[method](
            lo[..., 0], lo[..., 1], _up_vector(lo[..., 2], lo[..., 3], g_local_g), omega_h
        )
        jac[..., j] = (np.mod(d + np.pi, 2.0 * np.pi) - np.pi) / (2.0 * steps[j])
    return np.sqrt(np.einsum("...i,...ij,...j->...", jac, cov, jac))


def _checked_method_latitude_angles(
    method: str, latitude_deg: float, table_angle_deg
) -> tuple[float, np.ndarray]:
    """The method's name, the latitude inside MAX_ABS_LATITUDE_DEG and ≥ 3 finite table angles."""
    if method not in METHODS:
        raise InputError(f"method must be one of {list(METHODS)}, got {method!r}")
    lat = float(latitude_deg)
    if not np.isfinite(lat) or abs(lat) > MAX_ABS_LATITUDE_DEG:
        raise InputError(
            f"latitude_deg = {latitude_deg}: gyro north finding needs |latitude| ≤ {MAX_ABS_LATITUDE_DEG}° "
            "(the horizontal Earth rate vanishes at the poles)"
        )
    alpha_deg = np.asarray(table_angle_deg, dtype=float)
    if alpha_deg.ndim != 1 or alpha_deg.size < 3:
        raise InputError(f"table_angle_deg: need at least 3 table positions, got shape {alpha_deg.shape}")
    if not np.all(np.isfinite(alpha_deg)):
        raise InputError("table_angle_deg: contains NaN or inf")
    return lat, alpha_deg


def _checked_gravity(fx: np.ndarray, fy: np.ndarray, fz: np.ndarray | None, g_local_g: float,
                     accel_tolerance: float) -> np.ndarray:
    """|f| per trial [g] — the accelerometer means must be in g and the base still: with a z axis
    |f| within `accel_tolerance` of the local gravity and z up; without one, the horizontal part
    below gravity (NaN is returned for |f| then: it is not measured)."""
    if fz is not None:
        mag = np.sqrt(fx**2 + fy**2 + fz**2)
        bad = np.abs(mag / g_local_g - 1.0) > accel_tolerance
        if np.any(bad):
            m = float(mag[np.argmax(bad)])
            raise InputError(
                f"accel_g: |f| = {m:.4g} g is far from the local gravity {g_local_g:.5f} g ("
                f"{accel_tolerance:.0%}); pass accelerometer means in g (not m/s²) and keep the base still"
            )
        if np.any(fz <= 0.0):
            raise InputError("accel_g: the z axis reads negative gravity; mount the instrument z-up")
        return mag
    horizontal = np.sqrt(fx**2 + fy**2)
    if np.any(horizontal >= g_local_g):
        raise InputError(
            f"accel_g: the horizontal specific force is {float(horizontal.max()):.4g} g, not below the local "
            f"gravity {g_local_g:.5f} g; pass the means in g and keep the base still"
        )
    return np.full(np.shape(fx), np.nan)


def _checked_tilt_rad(up: np.ndarray, tilt_limit_deg: float) -> np.ndarray:
    """The table's tilt ε = arccos(up_z) per trial, refused above `tilt_limit_deg`."""
    tilt = np.arccos(np.clip(up[..., 2], -1.0, 1.0))
    if np.any(np.rad2deg(tilt) > tilt_limit_deg):
        raise InputError(
            f"accel_g: table tilt {np.rad2deg(tilt.max()):.2f}° exceeds the limit {tilt_limit_deg}°; "
            "level the base (or raise tilt_limit_deg)"
        )
    return tilt


def _check_earth_rate(wx: np.ndarray, wy: np.ndarray, up: np.ndarray, lat_deg: float) -> None:
    """The fitted horizontal rate must be near Ωe·cos L (0.05…3×): else the means are not in deg/h
    or the base moved."""
    omega_n = OMEGA_EARTH_RAD_S * np.cos(np.deg2rad(lat_deg))
    omega_h = OMEGA_EARTH_RAD_S * np.sin(np.deg2rad(lat_deg))
    horiz = np.hypot(wx - omega_h * up[..., 0], wy - omega_h * up[..., 1]) / omega_n
    off = (horiz > 3.0) | (horiz < 0.05)
    if np.any(off):
        raise InputError(
            f"gyro_dph: the fitted horizontal rate is {float(horiz[np.argmax(off)]):.3g} × the Earth rate's "
            f"north component {omega_n / DPH:.3f} °/h; pass the gyro means in deg/h and keep the base still"
        )


def solve_batch(
    table_angle_deg,
    gyro_dph,
    accel_g,
    latitude_deg: float,
    method: str = "exact",
    *,
    gyro_std_dph=None,
    accel_std_g=None,
    sample_count=None,
    sample_times_s=None,
    bias_model: str = "constant",
    height_m: float = 0.0,
    tilt_limit_deg: float = DEFAULT_TILT_LIMIT_DEG,
    accel_tolerance: float = DEFAULT_ACCEL_TOLERANCE,
) -> BatchSolution:
    """Solve T finds that share the table angles: gyro_dph (T, n) or (T, n, 3), likewise accel_g.

    Same arguments as :func:`solve_heading`; leading batch dimension on the means only.
    """
    lat, alpha_deg = _checked_method_latitude_angles(method, latitude_deg, table_angle_deg)
    n = alpha_deg.size
    alpha = np.deg2rad(alpha_deg)
    gyro, gyro_k = _as_batch(gyro_dph, n, "gyro_dph")
    accel, accel_k = _as_batch(accel_g, n, "accel_g")
    gyro2, accel2, accel3 = gyro_k >= 2, accel_k >= 2, accel_k == 3
    if gyro.shape[0] != accel.shape[0]:
        raise InputError(f"gyro_dph has {gyro.shape[0]} trials but accel_g has {accel.shape[0]}")
    if sample_times_s is not None:
        sample_times_s = np.asarray(sample_times_s, dtype=float)
        if sample_times_s.shape != (n,) or not np.all(np.isfinite(sample_times_s)):
            raise InputError(f"sample_times_s: expected {n} finite mid-dwell times in seconds")

    g_axes = ("x", "y") if gyro2 else ("y",)
    gyro_fit = fit_harmonic(
        alpha, gyro[..., :2] if gyro2 else gyro, g_axes,
        std=_std_for(gyro_std_dph, n, gyro_k, "gyro_std_dph"), sample_count=sample_count,
        time_s=sample_times_s, bias_model=bias_model, what="gyro fit",
    )  # fmt: skip
    accel_fit = fit_harmonic(
        alpha, accel[..., :2] if accel2 else accel, ("x", "y") if accel2 else ("y",),
        std=_std_for(accel_std_g, n, accel_k, "accel_std_g"), sample_count=sample_count,
        what="accelerometer fit",
    )  # fmt: skip

    g_local_g = float(normal_gravity_m_s2(lat, height_m)) / STANDARD_GRAVITY_M_S2
    fx, fy = accel_fit.coef("v_x"), accel_fit.coef("v_y")
    trials = gyro.shape[0]
    cov = np.zeros((trials, 4, 4))
    cov[:, :2, :2] = gyro_fit.covariance[:, :2, :2] * DPH**2
    cov[:, 2:4, 2:4] = accel_fit.covariance[:, :2, :2]
    fz = accel[..., 2].mean(axis=-1) if accel3 else None
    mag = _checked_gravity(fx, fy, fz, g_local_g, accel_tolerance)
    up = _up_vector(fx, fy, g_local_g)
    pitch, roll = pitch_roll_from_up(up)
    tilt = _checked_tilt_rad(up, tilt_limit_deg)
    omega_h = OMEGA_EARTH_RAD_S * np.sin(np.deg2rad(lat))
    wx, wy = gyro_fit.coef("v_x") * DPH, gyro_fit.coef("v_y") * DPH
    _check_earth_rate(wx, wy, up, lat)

    headings = {name: np.rad2deg(fn(wx, wy, up, omega_h)) for name, fn in METHODS.items()}
    psi = np.deg2rad(headings[method])
    std = _heading_std_rad(method, np.stack([wx, wy, fx, fy], axis=-1), cov, g_local_g, omega_h)
    _, tilt_az = tilt_and_azimuth(psi, pitch, roll)
    return BatchSolution(
        method=method,
        heading_deg=headings[method],
        heading_std_deg=np.rad2deg(std),
        pitch_deg=np.rad2deg(pitch),
        roll_deg=np.rad2deg(roll),
        tilt_deg=np.rad2deg(tilt),
        tilt_azimuth_deg=np.rad2deg(tilt_az),
        methods=headings,
        up_p=up,
        accel_magnitude_g=mag,
        gyro_fit=gyro_fit,
        accel_fit=accel_fit,
    )


def solve_heading(
    table_angle_deg,
    gyro_dph,
    accel_g,
    latitude_deg: float,
    method: str = "exact",
    *,
    gyro_std_dph=None,
    accel_std_g=None,
    sample_count=None,
    sample_times_s=None,
    bias_model: str = "constant",
    height_m: float = 0.0,
    tilt_limit_deg: float = DEFAULT_TILT_LIMIT_DEG,
    accel_tolerance: float = DEFAULT_ACCEL_TOLERANCE,
) -> HeadingSolution:
    """Heading, tilt and 1σ of one turntable north find.

    table_angle_deg (n,): measured (encoder) table angles α, any n ≥ 3 that separates cos/sin.
    gyro_dph: mean body rate per position [deg/h], (n,) for one gyro on b-y (the paper's case)
    or (n, 3) for x, y, z (x and y fitted jointly; z unused; (n, 2) for x, y also works).
    accel_g: mean specific force [g], (n,) for one accelerometer on b-y, (n, 2) or (n, 3) (z only
    checks |f| against the local gravity). method: "exact" (default), "coordinate_transform"
    (eq 3), "vector" (eq 10), "eq11", "uncompensated" (eq 8); every method's heading is in
    `.methods`.
    gyro_std_dph / accel_std_g: standard error of each position mean (same shape as the means);
    given, the fits are weighted by them and the 1σ comes from this noise. Without them the 1σ
    comes from the residuals, which at n = 4 with one gyro has 1 degree of freedom (σ̂ scatters
    by ±70 %) and is NaN at n = 3. sample_count (n,): weights when the standard errors are
    unknown. bias_model: "constant" (eq 4), or "linear"/"quadratic" drift in time (needs
    sample_times_s, each position's mid-dwell time; default: equal spacing in the given order)
    — use it when the gyro bias wanders during the revolution.
    Raises northfinder.errors.InputError on input that cannot give a meaningful heading.
    """
    b = solve_batch(
        table_angle_deg, gyro_dph, accel_g, latitude_deg, method,
        gyro_std_dph=gyro_std_dph, accel_std_g=accel_std_g, sample_count=sample_count,
        sample_times_s=sample_times_s, bias_model=bias_model, height_m=height_m,
        tilt_limit_deg=tilt_limit_deg, accel_tolerance=accel_tolerance,
    )  # fmt: skip
    if b.heading_deg.shape[0] != 1:
        raise InputError("solve_heading takes one find; use solve_batch for a batch of trials")
    return HeadingSolution(
        heading_deg=float(b.heading_deg[0]),
        heading_std_deg=float(b.heading_std_deg[0]),
        pitch_deg=float(b.pitch_deg[0]),
        roll_deg=float(b.roll_deg[0]),
        tilt_deg=float(b.tilt_deg[0]),
        tilt_azimuth_deg=float(b.tilt_azimuth_deg[0]),
        method=method,
        latitude_deg=float(latitude_deg),
        n_positions=int(np.size(table_angle_deg)),
        methods={k: float(v[0]) for k, v in b.methods.items()},
        up_p=tuple(float(x) for x in b.up_p[0]),
        accel_magnitude_g=float(b.accel_magnitude_g[0]),
        gyro_fit=b.gyro_fit,
        accel_fit=b.accel_fit,
    )


def solve_all_methods(table_angle_deg, gyro_dph, accel_g, latitude_deg: float, **kwargs) -> dict[str, float]:
    """Every method's heading [deg] for one find (the CLI prints all five)."""
    return solve_heading(table_angle_deg, gyro_dph, accel_g, latitude_deg, **kwargs).methods


def heading_with_gyro_fit(
    sol: HeadingSolution, gyro_fit: HarmonicFit, *, height_m: float = 0.0
) -> tuple[float, float, dict[str, float]]:
    """Heading [deg], 1σ [deg] and every method's heading from another fit of the horizontal Earth
    rate (v_x, v_y in deg/h with its covariance, e.g. the per-sample motion fit) and the tilt of
    `sol` (its accelerometer fit): the same methods and the same 4×4 propagation as solve_batch,
    with the gyro block taken from `gyro_fit`."""
    lat_deg = float(sol.latitude_deg)
    g_local_g = float(normal_gravity_m_s2(lat_deg, height_m)) / STANDARD_GRAVITY_M_S2
    acc = sol.accel_fit
    fx, fy = acc.coef("v_x"), acc.coef("v_y")
    wx, wy = gyro_fit.coef("v_x") * DPH, gyro_fit.coef("v_y") * DPH
    cov = np.zeros((wx.shape[0], 4, 4))
    cov[:, :2, :2] = gyro_fit.covariance[:, :2, :2] * DPH**2
    cov[:, 2:4, 2:4] = acc.covariance[:, :2, :2]
    up = _up_vector(fx, fy, g_local_g)
    omega_h = OMEGA_EARTH_RAD_S * np.sin(np.deg2rad(lat_deg))
    headings = {name: float(np.rad2deg(fn(wx, wy, up, omega_h))[0]) for name, fn in METHODS.items()}
    std = _heading_std_rad(sol.method, np.stack([wx, wy, fx, fy], axis=-1), cov, g_local_g, omega_h)
    return headings[sol.method], float(np.rad2deg(std)[0]), headings
