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
from ._grids import hemisphere_grid as hemisphere_grid
from ._grids import project as project
from ._grids import project_fn as project_fn
from ._grids import sphere_grid as sphere_grid
from ._rotation import rotate as rotate
from ._rotation import rotate_zyz as rotate_zyz
from ._rotation import rotate_zyz_cs as rotate_zyz_cs
from ._rotation import rotation_matrix as rotation_matrix
from ._rotation import zyz_prepare_matrix as zyz_prepare_matrix
from ._triple import gaunt_tensor as gaunt_tensor
from ._triple import product_matrix as product_matrix
from ._triple import sh_product as sh_product
from ._triple import sh_product_t as sh_product_t
from ._zonal import cap as cap
from ._zonal import clamped_cosine as clamped_cosine
from ._zonal import zonal_cap as zonal_cap
from ._zonal import zonal_cap_versine as zonal_cap_versine
from ._zonal import zonal_clamped_cosine as zonal_clamped_cosine
from ._zonal import zonal_dot as zonal_dot
from ._zonal import zonal_rotate as zonal_rotate
