"""Table motion: the angle α(t) of the turntable top, from the moves the SMC100 plans.

The motor follows trapezoidal velocity profiles (configurable speed and acceleration) stored as
knots of piecewise-constant acceleration. The table top is the motor plus a lightly damped
compliance: x'' + 2ζω₀x' + ω₀²x = −k·α̈_motor, so each change of acceleration (start, cruise,
stop) rings at ~10 Hz and dies out with the decay time τ = 1/(ζω₀). With k = 1 this is a plain
mass on a spring (the top's acceleration stays continuous); k scales the ringing to the
configured amplitude, the response to one step of the configured deceleration (the steps at
the start and end of braking superpose, so the ringing after a stop is up to ~1.5× that;
None or 0 turns it off). The encoder sits on the motor side
(as on a worm-driven rotation stage), so it reads the planned angle, quantized, and equals the
top's angle once the ringing has died out.

Two imperfections of a real worm-driven stage (issue 13; off unless given, the bench turns them
on, docs/simulator.md): a speed ripple and a bearing wobble.

- Speed ripple: the servo follows the plan with a periodic error tied to the worm's angle,
  e = A·sin(2π·p/λ)·v/V (p, v: planned angle and rate, V: the configured speed, λ: table angle
  per worm turn, A = r·λ/2π). At the configured speed the rate ripples by ±r of itself at v/λ Hz;
  e is 0 whenever the plan is at rest, so every move still ends exactly on its target and the
  encoder (motor side, it reads p + e) is exact at rest. The ripple does not excite the ringing.
- Wobble: the top's axis tilts by a small rotation vector w(α) = Σ_k a_k·[cos kα, sin kα, 0] in p
  (k = 1: a tilt fixed in the top that cones once per turn; k = 2: the bearing's out-of-round,
  which the top sees change as it turns). C_b^p = exp([w×])·Rz(α); the World applies it.

Everything is vectorized over t; commands must come in non-decreasing device time. A command
at t replaces whatever was planned after t (motion before t is history and never changes).
"""

from __future__ import annotations

import math

import numpy as np

DEG = math.pi / 180.0
_SETTLED_RAD = 1e-15  # ringing envelope below this counts as gone (fast path of the World)


