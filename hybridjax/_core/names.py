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


def bounds_of(owner: str, bounds: Any, shorthands: dict[str, Any]) -> tuple[Any, Any]:
    """A box as `(lower, upper)`: `bounds` itself, or built from the shorthands `lower` and
    `upper` (popped from `shorthands`; None counts as not passed, a missing side stays None).
    `bounds` with either shorthand is a `ValueError` naming both; `bounds` that is not a pair a
    `ValueError` naming the field."""
    given = {name: shorthands.pop(name) for name in ("lower", "upper") if name in shorthands}
    given = {name: value for name, value in given.items() if value is not None}
    if bounds is None:
        return given.get("lower"), given.get("upper")
    if given:
        names = " and ".join(["bounds", *given])
        raise ValueError(f"{owner}: {names} are the same option under two names; pass bounds=(lower, upper).")
    if not isinstance(bounds, tuple | list) or len(bounds) != 2:
        raise ValueError(f"{owner}: bounds must be a pair (lower, upper), got {bounds!r}.")
    return tuple(bounds)
