"""Batched, chunked, sharded Monte-Carlo studies with resumable checkpoints."""

from ._checkpoint import CheckpointWarning as CheckpointWarning
from ._montecarlo import MonteCarloResult as MonteCarloResult
from ._montecarlo import comparison_table as comparison_table
from ._montecarlo import monte_carlo as monte_carlo
from ._montecarlo import summarise as summarise
from ._noisy import NoisyOutput as NoisyOutput
from ._noisy import noisy_batch as noisy_batch
from ._noisy import with_noise as with_noise
