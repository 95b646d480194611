"""Analysis: observability, transition matrices, gramians, persistence of excitation, bounds, rates."""

from ._lti import is_observable as is_observable
from ._lti import obsv as obsv
