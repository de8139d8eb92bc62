"""Sensor error models: what a real gyro and accelerometer add to the world's truth.

Per axis (IEEE Std 952 terms): constant bias, white noise (ARW / accelerometer noise density),
bias instability, rate random walk, scale factor, small-angle axis misalignment, and float32
quantization of delta angles with the residual carried to the next sample. What a moving table
adds (issue 13): the gyro's scale-factor asymmetry (positive and negative rates see different
scales) and the g-sensitivity of its bias (°/h per g of the specific force the unit sees), both
pointwise in the sample, so they keep the block-split independence below.

Bias instability B [°/h] is the flicker floor of the Allan deviation (σ_A,min ≈ 0.664·B). We
model it as a first-order Gauss–Markov process with correlation time τ_c and steady-state
σ = B: its Allan deviation peaks at ≈ 0.62·σ near T ≈ 1.9·τ_c, close to the flicker floor, and
it is exact to sample with a one-pole filter. For `nav` (B = 0.005 °/h, τ_c = 600 s) the
process is nearly constant over a 4 min 8-position north find, so indexing cancels most of it:
its heading error is a small fraction of the 0.055° white-noise limit: 0.008° (1σ over 2000
simulated 8×30 s runs with 3 s moves, single-axis LS heading), adding ~1 % in quadrature
(tests/test_sim_physics.py checks it stays below 0.3× the limit).

Determinism: each error source draws from its own stream (SeedSequence.spawn), normals are
drawn sample by sample in order, the Gauss–Markov recursion works on blocks fixed on the sample
index (`FirstOrderRecursion`), cumulative sums carry their last value, so apply(a); apply(b) gives
exactly what apply(a ⧺ b) gives. numpy only: scipy.signal's import alone costs ~1 s of CPU, which
every simulator start would pay.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, fields, replace

import numpy as np

DEG = math.pi / 180.0
DPH = DEG / 3600.0
G0_M_S2 = 9.80665
UG_M_S2 = 1e-6 * G0_M_S2


def _triple(v) -> tuple[float, float, float]:
    a = np.broadcast_to(np.asarray(v, dtype=float), (3,))
    return (float(a[0]), float(a[1]), float(a[2]))


def _six(v) -> tuple[float, ...]:
    a = np.broadcast_to(np.asarray(v, dtype=float), (6,))
    return tuple(float(x) for x in a)


def _nine(v) -> tuple[float, ...]:
    """One number or three → a diagonal 3×3 (row-major); nine → the full matrix."""
    a = np.asarray(v, dtype=float).ravel()
    if a.size in (1, 3):
        return tuple(float(x) for x in np.diag(np.broadcast_to(a, (3,))).ravel())
    if a.size != 9:
        raise ValueError(f"give 1, 3 or 9 numbers for a 3×3 matrix, not {a.size}")
    return tuple(float(x) for x in a)


def _misalignment_matrix(six_urad) -> np.ndarray:
    """(xy, xz, yx, yz, zx, zy) µrad → off-diagonal M: axis i senses M[i, j] of true axis j."""
    m = np.zeros((3, 3))
    for (i, j), v in zip(((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)), six_urad, strict=True):
        m[i, j] = v * 1e-6
    return m


class _PerAxis:
    """Broadcast scalar fields to per-axis triples (custom values may be given as one number)."""

    _SIX = ("misalignment_urad",)
    _NINE = ("g_sensitivity_dph_g",)
    _SCALAR = ("bi_correlation_s", "float32_delta")

    def __post_init__(self) -> None:
        for f in fields(self):  # type: ignore[arg-type]
            if f.name in self._SCALAR:
                continue
            conv = _six if f.name in self._SIX else _nine if f.name in self._NINE else _triple
            object.__setattr__(self, f.name, conv(getattr(self, f.name)))


@dataclass(frozen=True)
class GyroErrors(_PerAxis):
    """Gyro errors per axis (x, y, z). Units at the edge: °/h, °/√h, °/h/√h, ppm, µrad."""

    bias_dph: tuple[float, float, float] = (0.0, 0.0, 0.0)
    arw_deg_rt_h: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bias_instability_dph: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bi_correlation_s: float = 600.0
    rrw_dph_rt_h: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale_factor_ppm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    misalignment_urad: tuple[float, ...] = (0.0,) * 6
    float32_delta: bool = True
    sf_asymmetry_ppm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """(S₊ − S₋)/S per axis: positive rates see the scale 1 + S + A/2, negative ones 1 + S − A/2."""
    g_sensitivity_dph_g: tuple[float, ...] = (0.0,) * 9
    """Row-major 3×3 G: gyro i's bias moves by G[i][j] °/h per g of specific force along axis j."""

    @property
    def tilt_to_z_rad(self) -> tuple[float, float]:
        """δ of the x and y gyros: how far each input axis leans toward z (M_xz, M_yz) [rad]."""
        return (self.misalignment_urad[1] * 1e-6, self.misalignment_urad[3] * 1e-6)

    def with_(self, **changes) -> GyroErrors:
        """A copy with some values changed (custom grades)."""
        return replace(self, **changes)


