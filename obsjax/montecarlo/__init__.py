"""Batched, chunked, sharded Monte-Carlo studies with resumable checkpoints."""

from ._montecarlo import MonteCarloResult as MonteCarloResult
from ._montecarlo import comparison_table as comparison_table
from ._montecarlo import monte_carlo as monte_carlo
from ._montecarlo import summarise as summarise
