"""Gain design for observers.

- Pole placement and Sylvester equations (Hassan thesis, chapters 2-3): `place` (observer gain L with
  eig(A − LC) = poles for any number of outputs, well-conditioned eigenvectors, differentiable in A, C
  and the poles), `pole_structure` (the pattern of a pole vector, for `place` under `jit`),
  `sylvester` (T A − F T = H), `observability_indices`, and `observable_canonical_form`: the
  multi-output canonical form (3.1c) of thesis §3.2.
- Matrix {1}-inverses and the Lovass-Nagy condition (Chaisanguanmitt's slides): `one_inverse`,
  `moore_penrose`, `is_one_inverse`, `null_space_basis`, `solvability_residual`, `lovass_nagy_T`.
- LTV observer canonical form and PD-spectrum synthesis (Huang & Zhu (8)-(14), (21)):
  `ltv_observability_matrix`, `ltv_observability_indices`, `strong_observability`,
  `ltv_observer_canonical_form`, `pd_coefficients`, `rpdo_coefficients`, `pd_modal_matrix`,
  `pd_observer_gain`, `RampBandwidth`.

Designs are computed in float64 (importing obsjax turns it on); rank decisions are relative to the scale
of the matrices.

Example:

```python
import obsjax

L = obsjax.design.place([[-2.0, 1.0], [0.0, -1.0]], [[1.0, 0.0]], [-3.0, -3.0])
print(L)   # [[3.], [4.]]: Hassan's example (2.8)
```
"""

from types import ModuleType as _ModuleType

from ._canonical import ObservableCanonicalForm as ObservableCanonicalForm
from ._canonical import observable_canonical_form as observable_canonical_form
from ._ginverse import LovassNagyT as LovassNagyT
from ._ginverse import LovassNagyTFlow as LovassNagyTFlow
from ._ginverse import frozen_T0 as frozen_T0
from ._ginverse import input_solvability_residual as input_solvability_residual
from ._ginverse import is_one_inverse as is_one_inverse
from ._ginverse import lovass_nagy_T as lovass_nagy_T
from ._ginverse import lovass_nagy_T_ode as lovass_nagy_T_ode
from ._ginverse import moore_penrose as moore_penrose
from ._ginverse import null_space_basis as null_space_basis
from ._ginverse import one_inverse as one_inverse
from ._ginverse import solvability_residual as solvability_residual
from ._ltv_canonical import LTVCanonicalForm as LTVCanonicalForm
from ._ltv_canonical import ltv_observability_indices as ltv_observability_indices
from ._ltv_canonical import ltv_observability_matrix as ltv_observability_matrix
from ._ltv_canonical import ltv_observer_canonical_form as ltv_observer_canonical_form
from ._ltv_canonical import strong_observability as strong_observability
from ._pd_spectrum import PDObserverGain as PDObserverGain
from ._pd_spectrum import RampBandwidth as RampBandwidth
from ._pd_spectrum import pd_coefficients as pd_coefficients
from ._pd_spectrum import pd_modal_matrix as pd_modal_matrix
from ._pd_spectrum import pd_observer_gain as pd_observer_gain
from ._pd_spectrum import rpdo_coefficients as rpdo_coefficients
from ._place import observability_indices as observability_indices
from ._place import place as place
from ._place import sylvester as sylvester
from ._poles import PoleStructure as PoleStructure
from ._poles import pole_structure as pole_structure
from ._tlc import NominalTrajectory as NominalTrajectory
from ._tlc import PDControllerGain as PDControllerGain
from ._tlc import dynamic_inversion as dynamic_inversion
from ._tlc import ltv_controllability_indices as ltv_controllability_indices
from ._tlc import pd_controller_gain as pd_controller_gain

# Every public name imported above (keep this line last: names added above it are exported too).
__all__ = [
    _n
    for _n in sorted(globals())
    if not _n.startswith("_") and not isinstance(globals()[_n], _ModuleType)
]
