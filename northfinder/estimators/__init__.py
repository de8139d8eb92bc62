"""Pure-numpy estimators for the turntable north finder (paper: turntable-north-seeking-leveling-algorithms)."""