@dataclass(frozen=True)
class AccelErrors(_PerAxis):
    """Accelerometer errors per axis. Units at the edge: µg, µg/√Hz, ppm, µrad."""

    bias_ug: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise_ug_rt_hz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bias_instability_ug: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bi_correlation_s: float = 600.0
    scale_factor_ppm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    misalignment_urad: tuple[float, ...] = (0.0,) * 6

    def with_(self, **changes) -> AccelErrors:
        return replace(self, **changes)


# Grades. ARW and bias instability of the gyros are the project brief's. The rest are choices
# typical of each class (stated, not a vendor's guarantee): turn-on biases are fixed per preset
# (the same every run, different per axis) so tests can account for them exactly.
#   nav: RLG/FOG navigation grade, quartz-flex accelerometers (~QA-2000 class: tens of µg bias,
#        ~10 µg/√Hz). kvh1760: KVH 1750/1760-class FOG IMU, accelerometer VRW 0.12 mg/√Hz and
#        bias stability 0.05 mg as on KVH's 1750 data sheet. tactical-mems: ADIS1649x class
#        (~25–50 µg/√Hz, sub-mg bias). consumer: phone-class MEMS (~150–300 µg/√Hz, tens of mg).
def _g_matrix(diag: float, off: float) -> tuple[float, ...]:
    """A g-sensitivity matrix [°/h/g]: `diag` on the own axis, cross terms of size ≤ `off`."""
    return (diag, off, -0.8 * off, -0.6 * off, diag, off, 0.8 * off, -off, diag)


