"""SH scaling: angular rescaling f_k and extrapolation matrices M_k between radial distances.

From the deformable-shadow-fields paper (Sec. 4.1–4.2, Appendices A–B), with the corrections of
DESIGN.md §2: visibility at distance d is ``V_d(θ, φ) = V_r(f_{1/k}(θ), φ)`` with k = r/d, and SH
coefficients extrapolate as ``S_d = M_k S_r``.
"""

from ._matrices import KINDS as KINDS
from ._matrices import ZONAL_BANDS_MAX as ZONAL_BANDS_MAX
from ._matrices import MkTable as MkTable
from ._matrices import mk_apply as mk_apply
from ._matrices import mk_apply_table as mk_apply_table
from ._matrices import mk_apply_zonal as mk_apply_zonal
from ._matrices import mk_bracket as mk_bracket
from ._matrices import mk_in_range as mk_in_range
from ._matrices import mk_interpolate as mk_interpolate
from ._matrices import mk_matrix as mk_matrix
from ._matrices import mk_pattern as mk_pattern
from ._matrices import mk_table as mk_table
from ._matrices import mk_zonal_table as mk_zonal_table
from ._rescale import MODELS as MODELS
from ._rescale import f_k as f_k
from ._rescale import f_k_inverse as f_k_inverse
from ._rescale import srf_jacobian as srf_jacobian
