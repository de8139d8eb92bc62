"""Pure-numpy estimators for the turntable north finder.

Paper: turntable-north-seeking-leveling-algorithms (Liu, Yuan, Zhou 2011). Entry point:
northfinder.estimators.heading.solve_heading (also `from northfinder import solve_heading`).
"""
