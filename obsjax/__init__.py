"""obsjax: differentiable state observers in JAX."""
