"""Visibility: exact any-hit ray queries and the base sphere visibility (BSV) sampler.

* :mod:`._raycast`: watertight brute-force any-hit queries (triangles, shared-origin fans, spheres),
  memory bounded for any mesh size.
* :mod:`._hemisphere`: the same fans tested against only the faces above each origin's tangent plane
  and within each ray group's sectors of azimuth (exact; the own-vertex casts).
* :mod:`._frames`: the BSV shell parametrisation (polar axis world +z) and local frames.
* :mod:`._directions`: hemisphere direction sets and closed-form cap / hemisphere SH projections.
* :mod:`._bsv`: the BSV module, brute-force and analytic samplers, and reuse across frames.
* :mod:`._edgescan`: the fast BSV for closed meshes on a shell R > r (silhouette-edge scanline).
* :mod:`._silhouette`, :mod:`._bsv_grad`: silhouette edges and the BSV's vertex gradients.
* :mod:`._edgescan_grad`: the edge-scan BSV's vertex gradient in the image plane, with the
  visibility of each silhouette point from the winding number of the projected silhouette (exact;
  11–31× faster than the ray-cast visibility on whole frames).
* :mod:`._edgescan_scan`: the same derivative as a sum over the edge-scan's pixel columns and rows,
  with the exact layer count at every crossing (faster on large meshes, noisier per vertex).
* :mod:`._halfspace`: a mesh's visibility SH from points it lies wholly above (half the rays).
* :mod:`._own`: a mesh's visibility of itself at its own vertices, by rays (self-shadowing).
* :mod:`._own_maps`: the same from entry-face depth images and rays against nearby faces only.
* :mod:`._own_exact`: exact tests for the (vertex, lamp) pairs next to a silhouette in those images.
* :mod:`._images`: single rays looked up in the BSV's occlusion images (sharp sphere-light shadows).
* :mod:`._coverage`: those images made continuous along the scan lines, with an exact derivative.
* :mod:`._lamps`: orthographic coverage and depth images along fixed directions (exact distant-lamp
  shadows).
"""

from ._bsv import BSV as BSV
from ._bsv import BSVCache as BSVCache
from ._bsv import bsv_mesh as bsv_mesh
from ._bsv import bsv_sample_points as bsv_sample_points
from ._bsv import bsv_sphere as bsv_sphere
from ._bsv import bsv_sphere_traced as bsv_sphere_traced
from ._bsv import bsv_unit_vertices as bsv_unit_vertices
from ._bsv import bsv_update as bsv_update
from ._bsv import is_closed_manifold as is_closed_manifold
from ._bsv_grad import bsv_mesh_diff as bsv_mesh_diff
from ._bsv_grad import bsv_sh_tangent as bsv_sh_tangent
from ._bsv_grad import bsv_silhouette_counts as bsv_silhouette_counts
from ._coverage import coverage_sh as coverage_sh
from ._coverage import scan_coverage as scan_coverage
from ._directions import cap_sh_projection as cap_sh_projection
from ._directions import far_hemisphere_sh_projection as far_hemisphere_sh_projection
from ._directions import hemisphere_directions as hemisphere_directions
from ._edgescan import bsv_mesh_edgescan as bsv_mesh_edgescan
from ._edgescan import bsv_mesh_edgescan_of as bsv_mesh_edgescan_of
from ._edgescan import edgescan_cone_directions as edgescan_cone_directions
from ._edgescan import edgescan_slots as edgescan_slots
from ._edgescan_grad import bsv_and_coverage_edgescan_diff as bsv_and_coverage_edgescan_diff
from ._edgescan_grad import bsv_mesh_edgescan_diff as bsv_mesh_edgescan_diff
from ._edgescan_grad import edgescan_grad_slots as edgescan_grad_slots
from ._edgescan_scan import bsv_mesh_edgescan_scan_diff as bsv_mesh_edgescan_scan_diff
from ._edgescan_scan import edgescan_scan_slots as edgescan_scan_slots
from ._frames import bsv_frames as bsv_frames
from ._frames import bsv_grid_angles as bsv_grid_angles
from ._halfspace import halfspace_visibility_sh as halfspace_visibility_sh
from ._hemisphere import hemisphere_fan_any_hit as hemisphere_fan_any_hit
from ._images import OcclusionImages as OcclusionImages
from ._images import bsv_with_occlusion_images as bsv_with_occlusion_images
from ._images import image_fan_visibility as image_fan_visibility
from ._images import image_fan_visibility_components as image_fan_visibility_components
from ._images import image_ray_visibility as image_ray_visibility
from ._images import image_reach as image_reach
from ._images import occlusion_images as occlusion_images
from ._lamps import LampImages as LampImages
from ._lamps import image_coords as image_coords
from ._lamps import lamp_images as lamp_images
from ._lamps import lamp_visibility as lamp_visibility
from ._lamps import stamp_groups as stamp_groups
from ._own import vertex_transfer_and_lamps as vertex_transfer_and_lamps
from ._own import vertex_visibility_sh as vertex_visibility_sh
from ._own_exact import settle_ambiguous as settle_ambiguous
from ._own_maps import near_any_hit as near_any_hit
from ._own_maps import ring_faces as ring_faces
from ._own_maps import vertex_lamp_visibility as vertex_lamp_visibility
from ._own_maps import vertex_transfer_maps as vertex_transfer_maps
from ._raycast import ray_fan_any_hit as ray_fan_any_hit
from ._raycast import ray_sphere_any_hit as ray_sphere_any_hit
from ._raycast import ray_triangle_any_hit as ray_triangle_any_hit
from ._silhouette import SilhouetteSamples as SilhouetteSamples
from ._silhouette import silhouette_edges_table as silhouette_edges_table
from ._silhouette import silhouette_samples as silhouette_samples
