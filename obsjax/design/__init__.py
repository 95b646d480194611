"""Gain design: pole placement, Sylvester equations, canonical forms, observability indices."""

from ._canonical import ObservableCanonicalForm as ObservableCanonicalForm
from ._canonical import observable_canonical_form as observable_canonical_form
from ._ginverse import LovassNagyT as LovassNagyT
from ._ginverse import is_one_inverse as is_one_inverse
from ._ginverse import lovass_nagy_T as lovass_nagy_T
from ._ginverse import moore_penrose as moore_penrose
from ._ginverse import null_space_basis as null_space_basis
from ._ginverse import one_inverse as one_inverse
from ._ginverse import solvability_residual as solvability_residual
from ._ltv_canonical import LTVCanonicalForm as LTVCanonicalForm
from ._ltv_canonical import ltv_observability_indices as ltv_observability_indices
from ._ltv_canonical import ltv_observability_matrix as ltv_observability_matrix
from ._ltv_canonical import ltv_observer_canonical_form as ltv_observer_canonical_form
from ._ltv_canonical import strong_observability as strong_observability
from ._pd_spectrum import PDObserverGain as PDObserverGain
from ._pd_spectrum import RampBandwidth as RampBandwidth
from ._pd_spectrum import pd_coefficients as pd_coefficients
from ._pd_spectrum import pd_modal_matrix as pd_modal_matrix
from ._pd_spectrum import pd_observer_gain as pd_observer_gain
from ._pd_spectrum import rpdo_coefficients as rpdo_coefficients
from ._place import observability_indices as observability_indices
from ._place import place as place
from ._place import sylvester as sylvester
from ._poles import PoleStructure as PoleStructure
from ._poles import pole_structure as pole_structure