# Motion terms (issue 13; docs/simulator.md says where each number comes from): scale-factor
# asymmetry and g-sensitivity are our choices of the order each class states (nav ~1 ppm and
# ~0.001 °/h/g; a KVH 1750-class FOG tens of ppm and ~0.1 °/h/g; a factory-compensated
# ADIS1649x-class MEMS hundreds of ppm and a few °/h/g; an uncompensated phone/industrial MEMS
# ~0.1–0.3 % and ~50 °/h/g, cf. the ±0.015 °/s/g ADIS16445 figure).
GYRO_PRESETS: dict[str, GyroErrors] = {
    "nav": GyroErrors(
        bias_dph=(0.004, -0.003, 0.002),
        arw_deg_rt_h=0.002,
        bias_instability_dph=0.005,
        bi_correlation_s=600.0,
        rrw_dph_rt_h=0.0005,
        scale_factor_ppm=(1.0, -1.0, 1.0),
        misalignment_urad=(5.0, -3.0, 4.0, 2.0, -6.0, 3.0),
        sf_asymmetry_ppm=(1.0, -0.8, 1.2),
        g_sensitivity_dph_g=_g_matrix(0.001, 0.0005),
    ),
    "kvh1760": GyroErrors(
        bias_dph=(0.3, -0.2, 0.25),
        arw_deg_rt_h=0.012,
        bias_instability_dph=0.05,
        bi_correlation_s=300.0,
        rrw_dph_rt_h=0.01,
        scale_factor_ppm=(50.0, -40.0, 45.0),
        misalignment_urad=(50.0, -30.0, 40.0, 20.0, -60.0, 30.0),
        sf_asymmetry_ppm=(20.0, -15.0, 25.0),
        g_sensitivity_dph_g=_g_matrix(0.1, 0.05),
    ),
    "tactical-mems": GyroErrors(
        bias_dph=(5.0, -4.0, 3.0),
        arw_deg_rt_h=0.15,
        bias_instability_dph=0.5,
        bi_correlation_s=100.0,
        rrw_dph_rt_h=0.5,
        scale_factor_ppm=(500.0, -400.0, 450.0),
        misalignment_urad=(500.0, -300.0, 400.0, 200.0, -600.0, 300.0),
        sf_asymmetry_ppm=(200.0, -150.0, 250.0),
        g_sensitivity_dph_g=_g_matrix(3.0, 1.0),
    ),
    # Safran Sensonor STIM300, TS1524 rev.31 Table 5-3: ARW 0.15 °/√h, bias instability 0.3 °/h
    # (Allan minimum; 0.5 °/h at 600 s), bias run-run 4 °/h (the turn-on biases below stay inside
    # it), scale factor ±500 ppm, misalignment 1 mrad, linear-acceleration bias 1 °/h/g with
    # g-compensation. Asymmetry and RRW are our choices of the class's order (not in the sheet).
    "stim300": GyroErrors(
        bias_dph=(3.0, -2.5, 2.0),
        arw_deg_rt_h=0.15,
        bias_instability_dph=0.3,
        bi_correlation_s=100.0,
        rrw_dph_rt_h=0.3,
        scale_factor_ppm=(300.0, -250.0, 200.0),
        misalignment_urad=(800.0, -600.0, 700.0, 500.0, -900.0, 600.0),
        sf_asymmetry_ppm=(100.0, -80.0, 120.0),
        g_sensitivity_dph_g=_g_matrix(1.0, 0.5),
    ),
    "consumer": GyroErrors(
        bias_dph=(200.0, -150.0, 100.0),
        arw_deg_rt_h=1.0,
        bias_instability_dph=10.0,
        bi_correlation_s=60.0,
        rrw_dph_rt_h=10.0,
        scale_factor_ppm=(5000.0, -4000.0, 3000.0),
        misalignment_urad=(5000.0, -3000.0, 4000.0, 2000.0, -6000.0, 3000.0),
        sf_asymmetry_ppm=(2000.0, -1500.0, 2500.0),
        g_sensitivity_dph_g=_g_matrix(50.0, 20.0),
    ),
}
ACCEL_PRESETS: dict[str, AccelErrors] = {
    "nav": AccelErrors(
        bias_ug=(30.0, -20.0, 25.0),
        noise_ug_rt_hz=10.0,
        bias_instability_ug=2.0,
        scale_factor_ppm=(20.0, -15.0, 10.0),
        misalignment_urad=(5.0, -3.0, 4.0, 2.0, -6.0, 3.0),
    ),
    "kvh1760": AccelErrors(
        bias_ug=(500.0, -400.0, 300.0),
        noise_ug_rt_hz=120.0,
        bias_instability_ug=50.0,
        bi_correlation_s=300.0,
        scale_factor_ppm=(300.0, -250.0, 200.0),
        misalignment_urad=(50.0, -30.0, 40.0, 20.0, -60.0, 30.0),
    ),
    "tactical-mems": AccelErrors(
        bias_ug=(800.0, -600.0, 700.0),
        noise_ug_rt_hz=40.0,
        bias_instability_ug=10.0,
        bi_correlation_s=100.0,
        scale_factor_ppm=(1000.0, -800.0, 900.0),
        misalignment_urad=(500.0, -300.0, 400.0, 200.0, -600.0, 300.0),
    ),
    # STIM300 10 g accelerometers, TS1524 rev.31 Table 5-5: VRW 0.024 m/s/√h = 0.024/60 m/s²/√Hz
    # = 40.8 µg/√Hz, bias instability 0.005 mg (Allan minimum), bias one-year stability 1.9 mg
    # (turn-on biases below inside it), scale factor ±200 ppm, misalignment 1 mrad.
    "stim300": AccelErrors(
        bias_ug=(800.0, -600.0, 500.0),
        noise_ug_rt_hz=0.024 / 60.0 / G0_M_S2 * 1e6,
        bias_instability_ug=5.0,
        bi_correlation_s=100.0,
        scale_factor_ppm=(150.0, -120.0, 100.0),
        misalignment_urad=(800.0, -600.0, 700.0, 500.0, -900.0, 600.0),
    ),
    "consumer": AccelErrors(
        bias_ug=(20000.0, -15000.0, 25000.0),
        noise_ug_rt_hz=200.0,
        bias_instability_ug=100.0,
        bi_correlation_s=60.0,
        scale_factor_ppm=(10000.0, -8000.0, 9000.0),
        misalignment_urad=(5000.0, -3000.0, 4000.0, 2000.0, -6000.0, 3000.0),
    ),
}


