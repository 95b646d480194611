"""obsjax: differentiable state observers in JAX."""
from .observers._least_squares import LeastSquaresReset as LeastSquaresReset
from .observers._least_squares import LeastSquaresState as LeastSquaresState
from .observers._least_squares import chen_yen_example as chen_yen_example
from .observers._kalman_bucy import KalmanBucy as KalmanBucy
from .observers._kalman_bucy import KalmanBucyState as KalmanBucyState
