"""hybridjax: hybrid dynamical systems in JAX, batched and differentiable.

A hybrid system H = (J, Gamma, D, F, G, R) is a set of `Mode`s (flows on domains) and
`Transition`s (guards and resets), collected in a `HybridSystem`; `simulate` runs one
execution of it (vmap it for thousands) and returns a `Solution`.
"""

import importlib as _importlib
from typing import TYPE_CHECKING as _TYPE_CHECKING

from . import examples as examples
from ._core.status import STATUS_NAMES as STATUS_NAMES
from ._core.status import Status as Status
from ._definition.system import AbstractHybridSystem as AbstractHybridSystem
from ._definition.system import HybridSystem as HybridSystem
from ._definition.system import Mode as Mode
from ._definition.system import Transition as Transition
from ._definition.system import ZenoCompletion as ZenoCompletion
from ._definition.validation import DefinitionError as DefinitionError
from ._rules.locate import AbstractEventLocator as AbstractEventLocator
from ._rules.locate import BracketedNewton as BracketedNewton
from ._rules.options import EventOptions as EventOptions
from ._rules.options import SolveOptions as SolveOptions
from ._rules.zeno import ZenoOptions as ZenoOptions
from ._solution.solution import Epoch as Epoch
from ._solution.solution import Solution as Solution
from ._solve.engines import AbstractEngine as AbstractEngine
from ._solve.engines import AutoEngine as AutoEngine
from ._solve.engines import BatchedEngine as BatchedEngine
from ._solve.engines import DiffraxEngine as DiffraxEngine
from ._solve.engines import FastEngine as FastEngine
from ._solve.engines import VmapEngine as VmapEngine
from ._solve.simulate import simulate as simulate
from ._solve.simulate_batch import simulate_batch as simulate_batch
from ._solve.simulator import Simulator as Simulator

__version__ = "0.1.0"

# Analysis, estimation, optimisation and scenes are imported on the first use of one of their
# names (PEP 562), so that `import hybridjax` loads only what `simulate` needs: a notebook's
# first call pays for the rest only when it uses it.
_LAZY = {
    "._analysis.montecarlo": ("MonteCarloResult", "monte_carlo", "wilson_interval"),
    "._analysis.periodic": ("PeriodicOrbit", "periodic_orbit"),
    "._analysis.presets": ("PRESET_NAMES", "accuracy_preset"),
    "._analysis.properties": (
        "Achievable", "Chain", "Gap", "Overlap", "PropertyReport", "ResetOutside",
        "check_properties",
    ),
    "._analysis.saltation": ("VariationalJacobian", "saltation_matrix", "variational_jacobian"),
    "._analysis.search": ("SearchOptions", "Witness", "box_samples", "constraint_violation", "find_point"),
    "._analysis.sensitivity": (
        "DGSMResult", "MorrisResult", "SensitivityOptions", "SobolResult", "dgsm",
        "execution_model", "morris_effects", "sample", "sobol_indices",
    ),
    "._estimation.kalman": ("KalmanResult", "SaltedKalmanFilter"),
    "._optimise.ilqr": ("HybridILQR", "HybridILQRResult", "HybridLQRProblem", "hybrid_ilqr"),
    "._optimise.multiple_shooting": (
        "EpochGuess", "MultipleShooting", "MultipleShootingCheck", "MultipleShootingResult",
        "MultipleShootingStatus", "multiple_shooting",
    ),
    "._optimise.shooting": ("Shooting", "ShootingResult", "shoot", "with_running_cost"),
    "._scenes.build": ("contact_system",),
    "._scenes.laws": (
        "AbstractImpactLaw", "AbstractTangentialLaw", "Coulomb", "Frictionless", "Newton",
        "Plastic", "StaticKineticCoulomb", "Sticking",
    ),
    "._scenes.scene": ("Constraint", "ContactSystem", "Relabel", "Scene"),
    "._scenes.friction": ("FrictionSystem",),
}
_LAZY_NAMES = {name: module for module, names in _LAZY.items() for name in names}


def __getattr__(name: str):
    module = _LAZY_NAMES.get(name)
    if module is None:
        raise AttributeError(f"module 'hybridjax' has no attribute {name!r}")
    value = getattr(_importlib.import_module(module, __name__), name)
    globals()[name] = value  # later look-ups find it without this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY_NAMES))


