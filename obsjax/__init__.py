"""obsjax: differentiable, batched state observers for control systems, in JAX and diffrax.

Importing obsjax turns on JAX's float64 mode (``jax_enable_x64``), because control designs are computed
in double precision; this is the one global side effect of the import.  Set the environment variable
``OBSJAX_NO_X64=1`` before the import to opt out (public entry points then raise instead of computing in
float32).

Importing obsjax also warns (:class:`JaxlibWarning`) when the installed jaxlib is a release known to
compute wrong results on the CPU (0.10.2); it changes no setting.
"""

from ._config import JaxlibWarning as JaxlibWarning
from ._config import check_jaxlib as _check_jaxlib
from ._config import enable_x64 as _enable_x64

_enable_x64()
_check_jaxlib()

from . import analysis as analysis
from . import design as design
from . import losses as losses
from . import noise as noise
from . import signals as signals
from ._cache import enable_compilation_cache as enable_compilation_cache
from ._trace_cache import enable_trace_cache as enable_trace_cache
from ._simulate import Trajectory as Trajectory
from ._simulate import simulate as simulate
from ._simulate_batch import simulate_batch as simulate_batch
from .observers._base import AbstractObserver as AbstractObserver
from .observers._luenberger import FunctionalObserver as FunctionalObserver
from .observers._luenberger import Luenberger as Luenberger
from .observers._luenberger import ReducedOrder as ReducedOrder
from .systems._plants import LTI as LTI
from .systems._plants import LTV as LTV
from .systems._plants import AbstractSystem as AbstractSystem
from .systems._plants import Nonlinear as Nonlinear
from .tuning._tune import TuneResult as TuneResult
from .tuning._tune import TuneWarning as TuneWarning
from .tuning._tune import risk_measure as risk_measure
from .tuning._tune import risk_weights as risk_weights
from .tuning._tune import tune as tune

# Observers by family
from .observers._tlo import TrajectoryLinearization as TrajectoryLinearization
from .observers._ekf import ExtendedKalman as ExtendedKalman
from .observers._generalized_inverse import GeneralizedInverse as GeneralizedInverse
from .observers._generalized_inverse import GeneralizedInverseReduced as GeneralizedInverseReduced
from .observers._minmax import MinMaxLuenberger as MinMaxLuenberger
from .observers._minmax import minmax_algorithm as minmax_algorithm
from .observers._minmax import minmax_initial_state as minmax_initial_state
from .observers._kreisselmeier import Kreisselmeier as Kreisselmeier
from .observers._kreisselmeier import kreisselmeier_form as kreisselmeier_form
from .observers._luders_narendra import LudersNarendra as LudersNarendra
from .observers._luders_narendra import luders_narendra_form as luders_narendra_form
from .observers._kudva_narendra import KudvaNarendra as KudvaNarendra
from .observers._kudva_narendra import ErrorModel1 as ErrorModel1
from .observers._kudva_narendra import ErrorModel2 as ErrorModel2
from .observers._ls_identifier import LeastSquaresIdentifier as LeastSquaresIdentifier
from .observers._minimal_adaptive import MinimalAdaptiveObserver as MinimalAdaptiveObserver
from .observers._nonminimal_adaptive import NonMinimalAdaptiveObserver as NonMinimalAdaptiveObserver
from .observers._finite_window import FiniteWindow as FiniteWindow
from .observers._least_squares import LeastSquaresReset as LeastSquaresReset
from .observers._least_squares import LeastSquaresState as LeastSquaresState
from .observers._least_squares import chen_yen_example as chen_yen_example
from .observers._kalman_bucy import KalmanBucy as KalmanBucy
from .observers._kalman_bucy import KalmanBucyState as KalmanBucyState
from .observers._least_squares import switching_ltv_example as switching_ltv_example
from .montecarlo import MonteCarloResult as MonteCarloResult
from .montecarlo import monte_carlo as monte_carlo

__version__ = "0.1.0"
from .observers._generalized_inverse import GeneralizedInverseODE as GeneralizedInverseODE
from .observers._minmax import minmax_sum_initial_state as minmax_sum_initial_state
from .observers._finite_window import FiniteWindowLTV as FiniteWindowLTV
from .observers._finite_window import delay_closed_loop as delay_closed_loop
from .design._tlc import TrajectoryLinearizationController as TrajectoryLinearizationController
from .design._tlc import dynamic_inversion as dynamic_inversion
from ._data._measurements import Measurements as Measurements
from ._data._estimate import Estimate as Estimate
from ._data._estimate import estimate as estimate
from .observers._cd_kalman import ContinuousDiscreteKalman as ContinuousDiscreteKalman
from .observers._cd_kalman import ContinuousDiscreteKalmanState as ContinuousDiscreteKalmanState
from .tuning._tune_data import tune_on_data as tune_on_data
