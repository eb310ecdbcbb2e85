"""Procedural closed meshes: a subdivided icosahedron (icosphere) and an egg.

Both are built in float64 NumPy and returned as :class:`Mesh` in the requested dtype; both are
closed, manifold, genus 0, with outward (counter-clockwise seen from outside) winding.
"""

from __future__ import annotations

import itertools

import jax.numpy as jnp
import numpy as np

from ._mesh import Mesh, float_dtype

__all__ = ["icosphere", "egg"]

_MAX_SUBDIVISIONS = 7  # 327 682 vertices


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    p = (1.0 + 5.0**0.5) / 2.0
    v = []
    for s1 in (-1.0, 1.0):
        for s2 in (-p, p):
            v += [(0.0, s1, s2), (s1, s2, 0.0), (s2, 0.0, s1)]
    v = np.asarray(v)
    # faces: the 20 vertex triples whose three edges all have the icosahedron's edge length 2
    faces = [
        f
        for f in itertools.combinations(range(12), 3)
        if all(abs(np.linalg.norm(v[i] - v[j]) - 2.0) < 1e-9 for i, j in itertools.combinations(f, 2))
    ]
    faces = np.asarray(faces, dtype=np.int64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    inward = np.sum(np.cross(b - a, c - a) * (a + b + c), axis=-1) < 0  # convex, centred at 0
    faces[inward] = faces[inward][:, [0, 2, 1]]
    return v / np.linalg.norm(v, axis=-1, keepdims=True), faces


def _subdivide(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split each triangle into four at its edge midpoints (projected onto the unit sphere)."""
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    inv = inv.reshape(3, -1) + v.shape[0]
    mid = v[uniq[:, 0]] + v[uniq[:, 1]]
    v = np.concatenate([v, mid / np.linalg.norm(mid, axis=-1, keepdims=True)])
    ab, bc, ca = inv
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    f = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return v, f


def _check_subdivisions(subdivisions) -> int:
    if not isinstance(subdivisions, int | np.integer) or not 0 <= subdivisions <= _MAX_SUBDIVISIONS:
        raise ValueError(f"subdivisions must be an integer in 0..{_MAX_SUBDIVISIONS}, got {subdivisions!r}")
    return int(subdivisions)


def _unit_icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    v, f = _icosahedron()
    for _ in range(subdivisions):
        v, f = _subdivide(v, f)
    return v, f


def icosphere(subdivisions: int = 2, dtype=None) -> Mesh:
    """The unit sphere as a subdivided icosahedron: 10·4^s + 2 vertices, 20·4^s faces.

    Every vertex lies on the unit sphere at the origin (so its bounding sphere is the unit sphere).
    ``dtype`` defaults to JAX's default float.
    """
    v, f = _unit_icosphere(_check_subdivisions(subdivisions))
    dtype = float_dtype(dtype)
    return Mesh(jnp.asarray(v, dtype), jnp.asarray(f, jnp.int32), name=f"icosphere({subdivisions})")


def egg(subdivisions: int = 2, stretch: float = 0.2, dtype=None) -> Mesh:
    """An egg: the unit icosphere with its +y end stretched, ``y' = y · (1 + stretch · (1 + y))``.

    x and z are unchanged, so the widest circle (radius 1) stays at y = 0; the bottom (y = −1) stays
    at −1 and the top moves to 1 + 2·stretch. The map is monotone in y for 0 ≤ stretch < 1, so the
    mesh stays closed, manifold and outward-wound. Not normalised: use
    :func:`normalize_to_unit_sphere` for an occluder's rest pose.
    """
    if not 0.0 <= float(stretch) < 1.0:
        raise ValueError(f"egg stretch must be in [0, 1), got {stretch!r}")
    v, f = _unit_icosphere(_check_subdivisions(subdivisions))
    y = v[:, 1]
    v = np.stack([v[:, 0], y * (1.0 + stretch * (1.0 + y)), v[:, 2]], axis=1)
    dtype = float_dtype(dtype)
    return Mesh(jnp.asarray(v, dtype), jnp.asarray(f, jnp.int32), name=f"egg({subdivisions})")
