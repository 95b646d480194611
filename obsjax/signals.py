"""Input signals u(t) for :func:`obsjax.simulate` and :func:`obsjax.tune`.

- `multisine` / `Multisine`: u_j(t) = Σ_k a_jk sin(ω_jk t + φ_jk), a sum of sinusoids per input channel
  (the persistently exciting inputs that adaptive observers need).
- `constant` / `Constant`: a step u(t) = value applied at t0.

Inputs are equinox modules called as ``u(t)``; amplitudes and frequencies are array leaves, so they can be
batched with ``jax.vmap`` and differentiated.

Example:

```python
import obsjax

u = obsjax.signals.multisine([1.0, 0.5], [0.7, 2.0])   # one input: sin(0.7 t) + 0.5 sin(2 t)
print(u(1.0))
```
"""

from types import ModuleType as _ModuleType

from .systems._signals import Constant as Constant
from .systems._signals import Multisine as Multisine
from .systems._signals import constant as constant
from .systems._signals import multisine as multisine

# Every public name imported above (keep this line last: names added above it are exported too).
__all__ = [
    _n
    for _n in sorted(globals())
    if not _n.startswith("_") and not isinstance(globals()[_n], _ModuleType)
]
