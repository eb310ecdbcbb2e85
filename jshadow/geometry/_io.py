"""Reading (and writing) triangle meshes through trimesh: OBJ, PLY, GLB/GLTF, STL, OFF."""

from __future__ import annotations

import os
import warnings

import jax.numpy as jnp
import numpy as np

from ._mesh import (
    Mesh,
    MeshWarning,
    float_dtype,
    mesh_is_closed_manifold,
    remove_degenerate_faces,
    validate_mesh,
)

__all__ = ["load_mesh", "save_mesh", "merge_duplicate_vertices"]


def merge_duplicate_vertices(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical vertex positions (NumPy); merged vertices keep first-occurrence order.

    STL stores three separate corners per triangle; without merging, an STL mesh has no shared edges.
    """
    v = np.asarray(vertices)
    _, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first)  # unique rows sorted by first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return v[first[order]], rank[inverse][np.asarray(faces)]


_TEXT_FORMATS = (".obj", ".off")


def _check_text_format(name: str) -> None:
    """OBJ and OFF are text: reject bytes that are not UTF-8 with a clear ``ValueError`` (trimesh
    would otherwise guess an encoding, or fail with an unrelated error)."""
    if not name.lower().endswith(_TEXT_FORMATS):
        return
    try:
        with open(name, "rb") as fh:
            data = fh.read()
    except OSError as err:
        raise ValueError(f"cannot read mesh file {name}: {err.strerror or err}") from None
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(
            f"cannot read mesh file {name}: not a UTF-8 text file (byte 0x{data[err.start]:02x} at "
            f"offset {err.start}); {os.path.splitext(name)[1]} meshes are text"
        ) from None


def load_mesh(path: str | os.PathLike, dtype=None) -> Mesh:
    """Load a triangle mesh with trimesh and check it.

    Formats: whatever trimesh reads (OBJ, PLY, GLB/GLTF, STL, OFF); polygons are triangulated, a
    multi-object file is concatenated into one mesh. Vertex order is kept (``process=False``: no
    merging, no reordering), except for STL, whose bit-identical corners are merged (first-occurrence
    order) because STL has no shared vertices. ``dtype`` of the vertices defaults to JAX's default
    float (float32 unless x64 is enabled); faces are int32.

    Raises ``ValueError`` naming the file for a missing or unreadable file and for the problems
    :func:`validate_mesh` finds (non-finite coordinates, out-of-range indices, no faces, all faces
    degenerate). Zero-area faces are dropped, and an open or non-manifold mesh is accepted, each
    with a :class:`MeshWarning`.
    """
    import trimesh

    name = os.fspath(path)
    if not os.path.isfile(name):
        raise ValueError(f"mesh file not found: {name}")
    _check_text_format(name)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # trimesh's own chatter about file details
            loaded = trimesh.load(name, process=False, force="mesh")
        vertices = np.asarray(loaded.vertices, dtype=np.float64)
        faces = np.asarray(loaded.faces)
    except IndexError as err:  # OBJ faces are resolved while parsing
        raise ValueError(
            f"cannot read mesh file {name}: face index out of range "
            f"(a face refers to a missing vertex: {err})"
        ) from err
    except Exception as err:  # trimesh raises many different types for bad files
        raise ValueError(f"cannot read mesh file {name}: {type(err).__name__}: {err}") from err
    if faces.size == 0:
        faces = faces.reshape(0, 3).astype(np.int64)
    if name.lower().endswith(".stl") and vertices.size:
        vertices, faces = merge_duplicate_vertices(vertices, faces)
    validate_mesh(vertices, faces, name=name, check_manifold=False)
    dtype = float_dtype(dtype)
    mesh = Mesh(jnp.asarray(vertices, dtype=dtype), jnp.asarray(faces, dtype=jnp.int32), name=name)
    mesh = remove_degenerate_faces(mesh)
    if not mesh_is_closed_manifold(np.asarray(mesh.faces)):
        warnings.warn(
            f"{name}: mesh is open or non-manifold (some edge is not shared by exactly two consistently "
            "wound faces); it will still be used",
            MeshWarning,
            stacklevel=2,
        )
    return mesh


def save_mesh(mesh: Mesh, path: str | os.PathLike) -> None:
    """Write ``mesh`` with trimesh; the format follows the file extension (e.g. .obj, .ply, .stl)."""
    import trimesh

    tm = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces), process=False)
    tm.export(os.fspath(path))
