"""Triangle meshes: the :class:`Mesh` container, validation, manifold test, normals, areas, volume.

Validation and the manifold test run on concrete (NumPy) values when a mesh is loaded or built; the
geometric functions (:func:`face_normals`, :func:`face_areas`, :func:`vertex_normals`,
:func:`signed_volume`) are pure JAX, jit-friendly and differentiable with respect to the vertices.
"""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._numerics import eps, safe_norm, safe_normalize

__all__ = [
    "Mesh",
    "MeshWarning",
    "validate_mesh",
    "mesh_is_closed_manifold",
    "degenerate_face_mask",
    "remove_degenerate_faces",
    "face_normals",
    "face_areas",
    "vertex_normals",
    "signed_volume",
    "NORMAL_FALLBACK",
]

NORMAL_FALLBACK = (0.0, 1.0, 0.0)  # unit normal given to a vertex whose area-weighted sum vanishes (+y, up)


class MeshWarning(UserWarning):
    """A mesh is usable but not clean: open or non-manifold, or some faces were dropped."""


def float_dtype(dtype=None):
    """The float dtype to build arrays in: JAX's default float for ``None``; float64 becomes float32
    when x64 is disabled (no truncation warning). Raises ``ValueError`` for a non-float dtype."""
    if dtype is None:
        return jnp.dtype(jnp.result_type(float))
    dt = jnp.dtype(dtype)
    if not jnp.issubdtype(dt, jnp.floating):
        raise ValueError(f"expected a floating-point dtype, got {dt}")
    return jnp.dtype(jax.dtypes.canonicalize_dtype(dt))


def _as_faces(faces) -> Int[Array, "F 3"]:
    faces = jnp.asarray(faces)
    if not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"mesh faces must be an integer array of shape (F, 3), got dtype {faces.dtype}")
    return faces.astype(jnp.int32)


class Mesh(eqx.Module):
    """A triangle mesh.

    ``vertices`` (V, 3) float positions; ``faces`` (F, 3) int32 vertex indices, counter-clockwise
    seen from outside (so ``cross(v1 - v0, v2 - v0)`` points outward). ``name`` (static) is used in
    error and warning messages, e.g. the file a mesh was loaded from. Only the shapes are checked
    here; :func:`validate_mesh` checks the values.
    """

    vertices: Float[Array, "V 3"] = eqx.field(converter=jnp.asarray)
    faces: Int[Array, "F 3"] = eqx.field(converter=_as_faces)
    name: str = eqx.field(static=True, default="mesh")

    def __check_init__(self):
        if self.vertices.ndim != 2 or self.vertices.shape[-1] != 3:
            raise ValueError(f"{self.name}: vertices must have shape (V, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[-1] != 3:
            raise ValueError(f"{self.name}: faces must have shape (F, 3), got {self.faces.shape}")

    @property
    def num_vertices(self) -> int:
        return self.vertices.shape[0]

    @property
    def num_faces(self) -> int:
        return self.faces.shape[0]


def degenerate_face_mask(vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]) -> np.ndarray:
    """Boolean (F,) NumPy mask of zero-area faces (concrete values only).

    A face is degenerate if two of its indices are equal, or if twice its area is at most
    ``eps(dtype)`` times its longest edge squared (the sine of its smallest angle is below the
    tolerance), computed in float64; ``dtype`` is that of ``vertices`` (float64 for NumPy input).
    """
    v = np.asarray(vertices)
    tol = eps(v.dtype if np.issubdtype(v.dtype, np.floating) else np.float64)
    v = v.astype(np.float64)
    f = np.asarray(faces)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.linalg.norm(np.cross(b - a, c - a), axis=-1)
    longest2 = np.max(
        np.stack([np.sum((b - a) ** 2, -1), np.sum((c - b) ** 2, -1), np.sum((a - c) ** 2, -1)]), axis=0
    )
    same = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    return same | (cross <= tol * longest2)


