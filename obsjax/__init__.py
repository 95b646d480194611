"""obsjax: differentiable state observers in JAX."""
from .observers._generalized_inverse import GeneralizedInverse as GeneralizedInverse
from .observers._generalized_inverse import GeneralizedInverseReduced as GeneralizedInverseReduced
