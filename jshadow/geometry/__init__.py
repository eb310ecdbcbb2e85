"""Geometry: triangle meshes, loading, bounding spheres, normals, deformations, procedural shapes.

Conventions (DESIGN.md §3): world right-handed, y up. An occluder's rest pose is normalised so that
its bounding sphere (centre of the axis-aligned box, radius to the farthest vertex) is the unit
sphere at the origin; deformations act in that normalised frame.
"""

from ._bounds import bounding_sphere as bounding_sphere
from ._bounds import cone_may_meet_sphere as cone_may_meet_sphere
from ._bounds import fan_may_meet_sphere as fan_may_meet_sphere
from ._bounds import normalize_to_unit_sphere as normalize_to_unit_sphere
from ._bounds import with_center_anchors as with_center_anchors
from ._deform import DEFORMATION_TYPES as DEFORMATION_TYPES
from ._deform import Bend as Bend
from ._deform import Breathe as Breathe
from ._deform import Compose as Compose
from ._deform import Offsets as Offsets
from ._deform import SquashStretch as SquashStretch
from ._deform import Taper as Taper
from ._deform import Twist as Twist
from ._deform import make_deformation as make_deformation
from ._distance import point_mesh_distance2 as point_mesh_distance2
from ._distance import point_triangle_distance2 as point_triangle_distance2
from ._io import load_mesh as load_mesh
from ._io import merge_duplicate_vertices as merge_duplicate_vertices
from ._io import save_mesh as save_mesh
from ._mesh import NORMAL_FALLBACK as NORMAL_FALLBACK
from ._mesh import Mesh as Mesh
from ._mesh import MeshWarning as MeshWarning
from ._mesh import degenerate_face_mask as degenerate_face_mask
from ._mesh import face_areas as face_areas
from ._mesh import face_normals as face_normals
from ._mesh import mesh_is_closed_manifold as mesh_is_closed_manifold
from ._mesh import remove_degenerate_faces as remove_degenerate_faces
from ._mesh import signed_volume as signed_volume
from ._mesh import validate_mesh as validate_mesh
from ._mesh import vertex_normals as vertex_normals
from ._procedural import egg as egg
from ._procedural import icosphere as icosphere