__all__ = sorted({n for n in globals() if not n.startswith("_")} | set(_LAZY_NAMES))

if _TYPE_CHECKING:  # the same names, for type checkers and the docs' static analysis
    from ._analysis.montecarlo import MonteCarloResult as MonteCarloResult
    from ._analysis.montecarlo import monte_carlo as monte_carlo
    from ._analysis.montecarlo import wilson_interval as wilson_interval
    from ._analysis.periodic import PeriodicOrbit as PeriodicOrbit
    from ._analysis.periodic import periodic_orbit as periodic_orbit
    from ._analysis.presets import PRESET_NAMES as PRESET_NAMES
    from ._analysis.presets import accuracy_preset as accuracy_preset
    from ._analysis.properties import Achievable as Achievable
    from ._analysis.properties import Chain as Chain
    from ._analysis.properties import Gap as Gap
    from ._analysis.properties import Overlap as Overlap
    from ._analysis.properties import PropertyReport as PropertyReport
    from ._analysis.properties import ResetOutside as ResetOutside
    from ._analysis.properties import check_properties as check_properties
    from ._analysis.saltation import VariationalJacobian as VariationalJacobian
    from ._analysis.saltation import saltation_matrix as saltation_matrix
    from ._analysis.saltation import variational_jacobian as variational_jacobian
    from ._analysis.search import SearchOptions as SearchOptions
    from ._analysis.search import Witness as Witness
    from ._analysis.search import box_samples as box_samples
    from ._analysis.search import constraint_violation as constraint_violation
    from ._analysis.search import find_point as find_point
    from ._analysis.sensitivity import DGSMResult as DGSMResult
    from ._analysis.sensitivity import MorrisResult as MorrisResult
    from ._analysis.sensitivity import SensitivityOptions as SensitivityOptions
    from ._analysis.sensitivity import SobolResult as SobolResult
    from ._analysis.sensitivity import dgsm as dgsm
    from ._analysis.sensitivity import execution_model as execution_model
    from ._analysis.sensitivity import morris_effects as morris_effects
    from ._analysis.sensitivity import sample as sample
    from ._analysis.sensitivity import sobol_indices as sobol_indices
    from ._estimation.kalman import KalmanResult as KalmanResult
    from ._estimation.kalman import SaltedKalmanFilter as SaltedKalmanFilter
    from ._optimise.ilqr import HybridILQR as HybridILQR
    from ._optimise.ilqr import HybridILQRResult as HybridILQRResult
    from ._optimise.ilqr import HybridLQRProblem as HybridLQRProblem
    from ._optimise.ilqr import hybrid_ilqr as hybrid_ilqr
    from ._optimise.multiple_shooting import EpochGuess as EpochGuess
    from ._optimise.multiple_shooting import MultipleShooting as MultipleShooting
    from ._optimise.multiple_shooting import MultipleShootingCheck as MultipleShootingCheck
    from ._optimise.multiple_shooting import MultipleShootingResult as MultipleShootingResult
    from ._optimise.multiple_shooting import MultipleShootingStatus as MultipleShootingStatus
    from ._optimise.multiple_shooting import multiple_shooting as multiple_shooting
    from ._optimise.shooting import Shooting as Shooting
    from ._optimise.shooting import ShootingResult as ShootingResult
    from ._optimise.shooting import shoot as shoot
    from ._optimise.shooting import with_running_cost as with_running_cost
    from ._scenes.build import contact_system as contact_system
    from ._scenes.friction import FrictionSystem as FrictionSystem
    from ._scenes.laws import AbstractImpactLaw as AbstractImpactLaw
    from ._scenes.laws import AbstractTangentialLaw as AbstractTangentialLaw
    from ._scenes.laws import Coulomb as Coulomb
    from ._scenes.laws import Frictionless as Frictionless
    from ._scenes.laws import Newton as Newton
    from ._scenes.laws import Plastic as Plastic
    from ._scenes.laws import StaticKineticCoulomb as StaticKineticCoulomb
    from ._scenes.laws import Sticking as Sticking
    from ._scenes.scene import Constraint as Constraint
    from ._scenes.scene import ContactSystem as ContactSystem
    from ._scenes.scene import Relabel as Relabel
    from ._scenes.scene import Scene as Scene
