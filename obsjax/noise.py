"""Measurement-noise models for :func:`obsjax.simulate`.

The noise is added to the plant's output, y(t) = h(t, x, u) + v(t), and drawn from the ``key`` passed to
:func:`obsjax.simulate` (one realisation per key, so ``jax.vmap`` over keys gives independent paths).

- `WhiteNoise`: white noise of intensity σ, simulated as a stochastic differential equation.
- `BandLimitedNoise`: N(0, σ²) samples every ``dt``, linearly interpolated: a continuous path that explicit
  ODE solvers integrate without an SDE solver and that gradients pass through.  It is piecewise linear,
  with a kink at every node t0 + k·dt that is not a breakpoint of the solve: an adaptive step across a kink
  loses order, so the solution is 10²–10⁴ times less accurate than `rtol` (errors up to 5e-7 at
  rtol 1e-10, and 0.4–1 % of the noise-driven error at the default rtol 1e-6, in checks against a
  node-by-node reference), and two adaptive solves that step differently (``simulate`` and the masked
  batch loop of ``simulate_batch``/``monte_carlo``) agree only to that level; fixed steps whose grid
  holds the nodes (dt a multiple of dt0, nodes on the step grid) integrate it to rounding, and are the
  choice for accurate or reproducible noisy studies.

Example:

```python
import jax, jax.numpy as jnp
import obsjax

plant = obsjax.LTI(A=[[-2.0, 1.0], [0.0, -1.0]], B=[[0.0], [1.0]], C=[[1.0, 0.0]])
obs = obsjax.Luenberger.from_poles(plant, [-3.0, -3.0])
traj = obsjax.simulate(plant, obs, jnp.array([1.0, -1.0]), jnp.zeros(2), jnp.linspace(0.0, 5.0, 101),
                       noise=obsjax.noise.BandLimitedNoise(0.05, dt=0.02), key=jax.random.PRNGKey(0))
print(traj.error_norm[-1])   # the error no longer vanishes: it is driven by the noise
```
"""

from types import ModuleType as _ModuleType

from .systems._noise import BandLimitedNoise as BandLimitedNoise
from .systems._noise import WhiteNoise as WhiteNoise

# Every public name imported above (keep this line last: names added above it are exported too).
__all__ = [
    _n
    for _n in sorted(globals())
    if not _n.startswith("_") and not isinstance(globals()[_n], _ModuleType)
]
