r"""Systems whose modes share one parametrised evaluation, for a mode index chosen at run time.

The engines carry the current mode as a traced integer. A `HybridSystem` written as separate
`Mode` and `Transition` functions is evaluated branch by branch: under `jax.vmap` every
mode's flow and every transition's guard is computed and one is selected, so the cost of a
step, and of tracing and compiling it, grows with the number of modes and transitions.

Some systems are one function with a per-mode parameter: the contact sets of a rigid-body
scene are masks over one list of constraints, and every mode's flow is the same constrained
dynamics with the mask of its set (A. M. Johnson, "Hybrid Dynamical Systems", section 1.1:
the modes of a body with contacts are the sets of active constraints). Such a system
implements `ModeIndexed`: the flow, the watched functions and the resets for a traced mode
(or transition) index, each in one call that looks its parameters up in tables. The
engines then evaluate it once per call, whatever the number of modes.

The per-mode `Mode` and `Transition` functions stay the definition: `ModeIndexed` must agree
with them (to rounding). The engines, and every tool that evaluates through `Kernels` (the
property checks), use `ModeIndexed`; the tools that take a mode's or a transition's own
function (saltation matrices, plots) use those. It is an internal extension point, not
exported.
"""

import abc

import equinox as eqx
import jax


class ModeIndexed(eqx.Module):
    r"""The flows, watched functions and resets of a system for a traced mode index.

    With $n$ the system's `max_dim` and the watched functions of mode $I$ in the engine's
    order (its outgoing transitions' guards in index order, then its domain components;
    `Kernels.mode_watch`), padded to `num_slots` entries with $+1$:

    - `flow(mode, t, y, args)` $= F_{\text{mode}}(t, y)$, shape $(n,)$;
    - `watch(mode, t, y, args)`: the watched values of `mode`, shape (`num_slots`,);
    - `reset(k, t, y, args)` $= R_k(t, y)$ of transition `k`, shape $(n,)$;
    - optionally `locate_watch` and `select`: transitions that share one guard function and
      differ by a choice made at the event state, located on the shared function alone.
    """

    @abc.abstractmethod
    def flow(self, mode, t, y, args) -> jax.Array:
        """The vector field of mode `mode` (a traced index) at (t, y)."""

    @abc.abstractmethod
    def watch(self, mode, t, y, args) -> jax.Array:
        """The watched values of mode `mode` in slot order, unused slots +1."""

    @abc.abstractmethod
    def reset(self, k, t, y, args) -> jax.Array:
        """The reset of transition `k` (a traced index) at (t, y)."""

    def locate_watch(self, mode, t, y, args) -> jax.Array:
        r"""The watched values the engines detect and locate events with (`Kernels` with
        `located=True`): `watch`, except where several transitions of a mode share one guard
        function $g$ and differ by a discrete choice made at the event state (which of them
        holds $g$'s crossing). There the first of them reads $g$, the others $+1$, and `select`
        names the one taken once the event is located. The events' times are those of `watch`
        (the transitions' guards cross zero where $g$ does, exactly one of them), and the choice
        is evaluated once per event rather than at every guard evaluation of every step."""
        return self.watch(mode, t, y, args)

    def select(self, mode, slot, t, y, args) -> jax.Array:
        """The slot of `mode` whose transition is taken when the event located on `slot`
        (`locate_watch`) happens at (t, y); `slot` itself unless `locate_watch` shares a guard."""
        del mode, t, y, args
        return slot
