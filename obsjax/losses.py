"""Losses on a simulated trajectory, for :func:`obsjax.tune`, and on an estimate from recorded data.

Each loss maps one :class:`obsjax.Trajectory` to a scalar; :func:`obsjax.tune` averages it over a batch of
initial conditions (and of noise realisations or sampled plants).  All are differentiable with respect to
every gain of the observer, through the diffrax solve.

- `ise`: integral of squared error ∫ ‖x̃(t)‖² dt.
- `itae`: integral of time-weighted absolute error ∫ (t − t0) ‖x̃(t)‖ dt.
- `terminal`: squared terminal error ‖x̃(t_end)‖².
- `peak`: smooth maximum of ‖x̃(t)‖ over the save grid.

On recorded data (an :class:`obsjax.Estimate`, for :func:`obsjax.tune_on_data`):

- `output_error`: mean of ‖y_k − ŷ_k‖² over the samples (or ∫ ‖y − ŷ‖² dt), padding ignored.
- `state_error`: mean of ‖x̂_k − x_ref,k‖² over the states measured for validation.

The integrals use the trapezoid rule on the save grid ``ts``, so a finer grid gives a more accurate loss.
`peak` is a smooth maximum over the save times: never below the maximum, and above it by at most
ln k / `sharpness` of it where k save times share the maximum (see :func:`peak`).

Example:

```python
import jax.numpy as jnp
import obsjax

plant = obsjax.LTI(A=[[-2.0, 1.0], [0.0, -1.0]], B=[[0.0], [1.0]], C=[[1.0, 0.0]])
obs = obsjax.Luenberger.from_poles(plant, [-3.0, -3.0])
traj = obsjax.simulate(plant, obs, jnp.array([1.0, -1.0]), jnp.zeros(2), jnp.linspace(0.0, 5.0, 201))
print(obsjax.losses.ise(traj))
```
"""

from types import ModuleType as _ModuleType

from .tuning._losses import ise as ise
from .tuning._losses import itae as itae
from .tuning._losses import peak as peak
from .tuning._losses import terminal as terminal
from .tuning._losses import output_error as output_error
from .tuning._losses import state_error as state_error

# Every public name imported above (keep this line last: names added above it are exported too).
__all__ = [
    _n
    for _n in sorted(globals())
    if not _n.startswith("_") and not isinstance(globals()[_n], _ModuleType)
]
