r"""Contact laws: how a contact's impact ends, and what its tangential force does while it is held.

A `Constraint` takes its two laws as objects (`restitution=`, `friction=`) or derives them from
numbers (`Constraint.impact_law`, `Constraint.tangential_law`); the builders ask the laws, not
the fields. A new law is one class.

**Impact laws** (`AbstractImpactLaw`): Newton's law on the contact's gap row,
$\dot a^+ = -e\, \dot a^-$, with the coefficient $e$ under `args`, and whether the contact leaves
the contact set after its impact (`Plastic`: $e = 0$, it stays; `Newton`: $e$ given, it leaves
unless $e$ is the number 0).

**Tangential laws** (`AbstractTangentialLaw`): the contact states of a held contact (A. M.
Johnson, "Hybrid Dynamical Systems", section 1.1: the contact conditions are the modes), and
for each state

- whether the tangent row $\dot b = 0$ is held (`holds_tangent`: a sticking state);
- the sign $s = \pm 1$ of a slipping state ($s \dot b > 0$; `slip_sign`) and its force,
  $\lambda_t = -\mu_\text{slip}\, s\, \lambda_n$ (`slip_coefficient`);
- the stick limit $\mu_\text{stick}(d)$ per slip direction $d = \pm 1$ (`stick_limit`): a
  sticking contact stays while $\mu_\text{stick}(d) \lambda_n + d \lambda_t \ge 0$ for both $d$,
  i.e. $-\mu_\text{stick}(+1) \lambda_n \le \lambda_t \le \mu_\text{stick}(-1) \lambda_n$, leaves
  into slip $d$ where $\mu_\text{stick}(d) \lambda_n + d \lambda_t \le 0$, and a slipping contact
  that stops sticks where its sticking force satisfies both;
- the transitions between its states other than a lift-off or an impact (`changes`).

Built in: `Frictionless` (one state, no tangent row), `Sticking` (one state, the tangent row
held), `Coulomb` ($\mu_\text{slip} = \mu_\text{stick} = \mu$: stick, slip+ and slip-) and
`StaticKineticCoulomb` ($\mu_\text{stick} = \mu_s \ge \mu_\text{slip} = \mu_k$). The friction
builder's states are named `"stick"`, `"slip+"` and `"slip-"` (one held state: `"held"`); a
stick-slip law uses these names.
"""

import abc
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import numpy as np

HELD, STICK, SLIP_POS, SLIP_NEG = "held", "stick", "slip+", "slip-"


def _value(x, args):
    """A coefficient given as a number or as a function of args, under `args`."""
    return x(args) if callable(x) else x


def _concrete(x) -> bool:
    """A number (or a scalar array with a value) rather than a function or a traced value."""
    return not callable(x) and not isinstance(x, jax.core.Tracer)


def check_coefficient(owner: str, field: str, x, upper: float | None = None) -> None:
    """A coefficient is a number >= 0 (and <= `upper`) or a function of args; the error names
    `owner` and `field`. A traced value is checked where the build reads it."""
    if not _concrete(x):
        return
    number = not isinstance(x, bool) and np.ndim(x) == 0 and np.issubdtype(np.asarray(x).dtype, np.number)
    if not number or not x >= 0 or (upper is not None and x > upper):
        bound = ">= 0" if upper is None else f"in [0, {upper:g}]"
        raise ValueError(f"{owner}: `{field}` must be a number {bound} or a function of args, got {x!r}.")


class AbstractImpactLaw(eqx.Module):
    r"""How an impact on a unilateral contact ends: $\dot a^+ = -e\, \dot a^-$ on its gap row."""

    @abc.abstractmethod
    def coefficient(self, args: Any) -> Any:
        """The coefficient of restitution $e$ under `args`."""

    @property
    @abc.abstractmethod
    def separates(self) -> bool:
        """True when the contact leaves the contact set after its impact."""


