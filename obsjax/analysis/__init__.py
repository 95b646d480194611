"""Analysis of plants and observers.

- LTI: `obsv` (observability matrix), `is_observable`, `observability_staircase` (the orthogonal
  staircase form of the balanced pair: every rank decision of the package), `pbh_margin`, and
  `closed_loop_eigvals` / `placement_error` (eigenvalues of A − LC in extended precision: how
  accurately a gain places its poles).
- LTV (Chen & Yen, 1999): `transition_matrix` Φ(t, τ) (2), `observability_gramian` (4),
  `uniform_observability_constants` ((2), (3), (16), (17)), `regressor_gramian` (16),
  `is_persistently_exciting` (Definition 2, (7)), `chen_yen_bound` (the Theorem's contraction factor per
  reset period) and `decay_rate` (exponential rate fitted to a simulated error).
- Adaptive laws (Hassan thesis, (4.20)-(4.21)): `morgan_narendra`, the Morgan–Narendra richness
  constants and certified convergence rates of a regressor (`MorganNarendra`).

Example:

```python
import obsjax

O = obsjax.analysis.obsv([[-2.0, 1.0], [0.0, -1.0]], [[1.0, 0.0]])
print(O, obsjax.analysis.is_observable([[-2.0, 1.0], [0.0, -1.0]], [[1.0, 0.0]]))
```
"""

from types import ModuleType as _ModuleType

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
from ._accuracy import closed_loop_eigvals as closed_loop_eigvals
from ._accuracy import placement_error as placement_error
from ._morgan_narendra import MorganNarendra as MorganNarendra
from ._morgan_narendra import morgan_narendra as morgan_narendra

# Every public name imported above (keep this line last: names added above it are exported too).
__all__ = [
    _n
    for _n in sorted(globals())
    if not _n.startswith("_") and not isinstance(globals()[_n], _ModuleType)
]
