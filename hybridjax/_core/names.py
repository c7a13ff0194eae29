"""One option under two names: the name used across the package and another a caller may use."""

from typing import Any


def one_of(owner: str, *, default: Any, **given: Any) -> Any:
    """The value of an option that has two keyword names (`given`: name=value, the package-wide
    name first, None where not passed): the one passed, `default` where neither was; passing
    both is a `ValueError` naming them."""
    passed = {name: value for name, value in given.items() if value is not None}
    if len(passed) > 1:
        names = " and ".join(passed)
        raise ValueError(f"{owner}: {names} are the same option under two names; pass one of them.")
    return next(iter(passed.values()), default)
