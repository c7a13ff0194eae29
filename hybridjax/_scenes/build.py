"""`contact_system`: a scene's hybrid system, from the builder of its contact laws (frictionless
contact sets, or stick and slip states where a contact has friction)."""

from collections.abc import Sequence
from typing import Any

from jaxtyping import PRNGKeyArray

from .._analysis.search import SearchOptions, search_options
from .friction import friction_system
from .frictionless import frictionless_system
from .scene import AbstractContactSystem, Relabel, Scene, point_search_key


def contact_system(
    scene: Scene,
    initial: Sequence,
    args: Any = None,
    *,
    args_values: Sequence | None = None,
    num_samples: int = 512,
    margin: float = 1e-3,
    key: PRNGKeyArray | None = None,
    redundant: str = "error",
    form: str = "mask",
    max_modes: int = 64,
    relabels: Sequence[Relabel] = (),
    search: SearchOptions | None = None,
    **shorthands,
) -> AbstractContactSystem:
    r"""Build the hybrid system of `scene`, with only the contact sets it reaches.

    Starting from the `initial` contact sets, each transition out of a built set (an impact of
    each open contact with each release candidate, a lift-off of each held contact) is kept
    when the point search finds a witness state in its guard for one of the `args` values
    (the conditions: docs, Scenes, "Only what the scene requires"); its target set is then built too. What is
    never found is pruned and listed, with the reason, in the repr; a pruned transition still
    fires into a terminal mode `"unbuilt: <set>"` that ends the execution with `BLOCKED`.

    **Arguments:**

    - `scene`: the `Scene`.
    - `initial`: the initial contact sets, each a sequence of constraint names or a mode name
      (`"free"`, `"G+H"`); bilateral constraints are always held.
    - `args`: the scene's `args`; or `args_values`: a sequence of them (a slope angle's values,
      or samples of its range) to build over: a transition found for any of them is kept, and
      the repr says for which. A batch or a derivative across values that change the modes
      built needs a system built over all of them.
    - `num_samples`, `key`: the point search's samples, drawn in the scene's `bounds` x
      `t_bounds` (`key` a `jax.random` key, default `jax.random.key(0)`).
    - `margin`: the least approach speed of an impact and the least pulling force of a
      lift-off that a witness must show, in the scene's units.
    - `redundant`: `"error"` (a reachable contact set with dependent constraints raises,
      naming them) or `"least_norm"` (its contact forces are the least-norm solution).
    - `form`: `"mask"` (the default: the engines evaluate the system for the current mode in
      one solve with all constraints, those not held masked out, `ContactEvaluation`; the
      cost of a step and of its compile does not grow with the modes built) or `"branch"`
      (each mode's and each transition's own function, evaluated and selected under
      `jax.vmap`: every mode's solve in every step). Both give the same executions to
      rounding; the mask is faster to compile and to run (docs: Scenes, "What it costs").
      Scenes with friction too (`FrictionEvaluation`).
    - `max_modes`: a build that would exceed this many modes stops with an error.
    - `relabels`: `Relabel`s identifying symmetric contact sets (a transition into a `source`
      set goes to its `target` set, the state relabelled).
    - `search`: an `hj.SearchOptions` (`num_starts`, `iterations`, `tol`: how the best samples
      are refined, the violation accepted as zero), as in `find_point`.

    **Keyword shorthands** (passing one with the name it stands for is a `ValueError`):
    `seed=s` for `key=jax.random.key(s)`; `num_starts`, `iterations` (or `max_steps`), `tol`
    for `search=hj.SearchOptions(...)` with them.

    !!! Example

        ```python
        system = hj.contact_system(scene, initial=["free"], args={"g": 9.81})
        system              # modes, transitions, witnesses, and what was pruned and why
        sol = hj.simulate(system, x0, "free", 0.0, 2.0, {"g": 9.81})
        system.contact_forces(sol)
        ```
    """
    search = search_options("contact_system", search, shorthands)
    unknown = sorted(set(shorthands) - {"seed"})
    if unknown:
        raise TypeError(f"contact_system() got an unexpected keyword argument {unknown[0]!r}.")
    key = point_search_key(key, shorthands.get("seed"))
    if redundant not in ("error", "least_norm"):
        raise ValueError(f"contact_system: `redundant` must be 'error' or 'least_norm', got {redundant!r}.")
    if form not in ("branch", "mask"):
        raise ValueError(f"contact_system: `form` must be 'branch' or 'mask', got {form!r}.")
    friction = any(len(c.tangential_law.states) > 1 for c in scene.constraints)
    builder = friction_system if friction else frictionless_system
    return builder(
        scene, initial, args, args_values=args_values, num_samples=num_samples, search=search,
        margin=margin, key=key, redundant=redundant, max_modes=max_modes, relabels=relabels,
        form=form,
    )  # fmt: skip
