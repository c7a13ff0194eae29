"""hybridjax: hybrid dynamical systems in JAX, batched and differentiable.

A hybrid system H = (J, Gamma, D, F, G, R) is a set of `Mode`s (flows on domains) and
`Transition`s (guards and resets), collected in a `HybridSystem`; `simulate` runs one
execution of it (vmap it for thousands) and returns a `Solution`.
"""

from . import examples as examples
from ._ilqr import HybridILQRResult as HybridILQRResult
from ._ilqr import HybridLQRProblem as HybridLQRProblem
from ._ilqr import hybrid_ilqr as hybrid_ilqr
from ._montecarlo import MonteCarloResult as MonteCarloResult
from ._montecarlo import monte_carlo as monte_carlo
from ._montecarlo import wilson_interval as wilson_interval
from ._multiple_shooting import EpochGuess as EpochGuess
from ._multiple_shooting import MultipleShooting as MultipleShooting
from ._multiple_shooting import MultipleShootingResult as MultipleShootingResult
from ._multiple_shooting import multiple_shooting as multiple_shooting
from ._periodic import PeriodicOrbit as PeriodicOrbit
from ._periodic import periodic_orbit as periodic_orbit
from ._presets import PRESET_NAMES as PRESET_NAMES
from ._presets import accuracy_preset as accuracy_preset
from ._scene import Constraint as Constraint
from ._scene import ContactSystem as ContactSystem
from ._scene import Relabel as Relabel
from ._scene import Scene as Scene
from ._scene import contact_system as contact_system
from ._properties import PropertyReport as PropertyReport
from ._properties import check_properties as check_properties
from ._saltation import VariationalJacobian as VariationalJacobian
from ._saltation import saltation_matrix as saltation_matrix
from ._saltation import variational_jacobian as variational_jacobian
from ._search import Witness as Witness
from ._search import box_samples as box_samples
from ._search import constraint_violation as constraint_violation
from ._search import find_point as find_point
from ._shooting import Shooting as Shooting
from ._shooting import ShootingResult as ShootingResult
from ._shooting import shoot as shoot
from ._shooting import with_running_cost as with_running_cost
from ._simulate import simulate as simulate
from ._simulate_batch import simulate_batch as simulate_batch
from ._solution import Epoch as Epoch
from ._solution import Solution as Solution
from ._status import STATUS_NAMES as STATUS_NAMES
from ._status import Status as Status
from ._system import HybridSystem as HybridSystem
from ._system import Mode as Mode
from ._system import Transition as Transition
from ._system import ZenoCompletion as ZenoCompletion
from ._validation import DefinitionError as DefinitionError

__version__ = "0.1.0"
from ._friction import FrictionSystem as FrictionSystem
from ._zeno import ZenoOptions as ZenoOptions
