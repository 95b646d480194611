"""Analysis: observability, transition matrices, gramians, persistence of excitation, bounds, rates."""

from ._lti import ObservabilityStaircase as ObservabilityStaircase
from ._lti import is_observable as is_observable
from ._lti import observability_staircase as observability_staircase
from ._lti import obsv as obsv
from ._lti import pbh_margin as pbh_margin
from ._ltv import PersistentExcitation as PersistentExcitation
from ._ltv import UniformObservability as UniformObservability
from ._ltv import chen_yen_bound as chen_yen_bound
from ._ltv import decay_rate as decay_rate
from ._ltv import is_persistently_exciting as is_persistently_exciting
from ._ltv import observability_gramian as observability_gramian
from ._ltv import regressor_gramian as regressor_gramian
from ._ltv import transition_matrix as transition_matrix
from ._ltv import uniform_observability_constants as uniform_observability_constants
