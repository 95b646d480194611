"""Array aliases with named dimensions.

Dimensions: ``n`` states, ``m`` outputs (measurements), ``p`` inputs, ``q`` observer states,
``T`` save times, ``batch`` a vmapped batch.  (The thesis writes r for the input dimension; obsjax
uses ``p`` throughout.)
"""

from typing import Any

from jaxtyping import Array, ArrayLike, Bool, Float, Int, PyTree

Scalar = Float[Array, ""]
ScalarLike = float | Float[ArrayLike, ""]
State = Float[Array, " n"]
Output = Float[Array, " m"]
Input = Float[Array, " p"]
Matrix = Float[Array, "a b"]
ObsState = PyTree[Any]

__all__ = [
    "Array",
    "ArrayLike",
    "Bool",
    "Float",
    "Int",
    "PyTree",
    "Scalar",
    "ScalarLike",
    "State",
    "Output",
    "Input",
    "Matrix",
    "ObsState",
]