class TableMotion:
    """α(t) of the turntable top from planned moves; the SMC100 device owns the state machine."""

    def __init__(
        self,
        *,
        speed_deg_s: float = 20.0,
        accel_deg_s2: float = 80.0,
        home_speed_deg_s: float | None = None,
        power_on_deg: float = 137.2345,
        ringing_amplitude_deg: float | None = 0.005,
        ringing_freq_hz: float = 10.0,
        ringing_decay_s: float = 0.3,
        encoder_step_deg: float = 1e-4,
        ripple_pct: float = 0.0,
        ripple_period_deg: float = 4.0,
        wobble_urad: float | tuple[float, ...] = 0.0,
    ) -> None:
        if speed_deg_s <= 0 or accel_deg_s2 <= 0:
            raise ValueError("table speed_deg_s and accel_deg_s2 must be > 0")
        if encoder_step_deg < 0:
            raise ValueError("table encoder_step_deg must be >= 0")
        self.speed_rad_s = speed_deg_s * DEG
        self.accel_rad_s2 = accel_deg_s2 * DEG
        self.home_speed_rad_s = (home_speed_deg_s or speed_deg_s) * DEG
        self.encoder_step_rad = encoder_step_deg * DEG
        self.power_on_rad = power_on_deg * DEG
        self.omega0 = 2.0 * math.pi * ringing_freq_hz
        self.zeta = 1.0 / (ringing_decay_s * self.omega0) if ringing_decay_s > 0 else 1.0
        self.decay_s = 1.0 / (self.zeta * self.omega0)
        self.omega_d = self.omega0 * math.sqrt(max(1.0 - self.zeta**2, 1e-12))
        # k so that a stop at the configured deceleration rings with the configured amplitude
        # None or 0: no ringing (k = 1, a plain spring, would be amplitude = accel/ω₀² ≈ 0.02°)
        amplitude_rad = (ringing_amplitude_deg or 0.0) * DEG
        self.ring_gain = amplitude_rad * self.omega0**2 / self.accel_rad_s2
        # knots: from t_k on, α = p_k + v_k·τ + a_k·τ²/2 (motor side)
        self._t = np.array([-np.inf])
        self._p = np.array([self.power_on_rad])
        self._v = np.array([0.0])
        self._a = np.array([0.0])
        self._last_cmd_s = -np.inf
        self.target_rad: float = self.power_on_rad
        """Where the current (or last) plan ends."""
        self.move_end_s: float = -np.inf
        """Device time the planned motion ends (the ringing goes on a little longer)."""
        self.stalled = False
        self._ring_cache: tuple | None = None
        if ripple_pct < 0 or ripple_period_deg <= 0:
            raise ValueError("table ripple_pct must be >= 0 and ripple_period_deg > 0")
        self.ripple_k = 2.0 * math.pi / (ripple_period_deg * DEG)  # rad of worm phase per rad of table
        self.ripple_amp_rad = ripple_pct / 100.0 / self.ripple_k  # A = r·λ/2π
        self.wobble_rad = np.atleast_1d(np.asarray(wobble_urad, dtype=float)) * 1e-6
        """a_k [rad] for k = 1, 2, …; all zero: no wobble (and not a single extra operation)."""

    # -- planning ---------------------------------------------------------------------------
    @property
    def planned_end_s(self) -> float:
        """Alias of move_end_s for the device."""
        return self.move_end_s

    def _motor_state(self, t_s: float) -> tuple[float, float]:
        k = int(np.searchsorted(self._t, t_s, side="right") - 1)
        tau = t_s - self._t[k]
        if not np.isfinite(tau):
            tau = 0.0
        return (
            float(self._p[k] + self._v[k] * tau + 0.5 * self._a[k] * tau**2),
            float(self._v[k] + self._a[k] * tau),
        )

    def _truncate(self, t_s: float) -> tuple[float, float]:
        if t_s < self._last_cmd_s:
            raise ValueError(
                f"table command at t={t_s:.6f} s is earlier than the last one ({self._last_cmd_s:.6f} s)"
            )
        self._last_cmd_s = t_s
        p, v = self._motor_state(t_s)
        keep = self._t < t_s
        self._t, self._p, self._v, self._a = self._t[keep], self._p[keep], self._v[keep], self._a[keep]
        self._ring_cache = None
        return p, v

    def _append(self, t_s: float, p: float, v: float, a: float) -> None:
        self._t = np.append(self._t, t_s)
        self._p = np.append(self._p, p)
        self._v = np.append(self._v, v)
        self._a = np.append(self._a, a)

    def _plan_stop(self, t_s: float, p: float, v: float, accel: float) -> tuple[float, float]:
        """Decelerate from (p, v) at `accel`; returns (t_end, p_end)."""
        if v == 0.0:
            return t_s, p
        a = -math.copysign(accel, v)
        dur = abs(v) / accel
        self._append(t_s, p, v, a)
        return t_s + dur, p + v * dur / 2.0

    def _plan_rest_move(self, t_s: float, p0: float, target: float, vmax: float) -> float:
        """Trapezoid (or triangle) from rest at p0 to rest at target; returns the end time."""
        d = target - p0
        if d == 0.0:
            return t_s
        s = math.copysign(1.0, d)
        dist, amax = abs(d), self.accel_rad_s2
        if dist >= vmax**2 / amax:
            t_acc, v_peak = vmax / amax, vmax
            t_cruise = (dist - vmax**2 / amax) / vmax
        else:
            v_peak = math.sqrt(dist * amax)
            t_acc, t_cruise = v_peak / amax, 0.0
        d_acc = 0.5 * v_peak * t_acc
        t1 = t_s + t_acc
        t2 = t1 + t_cruise
        self._append(t_s, p0, 0.0, s * amax)
        if t_cruise > 0.0:
            self._append(t1, p0 + s * d_acc, s * v_peak, 0.0)
        self._append(t2, target - s * d_acc, s * v_peak, -s * amax)
        return t2 + t_acc

    def _finish(self, t_end: float, p_end: float) -> float:
        self._append(t_end, p_end, 0.0, 0.0)
        self.move_end_s = t_end
        self.target_rad = p_end
        return t_end

    def command_move(
        self,
        t_s: float,
        target_rad: float,
        *,
        speed_rad_s: float | None = None,
        stall_fraction: float | None = None,
    ) -> float:
        """Plan a move to `target_rad` starting at device time t_s; returns the time it ends.

        If the table is moving, it first decelerates to rest, then moves. `stall_fraction` in
        (0, 1): the stage jams once it has covered that fraction of the distance and stops at 4×
        the configured deceleration, short of the target (a following error the device reports).
        """
        p, v = self._truncate(t_s)
        t_stop, p_stop = self._plan_stop(t_s, p, v, self.accel_rad_s2)
        vmax = self.speed_rad_s if speed_rad_s is None else float(speed_rad_s)
        self.stalled = False
        if stall_fraction is None:
            t_end = self._plan_rest_move(t_stop, p_stop, float(target_rad), vmax)
            return self._finish(t_end, float(target_rad))
        f = float(np.clip(stall_fraction, 0.0, 1.0))
        t_end = self._plan_rest_move(t_stop, p_stop, float(target_rad), vmax)
        self._append(t_end, float(target_rad), 0.0, 0.0)
        p_jam = p_stop + f * (float(target_rad) - p_stop)
        t_jam = self._time_at_position(t_stop, t_end, p_jam)
        self.stalled = True
        p_j, v_j = self._truncate_at(t_jam)
        t_rest, p_rest = self._plan_stop(t_jam, p_j, v_j, 4.0 * self.accel_rad_s2)
        self.target_rad = float(target_rad)
        end = self._finish(t_rest, p_rest)
        self.target_rad = float(target_rad)
        return end

    def _truncate_at(self, t_s: float) -> tuple[float, float]:
        p, v = self._motor_state(t_s)
        keep = self._t < t_s
        self._t, self._p, self._v, self._a = self._t[keep], self._p[keep], self._v[keep], self._a[keep]
        return p, v

    def _time_at_position(self, t_a: float, t_b: float, p_goal: float) -> float:
        """First time in [t_a, t_b] the (monotonic) planned motion reaches p_goal (bisection)."""
        p_a, _ = self._motor_state(t_a)
        sign = 1.0 if p_goal >= p_a else -1.0
        lo, hi = t_a, t_b
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if sign * (self._motor_state(mid)[0] - p_goal) < 0.0:
                lo = mid
            else:
                hi = mid
        return hi

    def stop(self, t_s: float) -> float:
        """Decelerate at the configured rate from wherever the table is at t_s; returns the end time."""
        p, v = self._truncate(t_s)
        t_end, p_end = self._plan_stop(t_s, p, v, self.accel_rad_s2)
        return self._finish(t_end, p_end)

    def home(self, t_s: float) -> float:
        """Homing: a move to α = 0 (from the unknown power-on angle) at the homing speed."""
        return self.command_move(t_s, 0.0, speed_rad_s=self.home_speed_rad_s)

    # -- evaluation -------------------------------------------------------------------------
    def planned_kinematics(self, t_s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Planned angle, rate, acceleration at t_s (vectorized): the trapezoids, no ripple."""
        t = np.asarray(t_s, dtype=float)
        k = np.searchsorted(self._t, t, side="right") - 1
        k = np.maximum(k, 0)
        tau = np.where(np.isfinite(self._t[k]), t - self._t[k], 0.0)
        a = self._a[k]
        return self._p[k] + self._v[k] * tau + 0.5 * a * tau**2, self._v[k] + a * tau, a

    def motor_kinematics(self, t_s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Motor-side angle, rate, acceleration at t_s: the plan plus the speed ripple.

        e = A·S·v/V, ė = A·(k·C·v² + S·a)/V, ë = A·(3k·C·v·a − k²·S·v³)/V with S, C = sin, cos(k·p)
        (a is constant between knots). 0 wherever the plan is at rest.
        """
        p, v, a = self.planned_kinematics(t_s)
        if self.ripple_amp_rad == 0.0:
            return p, v, a
        k, scale = self.ripple_k, self.ripple_amp_rad / self.speed_rad_s
        s, c = np.sin(k * p), np.cos(k * p)
        e = scale * s * v
        ed = scale * (k * c * v * v + s * a)
        edd = scale * (3.0 * k * c * v * a - k * k * s * v**3)
        return p + e, v + ed, a + edd

    def wobble(self, alpha_rad) -> tuple[np.ndarray, np.ndarray] | None:
        """(w [...,3], dw/dα [...,3]): the top's tilt as a rotation vector in p, at angles α; None
        when the stage has no wobble."""
        if not np.any(self.wobble_rad):
            return None
        alpha = np.asarray(alpha_rad, dtype=float)
        w = np.zeros(alpha.shape + (3,))
        dw = np.zeros(alpha.shape + (3,))
        for k, a_k in enumerate(self.wobble_rad, start=1):
            if a_k:
                c, s = np.cos(k * alpha), np.sin(k * alpha)
                w[..., 0] += a_k * c
                w[..., 1] += a_k * s
                dw[..., 0] -= k * a_k * s
                dw[..., 1] += k * a_k * c
        return w, dw

    def _ring_steps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Knot times, forcing steps Δu = −k·Δa, and cumsum of Δu (for settled knots)."""
        if self._ring_cache is None:
            da = np.diff(self._a)
            du = -self.ring_gain * da
            self._ring_cache = (self._t[1:], du, np.concatenate([[0.0], np.cumsum(du)]))
        return self._ring_cache

    def ringing(self, t_s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Top-minus-motor deflection x and its two derivatives at t_s (vectorized).

        x = Σ_j Δu_j·s(t − t_j) with the step response of x'' + 2ζω₀x' + ω₀²x = u:
        s = [1 − e^{−ζω₀τ}(cos ω_dτ + ζω₀/ω_d sin ω_dτ)]/ω₀², s' = e^{−ζω₀τ} sin(ω_dτ)/ω_d,
        s'' = e^{−ζω₀τ}(cos ω_dτ − ζω₀/ω_d sin ω_dτ).
        """
        t = np.asarray(t_s, dtype=float)
        tk, du, cum = self._ring_steps()
        zeros = np.zeros_like(t)
        if tk.size == 0 or t.size == 0:
            return zeros, zeros, zeros
        horizon = self.decay_s * 40.0  # e^-40: far below anything a sensor resolves
        t_lo, t_hi = float(np.min(t)), float(np.max(t))
        j0 = int(np.searchsorted(tk, t_lo - horizon, side="left"))
        j1 = int(np.searchsorted(tk, t_hi, side="right"))
        # knots older than the horizon: the step response is 1/ω₀² exactly (no derivatives)
        w2 = self.omega0**2
        x = np.full_like(t, cum[j0] / w2)
        xd, xdd = zeros.copy(), zeros.copy()
        if j1 > j0:
            tau = t[..., None] - tk[j0:j1]
            live = tau >= 0.0
            tau = np.where(live, tau, 0.0)
            sw = self.zeta * self.omega0
            e = np.exp(-sw * tau)
            c, s = np.cos(self.omega_d * tau), np.sin(self.omega_d * tau)
            r = sw / self.omega_d
            d = du[j0:j1] * live
            x = x + ((1.0 - e * (c + r * s)) / w2 * d).sum(axis=-1)
            xd = (e * s / self.omega_d * d).sum(axis=-1)
            xdd = (e * (c - r * s) * d).sum(axis=-1)
        return x, xd, xdd

    def kinematics(self, t_s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(α, α̇, α̈) of the table top at t_s [rad, rad/s, rad/s²]: planned motion plus ringing."""
        p, v, a = self.motor_kinematics(t_s)
        x, xd, xdd = self.ringing(t_s)
        return p + x, v + xd, a + xdd

    def encoder_rad(self, t_s) -> np.ndarray:
        """What the encoder reads: the motor-side angle quantized to the encoder step."""
        p = self.motor_kinematics(t_s)[0]
        q = self.encoder_step_rad
        return np.round(p / q) * q if q > 0 else p

    def is_moving(self, t_s) -> np.ndarray:
        """True where the planned motion is under way (ringing after a stop does not count)."""
        t = np.asarray(t_s, dtype=float)
        k = np.maximum(np.searchsorted(self._t, t, side="right") - 1, 0)
        return (self._v[k] != 0.0) | (self._a[k] != 0.0)

    def settled_s(self) -> float:
        """Device time from which the top is at rest to far below any sensor's resolution."""
        tk, du, _ = self._ring_steps()
        if tk.size == 0:
            return -np.inf
        amp = float(np.max(np.abs(du))) / self.omega0**2
        extra = self.decay_s * math.log(max(amp, _SETTLED_RAD) / _SETTLED_RAD) if amp > 0 else 0.0
        return float(tk[-1]) + extra

    def rest_s(self, threshold_rad: float) -> float:
        """Device time from which the top's angle stays within `threshold_rad` of where it comes to
        rest: the planned motion's end plus the time the ringing envelope needs to fall below it.

        Bound: each forcing step Δu_j leaves |x − x_final| ≤ |Δu_j|·√(1 + (ζω₀/ω_d)²)/ω₀²·e^{−τ/decay};
        the bound sums them at the last knot and lets the sum decay from there.
        """
        tk, du, _ = self._ring_steps()
        if tk.size == 0 or not np.isfinite(tk[-1]):
            return -np.inf
        t_last = float(tk[-1])
        recent = tk >= t_last - 40.0 * self.decay_s
        r = self.zeta * self.omega0 / self.omega_d
        amp = float(np.sum(np.abs(du[recent]) * np.exp(-(t_last - tk[recent]) / self.decay_s)))
        amp *= math.sqrt(1.0 + r * r) / self.omega0**2
        if amp <= threshold_rad:
            return t_last
        return t_last + self.decay_s * math.log(amp / threshold_rad)

    def still_between(self, t_a_s: float, t_b_s: float) -> bool:
        """True if the top does not move at all (to 1e-15 rad) over [t_a, t_b]."""
        if t_a_s >= self.settled_s():
            return True
        tk = self._t[1:]
        first = tk[0] if tk.size else np.inf
        return t_b_s <= first
