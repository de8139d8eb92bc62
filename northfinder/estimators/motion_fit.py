"""Per-sample harmonic fit: every gyro sample with its own table angle, moving or at rest.

docs/estimators.md §10 (equations M1–M4). Stop-and-go uses the dwell means only; here the
samples taken while the table turns and settles are fitted too. Their table angle comes from
the z gyro integrated between two encoder readings at rest, the integral pinned to the encoder
at both ends (M1). The horizontal gyros then read (M2)

    x(t) = R_x + v_x·cos α + v_y·sin α + δ_x·ω(t)
    y(t) = R_y − v_x·sin α + v_y·cos α + δ_y·ω(t)

where ω is the table rate and δ the input axis's misalignment toward the table axis. The
misalignment is estimated (`terms=("misalignment",)`) or, with whole revolutions in both
directions, cancels (its column is orthogonal to every other one, M3). Pure numpy.
"""

from __future__ import annotations

import numpy as np

from northfinder.constants import DPH, OMEGA_EARTH_RAD_S
from northfinder.errors import InputError
from northfinder.estimators.harmonic import HarmonicFit
from northfinder.estimators.methods import METHODS

MOTION_TERMS = ("misalignment", "wobble", "rate_squared")
"""misalignment: δ·ω per axis (odd in ω); wobble: the stage bearing's twice-per-turn tilt, whose rate
w·ẇ reads in b as ω·(−sin(α+φ), cos(α+φ)) — two coefficients shared by x and y (eq M2b; the
once-per-turn wobble reads as a constant ω on b-y, inside δ_y); rate_squared: c·ω² per axis (even:
centripetal g-sensitivity, does not cancel by reversing)."""

RUN_TERMS = ("misalignment", "wobble")
"""The terms the find's per-sample fit estimates (and the plan model predicts with)."""

MAX_CONDITION = 1.0e4
"""Largest accepted condition number of the column-normalised per-sample design."""