GM_BLOCK_E_FOLDS = 40.0
"""A block of the Gauss–Markov recursion spans at most this many e-folds of φ (φ^len ≥ e^−40), so
the weights φ^−j inside it stay below e^40 ≈ 2e17: far from overflow, and each weight is one
correctly rounded pow()."""
GM_BLOCK_MAX = 4096
"""…and at most this many samples (the table of φ^j per model)."""


class FirstOrderRecursion:
    """y[n] = φ·y[n−1] + x[n] per column, its state carried from call to call; numpy only.

    Started with `zi` = φ·y[−1] it is, in exact arithmetic, scipy.signal.lfilter([1], [1, −φ], x,
    axis=0, zi=zi), and `zf` is lfilter's final state φ·y[last]. Computed in blocks of B samples
    fixed on the sample index (block m holds samples mB … mB + B − 1 since the start), where
    φ^B ≥ e^−40: with j the position in the block and s the state entering it,
        y[mB + j] = φ^j · (s + Σ_{i≤j} x[mB + i] / φ^i),   s of the next block = φ·y[mB + B − 1],
    the sum a sequential cumulative sum that carries its last value to the next call. Each output
    is one fixed sequence of roundings of the input, whatever the calls' lengths: apply(a);
    apply(b) gives exactly apply(a ⧺ b), so the simulator's bytes do not depend on its ticks. Its
    rounding error grows like lfilter's, by ~1 ulp of the signal's scale per sample at worst
    (tests/test_sim_ar1.py). φ = 0: y = x (and y[0] = x[0] + zi); |φ| ≤ 1.
    """

    def __init__(self, phi: float, zi, width: int = 3) -> None:
        self.phi = float(phi)
        if not abs(self.phi) <= 1.0:
            raise ValueError(f"phi = {phi}: the recursion needs |φ| ≤ 1")
        e_folds = -math.log(abs(self.phi)) if self.phi else math.inf  # per sample
        fits = e_folds * GM_BLOCK_MAX <= GM_BLOCK_E_FOLDS
        block = GM_BLOCK_MAX if fits else int(GM_BLOCK_E_FOLDS / e_folds)
        self._powers = self.phi ** np.arange(max(block, 1), dtype=float)  # φ^j, j in the block
        self._sum = np.array(zi, dtype=float).reshape(width)  # s + Σ so far in the current block
        self._j = 0  # samples of the current block already done

    @property
    def zf(self) -> np.ndarray:
        """The state for the next sample, φ·y[last] (lfilter's zf), shape (1, width)."""
        if self._j == 0:
            return self._sum[None, :].copy()
        return (self.phi * (self._powers[self._j - 1] * self._sum))[None, :]

    def apply(self, x: np.ndarray) -> np.ndarray:
        """y for the next samples x [n, width] (state carried)."""
        x = np.asarray(x, dtype=float)
        n = x.shape[0]
        if self.phi == 0.0:
            y = x.copy()
            if n:
                y[0] = self._sum + x[0]
                self._sum = np.zeros_like(self._sum)
            return y
        y = np.empty_like(x)
        block = len(self._powers)
        done = 0
        while done < n:
            m = min(n - done, block - self._j)
            p = self._powers[self._j:self._j + m, None]
            terms = x[done:done + m] / p
            terms[0] += self._sum  # the first step of the block's running sum, as one call would do
            sums = np.cumsum(terms, axis=0)
            y[done:done + m] = sums * p
            done += m
            self._j += m
            if self._j == block:  # the next block starts from φ·y at this one's end
                self._sum, self._j = self.phi * y[done - 1], 0
            else:
                self._sum = sums[-1]
        return y


