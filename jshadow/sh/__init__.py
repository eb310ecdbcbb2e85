"""Real spherical harmonics: basis, projection, rotation, triple products, zonal harmonics.

See :mod:`jshadow.sh._basis` for the index and sign convention used throughout jshadow.
"""

from ._basis import num_coeffs as num_coeffs
from ._basis import sh_bands_of as sh_bands_of
from ._basis import sh_basis as sh_basis
from ._basis import sh_basis_spherical as sh_basis_spherical
from ._basis import sh_eval as sh_eval
from ._basis import sh_index as sh_index
from ._basis import sh_lm as sh_lm
