r"""Contact laws: how a contact's impact ends, and what its tangential force does while it is held.

A `Constraint` derives its two laws from its fields (`Constraint.impact_law`,
`Constraint.tangential_law`); the builders ask the laws, not the fields. A law is one class:

- impact laws (`AbstractImpactLaw`): the coefficient $e$ of Newton's law $\dot a^+ = -e \dot a^-$
  on the contact's gap row, and whether the contact leaves the contact set after its impact
  (`Plastic`: $e = 0$, it stays; `Newton`: $e$ given, it leaves unless $e$ is the number 0);
- tangential laws (`AbstractTangentialLaw`): the contact states of a held contact, for each
  whether its tangent row $\dot b = 0$ is held and the sign $s$ of its slip, and the transitions
  that leave it other than a lift-off or an impact (`Frictionless`: one state, no tangent row;
  `Sticking`: one state, the tangent row held; `Coulomb`: stick, slip+ and slip-, A. M. Johnson,
  "Hybrid Dynamical Systems", section 1.1: the contact conditions are the modes).
"""

import abc
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx

HELD, STICK, SLIP_POS, SLIP_NEG = "held", "stick", "slip+", "slip-"


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
    r"""Newton's law with coefficient `e` (a number in $[0, 1]$ or `e(args)`): the contact leaves
    the set after its impact, unless `e` is the number 0."""

    e: float | Callable

    def coefficient(self, args: Any) -> Any:
        return self.e(args) if callable(self.e) else self.e

    @property
    def separates(self) -> bool:
        return callable(self.e) or self.e > 0


class AbstractTangentialLaw(eqx.Module):
    """What a held contact's tangential force does: its contact states (`states`; a law with one
    state names it `"held"`, and a mode names the contact alone), for each whether the tangent row
    is held and the slip sign, and the transitions between its states."""

    states: ClassVar[tuple[str, ...]] = (HELD,)

    def holds_tangent(self, state: str) -> bool:
        r"""True when the tangent row ($\dot b = 0$) is held in `state`."""
        return False

    def slip_sign(self, state: str) -> float:
        r"""The sign $s$ of a slipping state ($s \dot b > 0$), 0 otherwise."""
        return 0.0

    def coefficient(self, args: Any) -> Any:
        r"""The friction coefficient $\mu$ under `args` (0 without a friction limit)."""
        return 0.0

    def changes(self, state: str) -> tuple[tuple[str, Any, str], ...]:
        """The transitions out of `state` between the law's states, as (kind, detail, new state):
        `("slip", d, ...)` when a sticking contact starts slipping in direction d, `("stop",
        True, ...)` when a slipping one stops and sticks, `("stop", None, ...)` when it reverses."""
        return ()


class Frictionless(AbstractTangentialLaw):
    """No tangential force: one state, no tangent row."""


class Sticking(AbstractTangentialLaw):
    r"""Unlimited friction (a `tangent` without `friction`): one state, $\dot b = 0$ held with the
    gap, its force free in sign."""

    def holds_tangent(self, state: str) -> bool:
        return True


class Coulomb(AbstractTangentialLaw):
    r"""Coulomb friction with coefficient `mu` (a number $\ge 0$ or `mu(args)`): stick ($\dot b = 0$
    held, $|\lambda_t| \le \mu \lambda_n$), slip+ and slip- ($\lambda_t = -\mu s \lambda_n$)."""

    mu: float | Callable
    states: ClassVar[tuple[str, ...]] = (STICK, SLIP_POS, SLIP_NEG)

    def holds_tangent(self, state: str) -> bool:
        return state == STICK

    def slip_sign(self, state: str) -> float:
        return {SLIP_POS: 1.0, SLIP_NEG: -1.0}.get(state, 0.0)

    def coefficient(self, args: Any) -> Any:
        return self.mu(args) if callable(self.mu) else self.mu

    def changes(self, state: str) -> tuple[tuple[str, Any, str], ...]:
        if state == STICK:
            return (("slip", 1.0, SLIP_POS), ("slip", -1.0, SLIP_NEG))
        other = SLIP_NEG if state == SLIP_POS else SLIP_POS
        return (("stop", True, STICK), ("stop", None, other))