def first_order_filter(x: np.ndarray, phi: float, zi) -> tuple[np.ndarray, np.ndarray]:
    """(y, zf) of lfilter([1], [1, −φ], x, axis=0, zi=zi) by `FirstOrderRecursion`, blocks counted
    from this call: calls in a row, each given the last one's zf, continue the stream."""
    x = np.asarray(x, dtype=float)
    rec = FirstOrderRecursion(phi, zi, width=x.shape[1])
    return rec.apply(x), rec.zf


def _seed_sequence(rng) -> np.random.SeedSequence:
    """int / SeedSequence / Generator → a SeedSequence to spawn independent streams from."""
    if isinstance(rng, np.random.SeedSequence):
        return rng
    if isinstance(rng, np.random.Generator):
        return np.random.SeedSequence(int(rng.integers(0, 2**63)))
    return np.random.SeedSequence(rng)


class Float32Carry:
    """Round each sample to float32 and carry the rounding residual into the next sample.

    q_k = f32(x_k + r_{k−1}), r_k = x_k + r_{k−1} − q_k, so Σq stays within half a float32 ulp of
    Σx however long the run (a real unit integrates internally and only rounds the output).
    The recursion is nonlinear and strictly sequential, which numpy cannot express: numpy
    rounds every sample and finds both neighbouring float32 midpoints at once; the Python loop
    only compares the carried value against them (a struct round-trip where the carry pushes
    it past a midpoint or a tie), ≈ 1 ms per 1000 three-axis samples.
    """

    def __init__(self, width: int = 3) -> None:
        self.residual = [0.0] * width
        self._f = struct.Struct("f")

    def apply(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float).reshape(-1, len(self.residual))
        q32 = x.astype(np.float32)
        q = q32.astype(float)
        hi = 0.5 * (q + np.nextafter(q32, np.float32(np.inf)).astype(float))
        lo = 0.5 * (q + np.nextafter(q32, np.float32(-np.inf)).astype(float))
        out = q.copy()
        pack, unpack = self._f.pack, self._f.unpack
        for ax in range(x.shape[1]):
            xs, qs, his, los = x[:, ax].tolist(), q[:, ax].tolist(), hi[:, ax].tolist(), lo[:, ax].tolist()
            col = list(qs)
            r = self.residual[ax]
            for k, xk in enumerate(xs):
                y = xk + r
                if los[k] < y < his[k]:
                    r = y - qs[k]
                else:  # the carry crosses a rounding midpoint (or sits on one): round exactly
                    qk = unpack(pack(y))[0]
                    col[k] = qk
                    r = y - qk
            out[:, ax] = col
            self.residual[ax] = r
        return out


