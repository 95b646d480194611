"""Gain design: pole placement, Sylvester equations, canonical forms, observability indices."""

from ._place import choose_reduction as choose_reduction
from ._place import observability_indices as observability_indices
from ._place import place as place
from ._place import sylvester as sylvester
from ._ginverse import LovassNagyT as LovassNagyT
from ._ginverse import is_one_inverse as is_one_inverse
from ._ginverse import lovass_nagy_T as lovass_nagy_T
from ._ginverse import moore_penrose as moore_penrose
from ._ginverse import null_space_basis as null_space_basis
from ._ginverse import one_inverse as one_inverse
from ._ginverse import solvability_residual as solvability_residual
