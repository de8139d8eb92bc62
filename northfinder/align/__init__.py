"""Strapdown alignment without a turntable: swaying base (inertial frame) and GNSS-aided."""