class _ErrorModel:
    """Shared machinery: scale/misalignment matrix, white noise, Gauss–Markov, random walk."""

    _streams = ("white", "gauss_markov", "random_walk", "initial")

    def __init__(
        self, sample_rate_hz: float, rng, sf_ppm, mis_urad, bias, white_sigma, gm_sigma, tau_s, rw_sigma
    ):
        if not float(sample_rate_hz) > 0.0:
            raise ValueError(f"sensor sample_rate_hz = {sample_rate_hz}: must be > 0")
        self.dt_s = 1.0 / float(sample_rate_hz)
        ss = _seed_sequence(rng)
        self.rng = {
            name: np.random.default_rng(s) for name, s in zip(self._streams, ss.spawn(4), strict=True)
        }
        self.matrix_t = (np.eye(3) + np.diag(np.asarray(sf_ppm) * 1e-6) + _misalignment_matrix(mis_urad)).T
        self.bias = np.asarray(bias, dtype=float)  # per-sample increment units / s
        self.white_sigma = np.asarray(white_sigma, dtype=float)  # per sample
        self.gm_sigma = np.asarray(gm_sigma, dtype=float)  # steady-state σ of the GM rate
        self.phi = math.exp(-self.dt_s / tau_s) if tau_s > 0 else 0.0
        self.rw_sigma = np.asarray(rw_sigma, dtype=float)  # random-walk step per sample
        # stationary start of the Gauss–Markov state; the random walk starts at zero
        gm0 = self.gm_sigma * self.rng["initial"].standard_normal(3)
        self._gm = FirstOrderRecursion(self.phi, self.phi * gm0)
        self._rw = np.zeros(3)
        self.samples = 0

    def _errors(self, n: int) -> np.ndarray:
        """Rate-like error per sample [n,3] (bias + GM + random walk) and white increments."""
        gm_in = self.rng["gauss_markov"].standard_normal((n, 3)) * (
            self.gm_sigma * math.sqrt(1.0 - self.phi**2)
        )
        gm = self._gm.apply(gm_in)
        steps = self.rng["random_walk"].standard_normal((n, 3)) * self.rw_sigma
        rw = np.cumsum(np.concatenate([self._rw[None, :], steps]), axis=0)[1:]
        self._rw = rw[-1].copy() if n else self._rw
        white = self.rng["white"].standard_normal((n, 3)) * self.white_sigma
        self.samples += n
        return (self.bias + gm + rw) * self.dt_s + white

    def _apply(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float).reshape(-1, 3)
        m = self.matrix_t
        # row by row in a fixed order (BLAS picks other kernels, and roundings, for other sizes)
        scaled = x[:, 0:1] * m[0] + x[:, 1:2] * m[1] + x[:, 2:3] * m[2]
        return scaled + self._errors(x.shape[0])


