"""Batched, chunked, sharded Monte-Carlo studies with resumable checkpoints.

`monte_carlo` simulates N trajectories of a plant and an observer with random initial states, initial
estimates, measurement noise and (optionally) sampled plants, in chunks of ``chunk_size`` trajectories
sharded over ``jax.devices()``; a checkpoint directory makes a long study resumable.  The result,
`MonteCarloResult`, carries the quantile bands of ‖x̃(t)‖, the convergence-time distribution, the ISE of
every trajectory and the number of failed solves (counted, never averaged into the statistics).
`comparison_table` prints several results side by side; `summarise` builds a result from error norms
computed elsewhere; `noisy_batch` and `with_noise` realise measurement noise as plants, for
:func:`obsjax.tune` with ``plant_batched=True``.

Example:

```python
import jax, jax.numpy as jnp
import obsjax

plant = obsjax.chen_yen_example()
obs = obsjax.LeastSquaresReset(plant, gamma=20.0, p0=0.1, T=0.25)
mc = obsjax.monte_carlo(plant, obs, jax.random.PRNGKey(0), 64,
                        x0_sampler=lambda k: 3 * jax.random.normal(k, (2,)),
                        xhat0_sampler=lambda k: jnp.zeros(2), ts=jnp.linspace(0.0, 10.0, 41),
                        chunk_size=64, progress=False)
print(mc.summary())
```
"""

from types import ModuleType as _ModuleType

from ._checkpoint import CheckpointWarning as CheckpointWarning
from ._montecarlo import MonteCarloResult as MonteCarloResult
from ._montecarlo import comparison_table as comparison_table
from ._montecarlo import monte_carlo as monte_carlo
from ._montecarlo import summarise as summarise
from ._noisy import NoisyOutput as NoisyOutput
from ._noisy import noisy_batch as noisy_batch
from ._noisy import with_noise as with_noise
from ._streaming import LogHistogram as LogHistogram

# Every public name imported above (keep this line last: names added above it are exported too).
__all__ = [
    _n
    for _n in sorted(globals())
    if not _n.startswith("_") and not isinstance(globals()[_n], _ModuleType)
]
