"""Direction sampling for the Monte Carlo reference.

* :mod:`._projected_cap`: sphere lights sampled in proportion to projected solid angle
  (Peters & Dachsbacher 2019, "Sampling Projected Spherical Caps in Real Time"), all three cases,
  with the density of an arbitrary direction.
* :mod:`._cone`: uniform cone (solid-angle) sampling of a sphere, the baseline, and its
  stratified midpoint nodes (the shadow field's sphere-light lookup).
* :mod:`._hemisphere`: cosine-weighted hemisphere sampling.
* :mod:`._envmap`: luminance importance sampling of lat-long environment maps.

Every sampler takes uniform numbers ``u (..., 2)`` (testable, stratifiable) and has a ``random_*``
wrapper that draws them from a PRNG key; all return a :class:`CapSample` (direction, solid-angle
``pdf``, projected-solid-angle ``pdf_proj``, ``valid``) and batch over leading axes.
"""

from ._cone import random_sphere_cone as random_sphere_cone
from ._cone import sample_sphere_cone as sample_sphere_cone
from ._cone import sphere_cone_pdf as sphere_cone_pdf
from ._cone import stratified_cone_components as stratified_cone_components
from ._cone import stratified_sphere_cone as stratified_sphere_cone
from ._envmap import EnvironmentSampler as EnvironmentSampler
from ._envmap import environment_pdf as environment_pdf
from ._envmap import environment_sampler as environment_sampler
from ._envmap import random_environment as random_environment
from ._envmap import sample_environment as sample_environment
from ._hemisphere import cosine_hemisphere_pdf as cosine_hemisphere_pdf
from ._hemisphere import random_cosine_hemisphere as random_cosine_hemisphere
from ._hemisphere import sample_cosine_hemisphere as sample_cosine_hemisphere
from ._projected_cap import CapCase as CapCase
from ._projected_cap import CapSample as CapSample
from ._projected_cap import projected_cap_case as projected_cap_case
from ._projected_cap import projected_cap_density_bound as projected_cap_density_bound
from ._projected_cap import projected_cap_frame as projected_cap_frame
from ._projected_cap import projected_cap_pdf as projected_cap_pdf
from ._projected_cap import projected_solid_angle as projected_solid_angle
from ._projected_cap import random_projected_cap as random_projected_cap
from ._projected_cap import sample_projected_cap as sample_projected_cap
from ._projected_cap import segment_area as segment_area
from ._projected_cap import segment_area_inverse as segment_area_inverse