class GyroModel(_ErrorModel):
    """Delta angles in, measured delta angles out [rad per sample], one model per gyro triad.

    Δθ_meas = (I + S + M)·Δθ_true + (A/2)·|Δθ_true| + G·Δv_true/g0 + (b + b_GM + b_RRW)·dt
              + N·√dt·w, then float32 with carry.
    N = ARW·(π/180)/60 rad/√s; RRW K [°/h/√h] → rate steps K·(π/180)/3600/60·√dt per sample.
    A: scale-factor asymmetry per axis (|·| of the axis's own true increment); G [°/h/g → rad/s
    per m/s²]: g-sensitivity acting on the true specific force over the sample (Δv_true/dt), so
    the bias moves with what the unit's accelerometers feel (gravity, table and lever-arm terms).
    """

    def __init__(self, errors: GyroErrors, sample_rate_hz: float, rng) -> None:
        dt = 1.0 / float(sample_rate_hz)
        self.errors = errors
        n_rad_rt_s = np.asarray(errors.arw_deg_rt_h) * DEG / 60.0
        k_rad_s_rt_s = np.asarray(errors.rrw_dph_rt_h) * DPH / 60.0
        super().__init__(
            sample_rate_hz,
            rng,
            errors.scale_factor_ppm,
            errors.misalignment_urad,
            np.asarray(errors.bias_dph) * DPH,
            n_rad_rt_s * math.sqrt(dt),
            np.asarray(errors.bias_instability_dph) * DPH,
            errors.bi_correlation_s,
            k_rad_s_rt_s * math.sqrt(dt),
        )
        self._f32 = Float32Carry(3) if errors.float32_delta else None
        half_asym = np.asarray(errors.sf_asymmetry_ppm) * 0.5e-6
        self._half_asym = half_asym if np.any(half_asym) else None  # off: not even a +0.0
        g_mat = np.asarray(errors.g_sensitivity_dph_g).reshape(3, 3) * DPH / G0_M_S2
        self._g_t = g_mat.T.copy() if np.any(g_mat) else None

    def apply(self, dtheta_true_rad: np.ndarray, dv_true_m_s: np.ndarray | None = None) -> np.ndarray:
        """Measured delta angles [n,3] rad for consecutive true ones (state carried).

        `dv_true_m_s` [n,3]: the true velocity increments at the unit over the same samples, for
        the g-sensitivity; None leaves that term out (a caller with no specific force at hand).
        """
        x = np.asarray(dtheta_true_rad, dtype=float).reshape(-1, 3)
        out = self._apply(x)
        if self._half_asym is not None:
            out = out + np.abs(x) * self._half_asym
        if self._g_t is not None and dv_true_m_s is not None:
            dv = np.asarray(dv_true_m_s, dtype=float).reshape(-1, 3)
            g = self._g_t
            out = out + (dv[:, 0:1] * g[0] + dv[:, 1:2] * g[1] + dv[:, 2:3] * g[2])
        return self._f32.apply(out) if self._f32 is not None else out


class AccelModel(_ErrorModel):
    """Velocity increments in, measured ones out [m/s per sample].

    Δv_meas = (I + S + M)·Δv_true + (b + b_GM)·dt + n·√dt·w, with n [m/s²/√Hz] = µg/√Hz·1e-6·g0.
    """

    def __init__(self, errors: AccelErrors, sample_rate_hz: float, rng) -> None:
        dt = 1.0 / float(sample_rate_hz)
        self.errors = errors
        super().__init__(
            sample_rate_hz,
            rng,
            errors.scale_factor_ppm,
            errors.misalignment_urad,
            np.asarray(errors.bias_ug) * UG_M_S2,
            np.asarray(errors.noise_ug_rt_hz) * UG_M_S2 * math.sqrt(dt),
            np.asarray(errors.bias_instability_ug) * UG_M_S2,
            errors.bi_correlation_s,
            np.zeros(3),
        )

    def apply(self, dv_true_m_s: np.ndarray) -> np.ndarray:
        """Measured velocity increments [n,3] m/s for consecutive true ones (state carried)."""
        return self._apply(dv_true_m_s)


def gyro_errors(grade: str, **overrides) -> GyroErrors:
    """A preset by name, optionally with some values changed; a clear error for an unknown name."""
    if grade not in GYRO_PRESETS:
        raise ValueError(f"gyro grade {grade!r} unknown; use one of {', '.join(GYRO_PRESETS)}")
    return GYRO_PRESETS[grade].with_(**overrides) if overrides else GYRO_PRESETS[grade]


def accel_errors(grade: str, **overrides) -> AccelErrors:
    """An accelerometer preset by name (same names as the gyros)."""
    if grade not in ACCEL_PRESETS:
        raise ValueError(f"accelerometer grade {grade!r} unknown; use one of {', '.join(ACCEL_PRESETS)}")
    return ACCEL_PRESETS[grade].with_(**overrides) if overrides else ACCEL_PRESETS[grade]