def mesh_is_closed_manifold(faces: Int[ArrayLike, "F 3"]) -> bool:
    """True if every edge is shared by exactly two faces that traverse it in opposite directions.

    That is: each directed edge (a, b) of a face occurs exactly once, and so does its reverse (b, a).
    This implies a closed (watertight) surface with consistent winding. Faces with repeated indices
    make the answer False. Vertex-only contacts ("bow ties") are not detected. NumPy, concrete values.
    """
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[-1] != 3 or f.shape[0] == 0:
        return False
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])):
        return False
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=0)
    n = int(f.max()) + 1
    key = directed[:, 0] * n + directed[:, 1]
    rev = directed[:, 1] * n + directed[:, 0]
    key_sorted = np.sort(key)
    if np.any(key_sorted[1:] == key_sorted[:-1]):
        return False  # a directed edge used twice: inconsistent winding or more than two faces
    pos = np.clip(np.searchsorted(key_sorted, rev), 0, key_sorted.size - 1)
    return bool(np.all(key_sorted[pos] == rev))


def validate_mesh(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    name: str = "mesh",
    check_manifold: bool = True,
) -> None:
    """Check a mesh's values; raise ``ValueError`` naming ``name`` and the problem.

    Errors: wrong shapes, non-finite coordinates, non-integer or out-of-range face indices, no faces,
    all faces degenerate (zero area, see :func:`degenerate_face_mask`). If ``check_manifold``, an
    open or non-manifold mesh (see :func:`mesh_is_closed_manifold`) only emits a :class:`MeshWarning`:
    such meshes still work (visibility needs no closed surface), but inside/outside is ill-defined.
    Works on concrete values (NumPy or JAX arrays outside ``jit``).
    """
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if f.size == 0:
        raise ValueError(f"{name}: mesh has no faces (need at least one triangle)")
    if v.ndim != 2 or v.shape[-1] != 3:
        raise ValueError(f"{name}: vertices must have shape (V, 3), got {v.shape}")
    if v.shape[0] == 0:
        raise ValueError(f"{name}: mesh has no vertices")
    if not np.issubdtype(v.dtype, np.floating):
        v = v.astype(np.float64)
    bad = ~np.isfinite(v).all(axis=-1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{name}: {int(bad.sum())} vertices have non-finite coordinates (NaN or inf), "
            f"first is vertex {i}: {v[i].tolist()}"
        )
    if f.ndim != 2 or f.shape[-1] != 3:
        raise ValueError(f"{name}: faces must have shape (F, 3) (triangles), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"{name}: face indices must be integers, got dtype {f.dtype}")
    out = (f < 0) | (f >= v.shape[0])
    if out.any():
        i = int(np.flatnonzero(out.any(axis=-1))[0])
        raise ValueError(
            f"{name}: face index out of range: face {i} is {f[i].tolist()}, "
            f"but vertex indices must be in [0, {v.shape[0] - 1}]"
        )
    if degenerate_face_mask(v, f).all():
        raise ValueError(f"{name}: all {f.shape[0]} faces are degenerate (zero area)")
    if check_manifold and not mesh_is_closed_manifold(f):
        warnings.warn(
            f"{name}: mesh is open or non-manifold (some edge is not shared by exactly two "
            "consistently wound faces); it will still be used",
            MeshWarning,
            stacklevel=2,
        )


def remove_degenerate_faces(mesh: Mesh) -> Mesh:
    """Drop zero-area faces (:func:`degenerate_face_mask`), with a :class:`MeshWarning` if any.

    Vertices are kept (indices stay valid). Concrete values only. Returns ``mesh`` itself when no
    face is degenerate.
    """
    bad = degenerate_face_mask(mesh.vertices, mesh.faces)
    if not bad.any():
        return mesh
    if bad.all():
        raise ValueError(f"{mesh.name}: all {bad.size} faces are degenerate (zero area)")
    warnings.warn(
        f"{mesh.name}: removed {int(bad.sum())} degenerate (zero-area) faces of {bad.size}",
        MeshWarning,
        stacklevel=2,
    )
    keep = np.flatnonzero(~bad)
    return Mesh(mesh.vertices, np.asarray(mesh.faces)[keep], name=mesh.name)


def _corners(vertices, faces):
    return vertices[..., faces[:, 0], :], vertices[..., faces[:, 1], :], vertices[..., faces[:, 2], :]


def face_normals(vertices: Float[Array, "... V 3"], faces: Int[Array, "F 3"]) -> Float[Array, "... F 3"]:
    """Unit face normals ``normalize(cross(v1 - v0, v2 - v0))``; a degenerate face gets (0, 0, 0)."""
    a, b, c = _corners(jnp.asarray(vertices), faces)
    return safe_normalize(jnp.cross(b - a, c - a))


def face_areas(vertices: Float[Array, "... V 3"], faces: Int[Array, "F 3"]) -> Float[Array, "... F"]:
    """Triangle areas, in squared scene units (zero-gradient-safe at degenerate faces)."""
    a, b, c = _corners(jnp.asarray(vertices), faces)
    return 0.5 * safe_norm(jnp.cross(b - a, c - a))


def signed_volume(vertices: Float[Array, "... V 3"], faces: Int[Array, "F 3"]) -> Float[Array, "..."]:
    """Enclosed volume by the divergence theorem, ``Σ_f v0 · (v1 × v2) / 6``.

    Positive for a closed mesh with outward (counter-clockwise) winding; meaningless for open meshes.
    Exact for the polyhedron and differentiable (a polynomial in the vertices).
    """
    a, b, c = _corners(jnp.asarray(vertices), faces)
    return jnp.sum(jnp.sum(a * jnp.cross(b, c), axis=-1), axis=-1) / 6.0


def _vertex_normals_single(vertices: Float[Array, "V 3"], faces: Int[Array, "F 3"]) -> Float[Array, "V 3"]:
    a, b, c = _corners(vertices, faces)
    n = jnp.cross(b - a, c - a)  # |n| = 2 · area: summing it weights faces by area
    ids = jnp.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    acc = jax.ops.segment_sum(jnp.concatenate([n, n, n], axis=0), ids, num_segments=vertices.shape[0])
    unit = safe_normalize(acc)  # zero vector -> zero, with zero gradient (double where inside)
    ok = jnp.sum(unit * unit, axis=-1, keepdims=True) > 0.5
    return jnp.where(ok, unit, jnp.asarray(NORMAL_FALLBACK, vertices.dtype))


def vertex_normals(vertices: Float[Array, "... V 3"], faces: Int[Array, "F 3"]) -> Float[Array, "... V 3"]:
    """Area-weighted unit vertex normals.

    Each vertex gets the normalised sum of ``cross(v1 - v0, v2 - v0)`` (twice the area times the unit
    normal) over its faces, accumulated with ``jax.ops.segment_sum`` (jit-friendly, static shapes).
    Where that sum is the zero vector (an unreferenced vertex, or faces that cancel), the normal is
    :data:`NORMAL_FALLBACK` = +y and its gradient is zero, not NaN. Leading batch axes of
    ``vertices`` are mapped over; ``faces`` is shared.
    """
    vertices = jnp.asarray(vertices)
    faces = jnp.asarray(faces)
    if vertices.shape[-1] != 3 or faces.ndim != 2 or faces.shape[-1] != 3:
        raise ValueError(
            f"vertex_normals expects vertices (..., V, 3) and faces (F, 3), got {vertices.shape} and "
            f"{faces.shape}"
        )
    return _vertex_normals_batched(vertices, faces)


@jax.jit
def _vertex_normals_batched(vertices, faces):
    fn = _vertex_normals_single
    for _ in range(vertices.ndim - 2):
        fn = jax.vmap(fn, in_axes=(0, None))
    return fn(vertices, faces)