class Plastic(AbstractImpactLaw):
    r"""A plastic impact: $e = 0$, the contact is held after it."""

    def coefficient(self, args: Any) -> Any:
        return 0.0

    @property
    def separates(self) -> bool:
        return False


class Newton(AbstractImpactLaw):
    r"""Newton's law $\dot a^+ = -e\, \dot a^-$ with coefficient `e` (a number in $[0, 1]$ or
    `e(args)`): the contact leaves the set after its impact, unless `e` is the number 0."""

    e: float | Callable

    def __check_init__(self):
        check_coefficient("Newton", "e", self.e, upper=1.0)

    def coefficient(self, args: Any) -> Any:
        return _value(self.e, args)

    @property
    def separates(self) -> bool:
        return callable(self.e) or self.e > 0


class AbstractTangentialLaw(eqx.Module):
    r"""What a held contact's tangential force does: its contact states (`states`; a law with one
    state names it `"held"`, and a mode names the contact alone), for each whether the tangent
    row is held, the slip sign and the slip force coefficient, the stick limits, and the
    transitions between its states. The defaults are a one-state law without friction.

    !!! Example

        ```python
        class Anisotropic(hj.AbstractTangentialLaw):  # mu_pos against motion towards +b
            mu_pos: float
            mu_neg: float
            states = ("stick", "slip+", "slip-")

            def holds_tangent(self, state): return state == "stick"
            def slip_sign(self, state): return {"slip+": 1.0, "slip-": -1.0}.get(state, 0.0)
            def slip_coefficient(self, state, args): return self.mu_pos if state == "slip+" else self.mu_neg
            def stick_limit(self, d, args): return self.mu_pos if d > 0 else self.mu_neg
            def changes(self, state):
                if state == "stick":
                    return (("slip", 1.0, "slip+"), ("slip", -1.0, "slip-"))
                return (("stop", True, "stick"), ("stop", None, "slip-" if state == "slip+" else "slip+"))
        ```
    """

    states: ClassVar[tuple[str, ...]] = (HELD,)

    def holds_tangent(self, state: str) -> bool:
        r"""True when the tangent row ($\dot b = 0$) is held in `state`."""
        return False

    def slip_sign(self, state: str) -> float:
        r"""The sign $s$ of a slipping state ($s \dot b > 0$), 0 otherwise."""
        return 0.0

    def slip_coefficient(self, state: str, args: Any) -> Any:
        r"""$\mu_\text{slip}$ of slipping `state` under `args`: its friction force is
        $\lambda_t = -\mu_\text{slip}\, s\, \lambda_n$."""
        return 0.0

    def stick_limit(self, d: float, args: Any) -> Any:
        r"""$\mu_\text{stick}(d)$ under `args` for the slip direction $d = \pm 1$: a sticking
        contact holds while $\mu_\text{stick}(d) \lambda_n + d \lambda_t \ge 0$."""
        return 0.0

    def changes(self, state: str) -> tuple[tuple[str, Any, str], ...]:
        """The transitions out of `state` between the law's states, as (kind, detail, new state):
        `("slip", d, ...)` when a sticking contact starts slipping in direction d, `("stop",
        True, ...)` when a slipping one stops and sticks, `("stop", None, ...)` when it reverses."""
        return ()

    def check(self, args: Any) -> str | None:
        """What is wrong with the law's coefficients under `args` (checked for every `args`
        value of a build), None when nothing is."""
        return None


def slip_state(law: AbstractTangentialLaw, s: float) -> str | None:
    """The state of `law` that slips with sign `s`, None if it has none."""
    return next((st for st in law.states if law.slip_sign(st) == s), None)


class Frictionless(AbstractTangentialLaw):
    """No tangential force: one state, no tangent row."""


class Sticking(AbstractTangentialLaw):
    r"""Unlimited friction (a `tangent` without `friction`): one state, $\dot b = 0$ held with the
    gap, its force free in sign."""

    def holds_tangent(self, state: str) -> bool:
        return True


