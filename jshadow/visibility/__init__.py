"""Visibility: exact any-hit ray queries and the base sphere visibility (BSV) sampler.

See :mod:`jshadow.visibility._raycast` for the ray casters and their watertightness guarantees.
"""

from ._raycast import ray_fan_any_hit as ray_fan_any_hit
from ._raycast import ray_sphere_any_hit as ray_sphere_any_hit
from ._raycast import ray_triangle_any_hit as ray_triangle_any_hit
