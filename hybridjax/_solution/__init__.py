"""The solution of a run and its dense output."""
