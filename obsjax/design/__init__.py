"""Gain design: pole placement, Sylvester equations, canonical forms, observability indices."""

from ._place import choose_reduction as choose_reduction
from ._place import observability_indices as observability_indices
from ._place import place as place
from ._place import sylvester as sylvester
