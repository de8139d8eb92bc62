"""northfinder: true north from a gyro — turntable, swaying base, GNSS-aided.

Public entry point: :func:`solve_heading` (see northfinder.estimators.heading).
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["solve_heading", "__version__"]


def __getattr__(name: str):
    # Lazy so that `import northfinder` (CLI start-up, drivers) does not pay for scipy.
    if name == "solve_heading":
        from northfinder.estimators.heading import solve_heading

        return solve_heading
    raise AttributeError(name)
