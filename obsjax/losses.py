"""Trajectory losses for :func:`obsjax.tune`."""

from .tuning._losses import ise as ise
from .tuning._losses import itae as itae
from .tuning._losses import peak as peak
from .tuning._losses import terminal as terminal
