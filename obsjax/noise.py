"""Measurement noise models for :func:`obsjax.simulate`."""

from .systems._noise import BandLimitedNoise as BandLimitedNoise
from .systems._noise import WhiteNoise as WhiteNoise
