"""IMU classes by their data-sheet figures: what the align filters assume of an IMU whose grade is known.

One table for both align modes (gnss_ins: the Kalman filter's noise and bias priors; swaying: the
bias floor and the sway-rectified asymmetry in its σ). The classes are docs/simulator.md's grades:
KVH 1750/1760 by its data sheet (ARW 0.012 °/√h, VRW 0.12 mg/√Hz, bias instability 0.05 °/h and
0.05 mg), the others by the class figures the simulator's grades state. The numbers are copied by
value: northfinder never imports firmware_sim.
"""

from __future__ import annotations

from dataclasses import dataclass

from northfinder.errors import InputError


@dataclass(frozen=True)
class ImuGrade:
    """Data-sheet-type figures of an IMU class.

    arw / vrw: gyro angle random walk [°/√h] and accelerometer noise density [µg/√Hz];
    *_bias_instability with `bias_correlation_s`: the in-run bias wander [°/h, µg] and its time;
    *_turn_on: 1σ of the bias a unit starts with, run to run [°/h, µg] (turn-on ⊕ bias instability);
    gyro_sf_asymmetry_ppm: 1σ of (S₊ − S₋)/S, the scale-factor asymmetry a sway rectifies into a bias.
    """

    arw_deg_sqrt_h: float
    vrw_ug_sqrt_hz: float
    gyro_bias_instability_dph: float
    accel_bias_instability_ug: float
    bias_correlation_s: float
    gyro_turn_on_dph: float
    accel_turn_on_ug: float
    gyro_sf_asymmetry_ppm: float


IMU_GRADES: dict[str, ImuGrade] = {
    name: ImuGrade(*figures)
    for name, *figures in (
        # name,          ARW,   VRW,  BI g,  BI a,  τ,     turn-on g, turn-on a, SF asym.
        ("nav",           0.002, 10.0, 0.005, 2.0,   600.0, 0.0061,    25.0,      1.0),
        ("kvh1760",       0.012, 120.0, 0.05, 50.0,  300.0, 0.26,      410.0,     20.0),
        ("tactical-mems", 0.15,  40.0, 0.5,   10.0,  100.0, 4.6,       700.0,     200.0),
        ("consumer",      1.0,   200.0, 10.0, 100.0, 60.0,  177.0,     20400.0,   2000.0),
        ("stim300",       0.15,  40.8, 0.3,   5.0,   100.0, 2.55,      646.0,     101.0),
    )
}
"""The turn-on figures are the rms over the axes of each class's stated turn-on biases, ⊕ its bias
instability (kvh1760: rms(0.3, 0.2, 0.25) °/h ⊕ 0.05 °/h = 0.26 °/h; rms(500, 400, 300) µg ⊕ 50 µg
= 410 µg; stim300, TS1524 rev.31 Tables 5-3/5-5 as firmware_sim's preset: rms(3, 2.5, 2) °/h ⊕ 0.3 °/h
= 2.55 °/h, rms(800, 600, 500) µg ⊕ 5 µg = 646 µg, SF asymmetry rms(100, 80, 120) = 101 ppm)."""


def imu_grade(name: str) -> ImuGrade:
    """The class by name; an InputError naming the known ones otherwise."""
    grade = IMU_GRADES.get(str(name))
    if grade is None:
        raise InputError(
            f"IMU grade {name!r} is not known: use one of {', '.join(IMU_GRADES)} (or leave it out "
            "for conservative default noise)"
        )
    return grade