class _AbstractStickSlip(AbstractTangentialLaw):
    """Stick, slip+ and slip-: the states and transitions of Coulomb-type laws; the subclass
    gives the coefficients."""

    states: ClassVar[tuple[str, ...]] = (STICK, SLIP_POS, SLIP_NEG)

    def holds_tangent(self, state: str) -> bool:
        return state == STICK

    def slip_sign(self, state: str) -> float:
        return {SLIP_POS: 1.0, SLIP_NEG: -1.0}.get(state, 0.0)

    def changes(self, state: str) -> tuple[tuple[str, Any, str], ...]:
        if state == STICK:
            return (("slip", 1.0, SLIP_POS), ("slip", -1.0, SLIP_NEG))
        other = SLIP_NEG if state == SLIP_POS else SLIP_POS
        return (("stop", True, STICK), ("stop", None, other))

    @abc.abstractmethod
    def slip_coefficient(self, state: str, args: Any) -> Any: ...

    @abc.abstractmethod
    def stick_limit(self, d: float, args: Any) -> Any: ...


class Coulomb(_AbstractStickSlip):
    r"""Coulomb friction with coefficient `mu` (a number $\ge 0$ or `mu(args)`): stick
    ($\dot b = 0$ held, $|\lambda_t| \le \mu \lambda_n$), slip+ and slip-
    ($\lambda_t = -\mu s \lambda_n$). `friction=mu` on a `Constraint` is `Coulomb(mu)`."""

    mu: float | Callable

    def __check_init__(self):
        check_coefficient("Coulomb", "mu", self.mu)

    def coefficient(self, args: Any) -> Any:
        r"""$\mu$ under `args`."""
        return _value(self.mu, args)

    def slip_coefficient(self, state: str, args: Any) -> Any:
        return _value(self.mu, args)

    def stick_limit(self, d: float, args: Any) -> Any:
        return _value(self.mu, args)


class StaticKineticCoulomb(_AbstractStickSlip):
    r"""Coulomb friction with a static coefficient `mu_static` $\mu_s$ and a kinetic one
    `mu_kinetic` $\mu_k$, $\mu_s \ge \mu_k \ge 0$ (numbers or functions of args): a sticking
    contact holds while $|\lambda_t| \le \mu_s \lambda_n$, a slipping one feels
    $\lambda_t = -\mu_k s \lambda_n$. A block on a slope with $\mu_k < \tan\theta \le \mu_s$
    stays where it stops; with Coulomb's $\mu = \mu_k$ it slides back down.

    !!! Example

        ```python
        floor = hj.Constraint("floor", gap, tangent=along, friction=hj.StaticKineticCoulomb(0.6, 0.4))
        ```
    """

    mu_static: float | Callable
    mu_kinetic: float | Callable

    def __check_init__(self):
        check_coefficient("StaticKineticCoulomb", "mu_static", self.mu_static)
        check_coefficient("StaticKineticCoulomb", "mu_kinetic", self.mu_kinetic)
        if _concrete(self.mu_static) and _concrete(self.mu_kinetic) and self.mu_static < self.mu_kinetic:
            raise ValueError(
                f"StaticKineticCoulomb: `mu_static` must be >= `mu_kinetic`, got {self.mu_static!r} < "
                f"{self.mu_kinetic!r}."
            )

    def slip_coefficient(self, state: str, args: Any) -> Any:
        return _value(self.mu_kinetic, args)

    def stick_limit(self, d: float, args: Any) -> Any:
        return _value(self.mu_static, args)

    def check(self, args: Any) -> str | None:
        ms, mk = _value(self.mu_static, args), _value(self.mu_kinetic, args)
        if not ms >= mk:
            return f"`mu_static` must be >= `mu_kinetic`, got {ms} < {mk}"
        return None
