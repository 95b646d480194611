"""obsjax: differentiable state observers in JAX."""
from .observers._finite_window import FiniteWindow as FiniteWindow
