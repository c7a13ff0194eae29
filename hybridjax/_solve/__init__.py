"""The entry points: `simulate`, `simulate_batch`, and compilation for direct calls."""
