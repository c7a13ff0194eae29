"""Analysis of systems and runs: saltation matrices, periodic orbits, Monte Carlo, accuracy presets,
the point search and the property checks."""
