"""Checks of the values a user passes in options, shared by every options Module."""

import numpy as np


def check_int(owner: str, name: str, value, low: int) -> None:
    """A `ValueError` naming `owner` and its field `name` unless `value` is an int (Python or
    numpy, not a bool) of at least `low`."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{owner}: {name} must be an int >= {low}, got {value!r}.")
