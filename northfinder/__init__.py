"""northfinder: true north from a gyro — turntable, swaying base, GNSS-aided.

Public entry point: :func:`solve_heading` (see northfinder.estimators.heading).
"""

from __future__ import annotations

import os as _os

__version__ = "0.1.0"

# One BLAS thread unless the user set otherwise, before anything loads numpy (OpenBLAS reads these
# once). northfinder's matrices are small (≤ 9 columns); OpenBLAS's own threads only spin
# against the reader threads and the other process on a shared host: a QR of 8 k × 9 took 99 ms
# with them on the loaded 2-core bench host, 2.5 ms with one (issue 27).
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__all__ = ["solve_heading", "__version__"]


def __getattr__(name: str):
    # Lazy so that `import northfinder` (CLI start-up, drivers) does not pay for scipy.
    if name == "solve_heading":
        from northfinder.estimators.heading import solve_heading

        return solve_heading
    raise AttributeError(name)
