"""Trajectory optimisation: shooting, multiple shooting and hybrid iLQR."""
