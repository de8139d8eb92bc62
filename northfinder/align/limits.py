"""Valid input ranges of the align estimators (swaying cone fit, coarse TRIAD, GNSS/INS filter).

One place for the limit and its words: config.py checks `[site] latitude_deg`, the align CLI
checks `--latitude`, and each estimator checks its argument again, all with `latitude_problem`,
so the same mistake reads the same in every mode.
"""

from __future__ import annotations

import math

LATITUDE_LIMIT_DEG = 85.0
"""|L| above which the align estimators refuse [deg]. Gyrocompassing resolves north from the
horizontal Earth rate Ωe·cos L (swaying paper eq 2; coarse TRIAD on ω × f): at 85° it is
1.3 °/h, and the heading noise grows as 1/cos L. The GNSS/INS filter's north/east local-level
frame is singular at the pole. The turntable find has its own, wider limit
(northfinder.estimators.heading.MAX_ABS_LATITUDE_DEG)."""

LATITUDE_ADVICE = (
    f"use −{LATITUDE_LIMIT_DEG:g}…{LATITUDE_LIMIT_DEG:g} degrees (north positive); nearer the pole the "
    "Earth axis has no usable horizontal projection"
)


def latitude_problem(latitude_deg: float) -> str | None:
    """None when the align estimators can use `latitude_deg`; else what to do (one clause the
    caller prefixes with the flag or key it came from)."""
    if isinstance(latitude_deg, int | float) and math.isfinite(latitude_deg) and (
        abs(latitude_deg) <= LATITUDE_LIMIT_DEG
    ):
        return None
    return LATITUDE_ADVICE