def _rest_segments(rest: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index ranges of consecutive rest samples."""
    edges = np.flatnonzero(np.diff(np.r_[0, rest.astype(np.int8), 0]))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def table_angle_from_z(z_dph, dt_s: float, rest_encoder_deg) -> tuple[np.ndarray, np.ndarray]:
    """Table angle α [deg] and rate ω [deg/s] at every sample (eq M1).

    `z_dph` (m,): the b-z gyro; `rest_encoder_deg` (m,): the encoder reading at rest, NaN while the
    table moves. At rest α is the encoder; the z bias b_z (Earth's vertical rate + gyro bias) is
    the mean z over the rest samples; through a move α(t) = α_0 + s·∫(z − b_z)dt (at each sample's
    middle: a sample is the rate averaged over its interval) with
    s = (α_1 − α_0)/∫_move(z − b_z)dt, so the integral lands on the encoder at both ends (s takes
    out the z gyro's scale factor and its asymmetry, move by move). Rest samples get ω = 0.
    """
    z = np.asarray(z_dph, dtype=float) / 3600.0  # deg/s
    enc = np.asarray(rest_encoder_deg, dtype=float)
    if z.shape != enc.shape or z.ndim != 1:
        raise InputError(f"z gyro {z.shape} and encoder {enc.shape} must be 1-D of the same length")
    rest = np.isfinite(enc)
    if not rest[0] or not rest[-1]:
        raise InputError("motion samples: the run must start and end at rest with an encoder reading")
    alpha, omega = enc.copy(), np.zeros_like(z)
    b_z = float(np.mean(z[rest]))
    segs = _rest_segments(rest)
    for (_, end0), (start1, _) in zip(segs[:-1], segs[1:], strict=True):
        rate = z[end0:start1] - b_z
        ends = np.cumsum(rate) * dt_s  # turned at each sample's end (a sample integrates its interval)
        a0, a1 = enc[end0 - 1], enc[start1]
        if abs(ends[-1]) < 1e-9:
            raise InputError(
                f"motion samples {end0}…{start1}: the z gyro shows no turn; is z the table axis?"
            )
        s = (a1 - a0) / ends[-1]
        alpha[end0:start1] = a0 + s * (ends - 0.5 * rate * dt_s)  # at each sample's middle
        omega[end0:start1] = s * rate
    return alpha, omega


def motion_design(
    alpha_deg, omega_dps, axes: tuple[str, ...], terms: tuple[str, ...] = ("misalignment",)
) -> tuple[np.ndarray, tuple[str, ...]]:
    """Per-sample design matrix (eq M2), rows axis-major, and its parameter names.

    Columns: v_x, v_y (the platform-frame Earth rate, paper eq 4 per sample), R_<axis> per axis,
    then per term and axis d_<axis> (ω [deg/s], coefficient δ in deg/h per deg/s) or
    q_<axis> (ω² [(deg/s)²]), then w_c, w_s (the wobble, shared; deg/h per deg/s).
    """
    unknown = set(terms) - set(MOTION_TERMS)
    if unknown:
        raise InputError(f"motion terms must be among {list(MOTION_TERMS)}, got {sorted(unknown)}")
    a = np.deg2rad(np.asarray(alpha_deg, dtype=float))
    w = np.asarray(omega_dps, dtype=float)
    m = a.size
    c, s = np.cos(a), np.sin(a)
    names = ["v_x", "v_y"] + [f"R_{ax}" for ax in axes]
    cols = {"misalignment": ("d", w), "rate_squared": ("q", w**2)}
    per_axis = [t for t in terms if t in cols]
    for t in per_axis:
        names += [f"{cols[t][0]}_{ax}" for ax in axes]
    if "wobble" in terms:
        names += ["w_c", "w_s"]
    blocks = []
    for ax in axes:
        block = np.zeros((m, len(names)))
        block[:, 0], block[:, 1] = (c, s) if ax == "x" else (-s, c)
        block[:, names.index(f"R_{ax}")] = 1.0
        for t in per_axis:
            block[:, names.index(f"{cols[t][0]}_{ax}")] = cols[t][1]
        if "wobble" in terms:  # eq M2b: x: −ω·sin(α+φ), y: ω·cos(α+φ) = w_c·(…) + w_s·(…)
            block[:, names.index("w_c")] = -w * s if ax == "x" else w * c
            block[:, names.index("w_s")] = -w * c if ax == "x" else -w * s
        blocks.append(block)
    return np.vstack(blocks), tuple(names)


def _check_condition(a_mat: np.ndarray, names: tuple[str, ...]) -> None:
    """One line when the samples cannot separate the parameters (e.g. motion terms, no motion)."""
    norms = np.linalg.norm(a_mat, axis=0)
    if np.any(norms == 0.0):
        raise InputError(
            f"motion fit: column {names[int(np.argmin(norms))]} is all zero (no motion in the samples?); "
            "drop the motion terms"
        )
    cond = float(np.linalg.cond(a_mat / norms))
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise InputError(
            f"motion fit: the samples cannot separate {', '.join(names)} (condition {cond:.3g}); "
            "turn through whole revolutions or more positions"
        )


def fit_motion(
    alpha_deg,
    omega_dps,
    gyro_dph,
    axes: tuple[str, ...] = ("x", "y"),
    *,
    sample_std_dph: float | None = None,
    terms: tuple[str, ...] = ("misalignment",),
) -> HarmonicFit:
    """Least squares of eq M2 over every sample, batched over trials (eq M3).

    gyro_dph (T, m, k) or (m, k) with k = len(axes) (column j is axis axes[j]), one row per
    sample at alpha_deg (m,), omega_dps (m,). X̂ = (AᵀA)⁻¹AᵀY (white noise: equal weights);
    with `sample_std_dph` (σ of one sample) Cov = σ²(AᵀA)⁻¹ (noise "given"), else from the
    residuals. terms=() is the fit that ignores what motion adds.
    """
    y = np.asarray(gyro_dph, dtype=float)
    if y.ndim == 2:
        y = y[None]
    trials, m, k = y.shape
    if k != len(axes) or np.size(alpha_deg) != m or np.size(omega_dps) != m:
        raise InputError(
            f"motion fit: gyro {y.shape[1:]} does not match {np.size(alpha_deg)} angles × {axes}"
        )
    if not np.all(np.isfinite(y)):
        raise InputError("motion fit: gyro samples contain NaN or inf")
    a_mat, names = motion_design(alpha_deg, omega_dps, axes, terms)
    _check_condition(a_mat, names)
    normal_inv = np.linalg.inv(a_mat.T @ a_mat)
    pinv = normal_inv @ a_mat.T
    rows = y.transpose(0, 2, 1).reshape(trials, k * m)
    coef = rows @ pinv.T
    resid = rows - coef @ a_mat.T
    dof = k * m - len(names)
    rms = {ax: np.sqrt(np.mean(resid[:, j * m : (j + 1) * m] ** 2, axis=-1)) for j, ax in enumerate(axes)}
    if sample_std_dph is not None:
        cov, noise = (
            np.broadcast_to(sample_std_dph**2 * normal_inv, (trials,) + normal_inv.shape).copy(),
            "given",
        )
    else:
        s2 = np.sum(resid**2, axis=-1) / dof
        cov, noise = s2[:, None, None] * normal_inv, "residuals"
    return HarmonicFit(names, coef, cov, rms, dof, noise)


def heading_from_rates(v_x_dph, v_y_dph, up_p, latitude_deg: float, cov_dph2=None):
    """Heading [deg, 0…360) of the exact method (docs/estimators.md §4) from fitted v_x, v_y,
    and its 1σ [deg] from their 2×2 covariance (eq M4: σψ² = ∇ψᵀ Σ ∇ψ, ∇ψ by central
    differences; the up vector u^p (…, 3) is taken as exact)."""
    lat = np.deg2rad(latitude_deg)
    omega_h = OMEGA_EARTH_RAD_S * np.sin(lat)
    wx, wy = np.asarray(v_x_dph, dtype=float) * DPH, np.asarray(v_y_dph, dtype=float) * DPH
    up = np.asarray(up_p, dtype=float)
    psi = METHODS["exact"](wx, wy, up, omega_h)
    if cov_dph2 is None:
        return np.rad2deg(psi), None
    h = 1e-4 * OMEGA_EARTH_RAD_S
    grads = []
    for dx, dy in ((h, 0.0), (0.0, h)):
        d = METHODS["exact"](wx + dx, wy + dy, up, omega_h) - METHODS["exact"](wx - dx, wy - dy, up, omega_h)
        grads.append((np.mod(d + np.pi, 2 * np.pi) - np.pi) / (2 * h) * DPH)  # rad per deg/h
    g = np.stack(grads, axis=-1)
    var = np.einsum("...i,...ij,...j->...", g, np.asarray(cov_dph2)[..., :2, :2], g)
    return np.rad2deg(psi), np.rad2deg(np.sqrt(var))


def place_samples(
    sample_index, gyro_dph, dwells, rate_hz: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, int]]:
    """Every gyro sample from the first rest's start to the last rest's end with its table angle
    and rate (eq M1 per pair of dwells), for the per-sample fit.

    `sample_index` (m,) strictly increasing device indices, `gyro_dph` (m, 3) with a z gyro;
    `dwells`: (first_index, last_index, encoder_deg) of each dwell at rest, in time order. The
    samples between two dwells are placed by the z gyro pinned to the two encoder readings; a
    stretch with a lost or invalid (NaN) sample cannot be integrated and is left out (its two
    dwells still count). Returns alpha_deg, omega_dps, gyro_dph of the kept samples and counts
    {"rest", "motion", "stretches_dropped"}.
    """
    idx = np.asarray(sample_index, dtype=np.int64)
    g = np.asarray(gyro_dph, dtype=float)
    if g.ndim != 2 or g.shape != (idx.size, 3):
        raise InputError(f"place_samples: gyro {g.shape} must be ({idx.size}, 3)")
    spans = sorted((int(a), int(b), float(e)) for a, b, e in dwells)
    if len(spans) < 2:
        raise InputError("motion samples need at least two dwells")
    alphas, omegas, gyros = [], [], []
    counts = {"rest": 0, "motion": 0, "stretches_dropped": 0}

    finite = np.all(np.isfinite(g), axis=1)

    def take(lo: int, hi: int, valid_only: bool = True) -> np.ndarray:
        sel = (idx >= lo) & (idx <= hi)
        return np.flatnonzero(sel & finite if valid_only else sel)

    for k, (a0, b0, e0) in enumerate(spans):
        rest = take(a0, b0)
        alphas.append(np.full(rest.size, e0))
        omegas.append(np.zeros(rest.size))
        gyros.append(g[rest])
        counts["rest"] += rest.size
        if k + 1 == len(spans):
            break
        a1, b1, e1 = spans[k + 1]
        between = take(b0 + 1, a1 - 1, valid_only=False)
        if between.size == 0:
            continue
        complete = between.size == a1 - b0 - 1 and bool(np.all(finite[between]))
        rest_next = take(a1, b1)
        if not complete or rest.size == 0 or rest_next.size == 0:
            counts["stretches_dropped"] += 1
            continue
        sel = np.concatenate([rest, between, rest_next])
        enc = np.full(sel.size, np.nan)
        enc[: rest.size], enc[rest.size + between.size :] = e0, e1
        alpha, omega = table_angle_from_z(g[sel, 2], 1.0 / rate_hz, enc)
        alphas.append(alpha[rest.size : rest.size + between.size])
        omegas.append(omega[rest.size : rest.size + between.size])
        gyros.append(g[between])
        counts["motion"] += between.size
    cat = np.concatenate
    return cat(alphas), cat(omegas), cat(gyros), counts


DISTURBED_K = 6.0
"""A stretch between dwells is left out when its mean squared residual exceeds the dwells' by more
than this many standard deviations of a mean of squares of white noise (√(2/n) relative)."""


def fit_motion_screened(
    alpha_deg, omega_dps, gyro_dph, axes: tuple[str, ...] = ("x", "y"), *,
    terms: tuple[str, ...] = RUN_TERMS, k_sigma: float = DISTURBED_K,
) -> tuple[HarmonicFit, np.ndarray, int]:
    """fit_motion with every stretch between dwells screened for what the model lacks (a knock on
    the table while it turned: the dwells are re-measured for it, the motion samples are not).

    Stretches are the runs of samples with ω ≠ 0 (place_samples gives rest samples ω = 0 exactly).
    The fit is repeated leaving out the worst stretch while its mean squared residual (summed over
    axes) is above the rest samples' by more than k_sigma·√(2/(n·k)) relative (n samples, k axes:
    the spread of a mean of squares of white noise) — one at a time, since a big disturbance
    drags the whole fit and raises every stretch's residual. Returns (fit, samples kept, stretches
    left out); InputError if no motion sample is left."""
    alpha = np.asarray(alpha_deg, dtype=float)
    w = np.asarray(omega_dps, dtype=float)
    y = np.asarray(gyro_dph, dtype=float)
    keep = np.ones(w.size, dtype=bool)
    rest = w == 0.0
    label = np.cumsum(np.r_[0, np.diff(rest.astype(np.int8)) != 0])
    a_mat = motion_design(alpha, w, axes, terms)[0] if np.any(rest) else None
    dropped = 0
    while True:
        fit = fit_motion(alpha[keep], w[keep], y[keep], axes, terms=terms)
        if a_mat is None:
            return fit, keep, dropped
        resid = (y.T.reshape(-1) - a_mat @ fit.coefficients[0]).reshape(len(axes), w.size)
        r2 = np.sum(resid**2, axis=0)
        floor = float(np.mean(r2[rest]))
        worst, worst_excess = None, 0.0
        for k in np.unique(label[keep & ~rest]):
            sel = label == k
            n = int(sel.sum())
            excess = (np.mean(r2[sel]) / floor - 1.0) / (k_sigma * np.sqrt(2.0 / (n * len(axes))))
            if excess > max(1.0, worst_excess):
                worst, worst_excess = sel, excess
        if worst is None:
            return fit, keep, dropped
        keep &= ~worst
        dropped += 1


# --------------------------------------------------------------------------------------------
# The same fit from the samples as they arrive: memory flat in run length (issue 27, item 5)

_CHUNK_ROWS = 8192
"""Rows folded into a stretch's triangular factor at a time (bounds the transient design)."""


def _fold(r_mat: np.ndarray | None, rows: np.ndarray) -> np.ndarray:
    """The triangular factor R of [r_mat; rows] (QR, R only): RᵀR = r_matᵀr_mat + rowsᵀrows."""
    stacked = rows if r_mat is None else np.vstack([r_mat, rows])
    return np.linalg.qr(stacked, mode="r")


class _Stretch:
    """One rest or motion stretch as the fit sees it: per axis the triangular factor R_j of its
    rows [A_j | y_j] (the design's axis-j block and that axis's gyro), and its sample count. Then
    ‖A_j·x − y_j‖² = ‖R_j·[x; −1]‖² for any x — residuals need no samples."""

    __slots__ = ("factors", "motion", "n")

    def __init__(self, motion: bool, n_axes: int) -> None:
        self.motion = motion
        self.n = 0
        self.factors: list[np.ndarray | None] = [None] * n_axes

    def add(self, alpha_deg, omega_dps, gyro_dph, axes, terms) -> None:
        for lo in range(0, len(alpha_deg), _CHUNK_ROWS):
            hi = lo + _CHUNK_ROWS
            a_mat, _ = motion_design(alpha_deg[lo:hi], omega_dps[lo:hi], axes, terms)
            m = min(hi, len(alpha_deg)) - lo
            for j in range(len(axes)):
                rows = np.column_stack([a_mat[j * m : (j + 1) * m], gyro_dph[lo:hi, j]])
                self.factors[j] = _fold(self.factors[j], rows)
            self.n += m

    def add_rest(self, encoder_deg: float, gyro_dph, axes, terms) -> None:
        """A rest's rows, all with one design row a (α = encoder, ω = 0), folded without the rows:
        for rows [a, y_i], i = 1…n, the two rows √n·[a, ȳ] and [0, √Σ(y_i − ȳ)²] have the same
        RᵀR (n·aaᵀ, a·Σy, Σy²), so ‖A·x − y‖² = n(a·x − ȳ)² + Σ(y_i − ȳ)² exactly; the centred sum
        is the stable two-pass one. O(n) instead of a QR of n rows (the dwell is most of a run)."""
        g = np.asarray(gyro_dph, dtype=float)
        n = g.shape[0]
        if n == 0:
            return
        a_mat, _ = motion_design(np.array([float(encoder_deg)]), np.zeros(1), axes, terms)
        for j in range(len(axes)):
            y = g[:, j]
            mean = float(np.mean(y))
            spread = float(np.sqrt(np.sum((y - mean) ** 2)))
            rows = np.zeros((2, a_mat.shape[1] + 1))
            rows[0, :-1], rows[0, -1] = np.sqrt(n) * a_mat[j], np.sqrt(n) * mean
            rows[1, -1] = spread
            self.factors[j] = _fold(self.factors[j], rows)
        self.n += n

    def sq_residual(self, x_aug: np.ndarray) -> np.ndarray:
        """Σ over the stretch's samples of the squared residual at coefficients x, per axis."""
        return np.array([float(np.sum((f @ x_aug) ** 2)) if f is not None else 0.0 for f in self.factors])


class MotionFitAccumulator:
    """place_samples + fit_motion_screened fed the run as it arrives, holding per rest or motion
    stretch only a small triangular factor (docs/estimators.md §10; issue 27 item 5).

    `add_samples(sample_index, gyro_dph)` takes the IMU stream in time order (any chunking; gyro
    (n, 3) with the z gyro), `add_dwell(first_index, last_index, encoder_deg)` each dwell at rest
    once its samples have arrived, in time order. Held at any moment: the samples since the last
    dwell's end (one move and the next dwell) and the last dwell's rest samples (the next stretch
    is placed with them, eq M1) — bounded by the plan's step, not by the run's length — plus, per
    stretch and axis, R (p+1)² floats (p = 8 for RUN_TERMS on x, y: 81 floats).

    The samples are placed by the same calls as place_samples (table_angle_from_z on the same
    arrays), so every sample's α, ω is bit-identical. The fit is least squares through the QR
    factors rather than the batch's (AᵀA)⁻¹Aᵀy: coefficients, covariance and residuals agree with
    fit_motion_screened to rounding (relative ~1e-12 for the design's condition ≤ MAX_CONDITION;
    tests/test_motion_accumulator.py), and the screening drops the same stretches.
    """

    def __init__(self, rate_hz: float, axes: tuple[str, ...] = ("x", "y"),
                 terms: tuple[str, ...] = RUN_TERMS) -> None:
        self.rate_hz = float(rate_hz)
        self.axes = tuple(axes)
        self.terms = tuple(terms)
        self.names = motion_design(np.zeros(1), np.zeros(1), self.axes, self.terms)[1]
        self.stretches: list[_Stretch] = []
        self.counts = {"rest": 0, "motion": 0, "stretches_dropped": 0}
        self._pending_idx: list[np.ndarray] = []
        self._pending_gyro: list[np.ndarray] = []
        self._last_index: int | None = None
        self._dwell: tuple[int, int, float, np.ndarray] | None = None  # last dwell: a, b, enc, rest gyro

    def add_samples(self, sample_index, gyro_dph) -> None:
        idx = np.asarray(sample_index, dtype=np.int64)
        g = np.asarray(gyro_dph, dtype=float)
        if g.ndim != 2 or g.shape != (idx.size, 3):
            raise InputError(f"motion samples: gyro {g.shape} must be ({idx.size}, 3)")
        if idx.size == 0:
            return
        first = int(idx[0])
        if np.any(np.diff(idx) <= 0) or (self._last_index is not None and first <= self._last_index):
            raise InputError("motion samples: sample indices must increase")
        self._last_index = int(idx[-1])
        self._pending_idx.append(idx.copy())
        self._pending_gyro.append(g.copy())

    def _held(self) -> tuple[np.ndarray, np.ndarray]:
        if not self._pending_idx:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        idx, g = np.concatenate(self._pending_idx), np.concatenate(self._pending_gyro)
        self._pending_idx, self._pending_gyro = [idx], [g]
        return idx, g

    def add_dwell(self, first_index: int, last_index: int, encoder_deg: float) -> None:
        a1, b1, e1 = int(first_index), int(last_index), float(encoder_deg)
        if self._dwell is not None and a1 <= self._dwell[1]:
            raise InputError("motion samples: dwells must come in time order")
        idx, g = self._held()
        finite = np.all(np.isfinite(g), axis=1)
        rest_next = g[(idx >= a1) & (idx <= b1) & finite]
        if self._dwell is not None:
            a0, b0, e0, rest = self._dwell
            between = np.flatnonzero((idx >= b0 + 1) & (idx <= a1 - 1))
            if between.size:
                complete = between.size == a1 - b0 - 1 and bool(np.all(finite[between]))
                if not complete or rest.shape[0] == 0 or rest_next.shape[0] == 0:
                    self.counts["stretches_dropped"] += 1
                else:
                    z = np.concatenate([rest[:, 2], g[between, 2], rest_next[:, 2]])
                    enc = np.full(z.size, np.nan)
                    enc[: rest.shape[0]], enc[rest.shape[0] + between.size :] = e0, e1
                    alpha, omega = table_angle_from_z(z, 1.0 / self.rate_hz, enc)
                    span = slice(rest.shape[0], rest.shape[0] + between.size)
                    self._add_stretch(True, alpha[span], omega[span], g[between])
        self._add_rest(e1, rest_next)
        later = idx > b1
        self._pending_idx, self._pending_gyro = [idx[later]], [g[later]]
        self._dwell = (a1, b1, e1, rest_next)

    def _add_stretch(self, motion: bool, alpha, omega, gyro) -> None:
        if len(alpha) == 0:
            return
        cols = [{"x": 0, "y": 1, "z": 2}[ax] for ax in self.axes]
        stretch = _Stretch(motion, len(self.axes))
        stretch.add(alpha, omega, gyro[:, cols], self.axes, self.terms)
        self.stretches.append(stretch)
        self.counts["motion" if motion else "rest"] += stretch.n

    def _add_rest(self, encoder_deg: float, gyro) -> None:
        if len(gyro) == 0:
            return
        cols = [{"x": 0, "y": 1, "z": 2}[ax] for ax in self.axes]
        stretch = _Stretch(False, len(self.axes))
        stretch.add_rest(encoder_deg, gyro[:, cols], self.axes, self.terms)
        self.stretches.append(stretch)
        self.counts["rest"] += stretch.n

    def held_samples(self) -> int:
        """Samples held right now (the memory that does not shrink to factors)."""
        rest = 0 if self._dwell is None else self._dwell[3].shape[0]
        return sum(i.size for i in self._pending_idx) + rest

    def _fit(self, keep: list[bool]) -> HarmonicFit:
        names, p, k = self.names, len(self.names), len(self.axes)
        used = [s for s, kept in zip(self.stretches, keep, strict=True) if kept]
        m = sum(s.n for s in used)
        if m == 0:
            raise InputError("motion fit: no samples")
        total = None
        for s in used:
            for f in s.factors:
                total = _fold(total, f)
        r_a = total[:p, :p]
        norms = np.linalg.norm(r_a, axis=0)  # = the design's column norms (AᵀA = R_AᵀR_A)
        if np.any(norms == 0.0):
            raise InputError(
                f"motion fit: column {names[int(np.argmin(norms))]} is all zero (no motion in the samples?); "
                "drop the motion terms"
            )
        cond = float(np.linalg.cond(r_a / norms))  # the same singular values as A/norms
        if not np.isfinite(cond) or cond > MAX_CONDITION:
            raise InputError(
                f"motion fit: the samples cannot separate {', '.join(names)} (condition {cond:.3g}); "
                "turn through whole revolutions or more positions"
            )
        coef = np.linalg.solve(r_a, total[:p, p])
        r_inv = np.linalg.inv(r_a)
        normal_inv = r_inv @ r_inv.T
        x_aug = np.r_[coef, -1.0]
        ssr = sum((s.sq_residual(x_aug) for s in used), np.zeros(k))
        dof = k * m - p
        rms = {ax: np.array([np.sqrt(ssr[j] / m)]) for j, ax in enumerate(self.axes)}
        cov = (float(np.sum(ssr)) / dof * normal_inv)[None]
        return HarmonicFit(names, coef[None], cov, rms, dof, "residuals")

    def fit_screened(self, k_sigma: float = DISTURBED_K) -> tuple[HarmonicFit, dict[str, int]]:
        """fit_motion_screened on what was added: the fit with the disturbed motion stretches left
        out one at a time, the same rule. Returns (fit, counts: rest, motion, stretches_dropped
        (could not be placed), stretches_disturbed (left out), motion_kept, samples_used)."""
        keep = [True] * len(self.stretches)
        rest = [not s.motion for s in self.stretches]
        k = len(self.axes)
        dropped = 0
        while True:
            fit = self._fit(keep)
            if not any(rest):
                break
            x_aug = np.r_[fit.coefficients[0], -1.0]
            sums = [float(np.sum(s.sq_residual(x_aug))) for s in self.stretches]
            floor = (sum(v for v, r in zip(sums, rest, strict=True) if r)
                     / sum(s.n for s, r in zip(self.stretches, rest, strict=True) if r))
            worst, worst_excess = None, 0.0
            for i, s in enumerate(self.stretches):
                if rest[i] or not keep[i]:
                    continue
                excess = (sums[i] / s.n / floor - 1.0) / (k_sigma * np.sqrt(2.0 / (s.n * k)))
                if excess > max(1.0, worst_excess):
                    worst, worst_excess = i, excess
            if worst is None:
                break
            keep[worst] = False
            dropped += 1
        kept = [s for s, kp in zip(self.stretches, keep, strict=True) if kp]
        counts = {**self.counts, "stretches_disturbed": dropped,
                  "motion_kept": sum(s.n for s in kept if s.motion), "samples_used": sum(s.n for s in kept)}
        return fit, counts
