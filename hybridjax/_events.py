"""The event rules under this module's name: `_rules` holds them (one function per rule)."""

from ._rules import (  # noqa: F401
    carries_step,
    departure_step_bound,
    dip_candidates,
    first_crossings,
    first_step,
    locate_minimum,
    locate_root,
    nonfinite_step,
    start_decision,
    step_collapsed,
    strictly_inside,
    trending_negative,
)
