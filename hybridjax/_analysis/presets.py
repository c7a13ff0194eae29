"""Accuracy presets: named solver/tolerance choices for `simulate`, scaled to the dtype."""

import diffrax
import jax.numpy as jnp
from jaxtyping import DTypeLike

# name -> (solver, rtol = atol, event_tol) for float64 and for float32. float32 resolves
# about 1e-7 relative, so its tolerances stop at 1e-6 (see `simulate`'s warning below 8 eps).
_PRESETS = {
    "fast": {"float64": (diffrax.Tsit5, 1e-5, 1e-8), "float32": (diffrax.Bosh3, 1e-3, 1e-4)},
    "balanced": {"float64": (diffrax.Tsit5, 1e-8, 1e-12), "float32": (diffrax.Tsit5, 1e-5, 1e-6)},
    "precise": {"float64": (diffrax.Dopri5, 1e-12, 1e-13), "float32": (diffrax.Tsit5, 1e-6, 1e-6)},
}
PRESET_NAMES = tuple(_PRESETS)


def accuracy_preset(name: str, dtype: DTypeLike = jnp.float64) -> dict:
    """Keyword arguments for `simulate` that trade speed for accuracy, by name.

    | name | float64 | float32 |
    |---|---|---|
    | `"fast"` | Tsit5, rtol = atol = 1e-5, event_tol 1e-8 | Bosh3, 1e-3, 1e-4 |
    | `"balanced"` (the defaults) | Tsit5, 1e-8, 1e-12 | Tsit5, 1e-5, 1e-6 |
    | `"precise"` | Dopri5, 1e-12, 1e-13 | Tsit5, 1e-6, 1e-6 |

    (Dopri8 is not the precise choice with events: on the benchmark problems its events,
    located on its dense output over its long steps, are less accurate than Dopri5's at the
    same tolerance.)

    Their measured cost and error on the benchmark problems are in the documentation's
    "Work-precision and baselines" page (`benchmarks/work_precision.py`). Use as
    `hj.simulate(..., **hj.accuracy_preset("fast"))`; pass the dtype of `x0` when it is float32.
    """
    if name not in _PRESETS:
        raise ValueError(f"unknown accuracy preset {name!r}; choose one of {PRESET_NAMES}.")
    key = jnp.dtype(dtype).name
    if key not in ("float64", "float32"):
        raise ValueError(f"accuracy presets exist for float64 and float32, not {key}.")
    solver, tol, event_tol = _PRESETS[name][key]
    return dict(solver=solver(), stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
                event_tol=event_tol)
