"""Parametric deformations of a mesh in its normalised frame.

A :class:`~jshadow.entities.MeshOccluder`'s world vertices at animation time t ∈ [0, 1] are
``center + radius · deform(unit_vertices, t)``, where ``unit_vertices`` lie in the unit bounding
sphere at the origin (DESIGN.md §3). Deformations therefore act in that normalised frame and their
amounts are scale-free (per unit of bounding radius). The deformable-shadow-fields paper handles
arbitrary non-rigid motion by resampling an occluder's base sphere visibility in every frame in which
it deforms; the deformations here are simple parametric ones (global bend, twist and taper after
Barr 1984, "Global and local deformations of solid primitives"), whose few amounts can be fitted.

Every deformation is an ``equinox.Module`` called as ``deform(x, t)``:

* ``x`` (..., V, 3) points, ``t`` animation time (a scalar or an array whose shape broadcasts
  against the leading axes of ``x``; e.g. ``x`` (V, 3) and ``t`` (T,) give (T, V, 3));
* the amount at time t is ``amount_start + (amount_end - amount_start) · t``; both are float pytree
  leaves, so ``jax.grad``/``jax.jvp`` differentiate with respect to them (and to ``x``);
* an amount of 0 is exactly the identity: every map is written as ``x + Δ`` with Δ exactly 0 there,
  and value and gradient are finite at 0 (a bend's 0/0 limit uses a Taylor branch behind a double
  ``where``).

``axis`` names the coordinate axis a deformation is organised around ("x", "y" or "z", or 0/1/2;
default "y", the world's up axis); ``origin`` is the coordinate along ``axis`` of the plane the
deformation leaves fixed (default 0, the bounding-sphere centre; -1 keeps the bottom of the unit
sphere in place). Computations run in the dtype of ``x``.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._numerics import eps

__all__ = [
    "Bend",
    "Twist",
    "Taper",
    "SquashStretch",
    "Breathe",
    "Offsets",
    "Compose",
    "make_deformation",
    "DEFORMATION_TYPES",
]

_AXES = {"x": 0, "y": 1, "z": 2}


def _axis_index(axis, what: str = "axis") -> int:
    if isinstance(axis, str) and axis.lower() in _AXES:
        return _AXES[axis.lower()]
    if isinstance(axis, int | np.integer) and not isinstance(axis, bool) and 0 <= int(axis) <= 2:
        return int(axis)
    raise ValueError(f"{what} must be 'x', 'y' or 'z' (or 0, 1, 2), got {axis!r}")


def _others(ai: int) -> tuple[int, int]:
    """The two other axes (b, c) such that (a, b, c) is a cyclic (right-handed) order."""
    return (ai + 1) % 3, (ai + 2) % 3


def _check_points(x) -> Float[Array, "... V 3"]:
    x = jnp.asarray(x)
    if x.ndim < 2 or x.shape[-1] != 3:
        raise ValueError(f"a deformation expects points of shape (..., V, 3), got {x.shape}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        raise ValueError(f"a deformation expects floating-point points, got dtype {x.dtype}")
    return x


def _amount_at(a0, a1, t, dtype) -> Float[Array, "... 1"]:
    """Amount a0 + (a1 - a0)·t in ``dtype``, with a trailing axis to broadcast against V."""
    a0 = jnp.asarray(a0, dtype)
    a1 = jnp.asarray(a1, dtype)
    t = jnp.asarray(t, dtype)
    return (a0 + (a1 - a0) * t)[..., None]


def _assemble(x, ai: int, new: dict[int, Array]) -> Float[Array, "... V 3"]:
    """Stack components: axis i from ``new`` if given, else ``x``'s, broadcast to a common shape."""
    comps = [new.get(i, x[..., i]) for i in range(3)]
    shape = jnp.broadcast_shapes(*(c.shape for c in comps))
    return jnp.stack([jnp.broadcast_to(c, shape) for c in comps], axis=-1)


def _sin_half_sq2(theta):
    """1 - cos θ computed as 2 sin²(θ/2) (no cancellation near 0)."""
    s = jnp.sin(0.5 * theta)
    return 2.0 * s * s


def _bend_factors(theta):
    """(sin θ/θ - 1, (1 - cos θ)/θ) with a Taylor branch near θ = 0 (both → 0 there)."""
    dtype = theta.dtype
    thr = min(1.0, (eps(dtype) * 4.0e7) ** 0.1)  # series remainder ~θ¹⁰/4·10⁷ below eps at |θ| < thr
    small = jnp.abs(theta) < thr
    th_safe = jnp.where(small, 1.0, theta)  # double where: the direct formulas never see θ = 0
    sinc_m1_direct = jnp.sin(th_safe) / th_safe - 1.0
    g_direct = _sin_half_sq2(th_safe) / th_safe
    t2 = theta * theta
    sinc_m1_series = t2 * (-1.0 / 6.0 + t2 * (1.0 / 120.0 + t2 * (-1.0 / 5040.0 + t2 / 362880.0)))
    g_series = theta * (
        0.5 + t2 * (-1.0 / 24.0 + t2 * (1.0 / 720.0 + t2 * (-1.0 / 40320.0 + t2 / 3628800.0)))
    )
    return jnp.where(small, sinc_m1_series, sinc_m1_direct), jnp.where(small, g_series, g_direct)


class _AxialDeformation(eqx.Module):
    """Shared fields of the deformations that act along one axis: the amount at t = 0 and t = 1
    (linear in between), the axis (0, 1, 2 or "x", "y", "z") and the fixed plane's coordinate along
    it. Subclasses define ``_apply(x, t)``."""

    amount_start: Float[Array, ""]
    amount_end: Float[Array, ""]
    axis: int = eqx.field(static=True)
    origin: float = eqx.field(static=True)

    def __init__(self, amount_start, amount_end=None, axis="y", origin: float = 0.0):
        self.amount_start = jnp.asarray(amount_start)
        self.amount_end = jnp.asarray(amount_start if amount_end is None else amount_end)
        self.axis = _axis_index(axis, f"{type(self).__name__} axis")
        self.origin = float(origin)

    def __call__(self, x: Float[Array, "... V 3"], t=0.0) -> Float[Array, "... V 3"]:
        x = _check_points(x)
        return self._apply(x, jnp.asarray(t, x.dtype))

    def _apply(self, x, t):
        raise TypeError(f"{type(self).__name__} must define _apply(x, t)")


class Bend(eqx.Module):
    """Bend the ``axis`` (the spine, default y) into a circular arc curving toward ``toward`` (default x).

    ``amount`` κ is the bend angle in radians per unit length along the spine (the curvature of the
    bent spine, 1/radius, in units of the bounding radius); 0 is the identity. With h = x_axis −
    origin, u = x_toward, θ = κ h, the bending axis being the third coordinate (unchanged)::

        u' = u cos θ + h (1 − cos θ)/θ        (the spine bends toward +u for κ > 0)
        h' = h sin θ/θ − u sin θ

    This is Barr's global bend: the plane h = 0 stays fixed, lines across the spine stay straight and
    perpendicular to it, and the spine keeps its length. Points with u > 1/κ fold over; keep
    |κ| ≲ 1 for a unit-sphere-normalised mesh. The 0/0 at θ = 0 (κ = 0 or h = 0) uses a Taylor
    series behind a double ``where``, so value and gradient are finite there.
    """

    amount_start: Float[Array, ""]
    amount_end: Float[Array, ""]
    axis: int = eqx.field(static=True)
    toward: int = eqx.field(static=True)
    origin: float = eqx.field(static=True)

    def __init__(self, amount_start, amount_end=None, axis="y", toward="x", origin: float = 0.0):
        self.amount_start = jnp.asarray(amount_start)
        self.amount_end = jnp.asarray(amount_start if amount_end is None else amount_end)
        self.axis = _axis_index(axis, "Bend axis")
        self.toward = _axis_index(toward, "Bend toward")
        if self.toward == self.axis:
            raise ValueError(f"Bend 'toward' must differ from 'axis' (both are {'xyz'[self.axis]!r})")
        self.origin = float(origin)

    def __call__(self, x: Float[Array, "... V 3"], t=0.0) -> Float[Array, "... V 3"]:
        x = _check_points(x)
        return self._apply(x, jnp.asarray(t, x.dtype))

    @eqx.filter_jit
    def _apply(self, x, t):
        k = _amount_at(self.amount_start, self.amount_end, t, x.dtype)
        ha, u = x[..., self.axis], x[..., self.toward]
        h = ha - self.origin
        theta = k * h
        sinc_m1, g = _bend_factors(theta)
        u_new = u + (h * g - u * _sin_half_sq2(theta))  # u cos θ + h(1 − cos θ)/θ
        h_new = ha + (h * sinc_m1 - u * jnp.sin(theta))  # origin + h sin θ/θ − u sin θ
        return _assemble(x, self.axis, {self.axis: h_new, self.toward: u_new})


class Twist(_AxialDeformation):
    """Rotate each slice perpendicular to ``axis`` (default y) by ``amount · (x_axis − origin)`` radians.

    ``amount`` is the twist rate in radians per unit length (right-handed about +axis); 0 is the
    identity. Distances to the axis and heights are preserved (an isometry of each slice), so the
    volume is preserved exactly.
    """

    @eqx.filter_jit
    def _apply(self, x, t):
        a = _amount_at(self.amount_start, self.amount_end, t, x.dtype)
        bi, ci = _others(self.axis)
        xb, xc = x[..., bi], x[..., ci]
        ang = a * (x[..., self.axis] - self.origin)
        one_m_cos, s = _sin_half_sq2(ang), jnp.sin(ang)
        b_new = xb - (xb * one_m_cos + xc * s)  # xb cos − xc sin
        c_new = xc + (xb * s - xc * one_m_cos)  # xb sin + xc cos
        return _assemble(x, self.axis, {bi: b_new, ci: c_new})


class Taper(_AxialDeformation):
    """Scale the two coordinates perpendicular to ``axis`` by ``1 + amount · (x_axis − origin)``.

    ``amount`` is the relative change of width per unit length along the axis (> 0 widens toward
    +axis); 0 is the identity. The factor becomes negative (the shape inverts) where
    amount · h < −1: keep |amount| < 1 for a unit-sphere-normalised mesh.
    """

    @eqx.filter_jit
    def _apply(self, x, t):
        a = _amount_at(self.amount_start, self.amount_end, t, x.dtype)
        bi, ci = _others(self.axis)
        d = a * (x[..., self.axis] - self.origin)  # factor − 1
        return _assemble(x, self.axis, {bi: x[..., bi] + x[..., bi] * d, ci: x[..., ci] + x[..., ci] * d})


def _squash(x, s_m1, ai: int, origin: float):
    """Volume-preserving scale: along ``ai`` by s = 1 + s_m1, across by 1/√s (s clamped to > 0)."""
    s_m1 = jnp.maximum(s_m1, eps(x.dtype) - 1.0)  # keep s > 0 (no NaN from 1/√s)
    inv_sqrt_m1 = jax.lax.rsqrt(1.0 + s_m1) - 1.0  # exactly 0 at s = 1
    bi, ci = _others(ai)
    return _assemble(
        x,
        ai,
        {
            ai: x[..., ai] + (x[..., ai] - origin) * s_m1,
            bi: x[..., bi] + x[..., bi] * inv_sqrt_m1,
            ci: x[..., ci] + x[..., ci] * inv_sqrt_m1,
        },
    )


class SquashStretch(_AxialDeformation):
    """Volume-preserving stretch along ``axis`` by s = 1 + amount, squash across it by 1/√s.

    ``amount`` > 0 stretches (taller and thinner), −1 < amount < 0 squashes; 0 is the identity. The
    Jacobian determinant is s · (1/√s)² = 1, so volumes are preserved exactly (not just to first
    order). Amounts ≤ −1 are clamped to s = eps (no NaN); :func:`make_deformation` rejects them.
    """

    @eqx.filter_jit
    def _apply(self, x, t):
        a = _amount_at(self.amount_start, self.amount_end, t, x.dtype)
        return _squash(x, a, self.axis, self.origin)


class Breathe(eqx.Module):
    """A periodic :class:`SquashStretch` ("an egg that breathes").

    At time t the squash-stretch amount is ``A(t) · sin(2π t / period)``, where the amplitude
    A(t) = amplitude_start + (amplitude_end − amplitude_start)·t (fields ``amount_start``,
    ``amount_end``) and ``period`` is in units of animation time (1 = one breath over the animation).
    Amplitude 0 is the identity. Differentiable with respect to the amplitudes and the period.
    ``periodic`` is True: the shape changes over time even when amount_start == amount_end.
    """

    amount_start: Float[Array, ""]
    amount_end: Float[Array, ""]
    period: Float[Array, ""]
    axis: int = eqx.field(static=True)
    origin: float = eqx.field(static=True)

    def __init__(self, amount_start, amount_end=None, period=1.0, axis="y", origin: float = 0.0):
        self.amount_start = jnp.asarray(amount_start)
        self.amount_end = jnp.asarray(amount_start if amount_end is None else amount_end)
        self.period = jnp.asarray(period)
        self.axis = _axis_index(axis, "Breathe axis")
        self.origin = float(origin)

    @property
    def periodic(self) -> bool:
        return True

    def __call__(self, x: Float[Array, "... V 3"], t=0.0) -> Float[Array, "... V 3"]:
        x = _check_points(x)
        return self._apply(x, jnp.asarray(t, x.dtype))

    @eqx.filter_jit
    def _apply(self, x, t):
        amp = _amount_at(self.amount_start, self.amount_end, t, x.dtype)
        t = jnp.asarray(t, x.dtype)[..., None]
        s_m1 = amp * jnp.sin((2.0 * math.pi) * t / jnp.asarray(self.period, x.dtype))
        return _squash(x, s_m1, self.axis, self.origin)


class Offsets(eqx.Module):
    """Free per-vertex displacements, for fitting: ``x + offsets(t)``.

    ``amount_start`` and ``amount_end`` are (V, 3) arrays (in units of the bounding radius);
    offsets(t) interpolates them linearly. Zero offsets are the identity. ``x`` must have V vertices.
    """

    amount_start: Float[Array, "V 3"]
    amount_end: Float[Array, "V 3"]

    def __init__(self, amount_start, amount_end=None):
        self.amount_start = jnp.asarray(amount_start)
        self.amount_end = jnp.asarray(amount_start if amount_end is None else amount_end)
        for name in ("amount_start", "amount_end"):
            shape = getattr(self, name).shape
            if len(shape) != 2 or shape[-1] != 3:
                raise ValueError(f"Offsets.{name} must have shape (V, 3), got {shape}")
        if self.amount_start.shape != self.amount_end.shape:
            raise ValueError(
                f"Offsets start and end shapes differ: {self.amount_start.shape} vs {self.amount_end.shape}"
            )

    def __call__(self, x: Float[Array, "... V 3"], t=0.0) -> Float[Array, "... V 3"]:
        x = _check_points(x)
        if x.shape[-2] != self.amount_start.shape[0]:
            raise ValueError(
                f"Offsets hold {self.amount_start.shape[0]} vertices but the points have {x.shape[-2]}"
            )
        a0 = jnp.asarray(self.amount_start, x.dtype)
        a1 = jnp.asarray(self.amount_end, x.dtype)
        t = jnp.asarray(t, x.dtype)[..., None, None]
        return x + (a0 + (a1 - a0) * t)


class Compose(eqx.Module):
    """Apply several deformations in order: ``d_n(… d_2(d_1(x, t), t) …, t)``."""

    deformations: tuple

    def __init__(self, *deformations):
        if len(deformations) == 1 and isinstance(deformations[0], tuple | list):
            deformations = tuple(deformations[0])
        self.deformations = tuple(deformations)

    def __call__(self, x: Float[Array, "... V 3"], t=0.0) -> Float[Array, "... V 3"]:
        x = _check_points(x)
        for d in self.deformations:
            x = d(x, t)
        return x


# type -> (class, accepted keyword parameters besides the amount)
DEFORMATION_TYPES: dict[str, tuple[type, tuple[str, ...]]] = {
    "bend": (Bend, ("axis", "toward", "origin")),
    "twist": (Twist, ("axis", "origin")),
    "taper": (Taper, ("axis", "origin")),
    "squash_stretch": (SquashStretch, ("axis", "origin")),
    "breathe": (Breathe, ("period", "axis", "origin")),
    "offsets": (Offsets, ()),
}
_ALIASES = {"squash-stretch": "squash_stretch", "squashstretch": "squash_stretch", "offset": "offsets"}


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _split_amount(kind: str, amount):
    """(start, end) of a scalar amount given as a number or a pair; tracers pass through."""
    if isinstance(amount, tuple | list):
        if len(amount) != 2:
            raise ValueError(
                f"deformation {kind!r}: amount must be a number or a pair [start, end], "
                f"got {len(amount)} values"
            )
        return amount[0], amount[1]
    shape = np.shape(amount)
    if shape == ():
        return amount, amount
    if shape == (2,):
        return amount[0], amount[1]
    raise ValueError(
        f"deformation {kind!r}: amount must be a number or a pair [start, end], got shape {shape}"
    )


def _check_finite(kind: str, *values, what: str = "amount") -> None:
    for v in values:
        if _is_tracer(v):
            continue
        arr = np.asarray(v)
        if not np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_:
            raise ValueError(f"deformation {kind!r}: {what} must be a number, got {v!r}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"deformation {kind!r}: {what} must be finite, got {arr.tolist()}")


def make_deformation(type: str, amount=0.0, **params):
    """Build a deformation from its config form, e.g. ``make_deformation("bend", (0.0, 0.8))``.

    ``type``: one of :data:`DEFORMATION_TYPES` (bend, twist, taper, squash_stretch, breathe,
    offsets). ``amount``: a number (constant over the animation) or a pair (start, end) interpolated
    over t ∈ [0, 1]; for "breathe" it is the amplitude; for "offsets" an array (V, 3) or a pair of
    them (or an array (2, V, 3)). Amounts may be JAX tracers (``build_scene`` under ``jax.grad``).
    ``params``: the type's keyword options (``axis``, ``toward``, ``origin``, ``period``).

    Raises ``ValueError`` naming an unknown type or parameter, a malformed or non-finite amount, a
    squash_stretch amount ≤ −1, or a non-positive breathe period.
    """
    kind = str(type).lower()
    kind = _ALIASES.get(kind, kind)
    if kind not in DEFORMATION_TYPES:
        raise ValueError(
            f"unknown deformation type {type!r}; expected one of {', '.join(sorted(DEFORMATION_TYPES))}"
        )
    cls, allowed = DEFORMATION_TYPES[kind]
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        raise ValueError(
            f"unknown parameter {unknown[0]!r} for deformation {kind!r}; "
            f"allowed: {', '.join(('amount',) + allowed)}"
        )
    if kind == "offsets":
        if isinstance(amount, tuple | list) and len(amount) == 2 and np.ndim(amount[0]) == 2:
            start, end = amount
        elif np.ndim(amount) == 3 and np.shape(amount)[0] == 2:
            start, end = amount[0], amount[1]
        elif np.ndim(amount) == 2:
            start, end = amount, amount
        else:
            raise ValueError(
                f"deformation 'offsets': amount must be an array (V, 3) or a pair of them, "
                f"got shape {np.shape(amount)}"
            )
        _check_finite(kind, start, end)
        return Offsets(start, end)
    start, end = _split_amount(kind, amount)
    _check_finite(kind, start, end)
    if kind == "squash_stretch":
        for v in (start, end):
            if not _is_tracer(v) and not float(np.asarray(v)) > -1.0:
                raise ValueError(
                    f"deformation 'squash_stretch': amount must be > -1 (scale s = 1 + amount > 0), got {v}"
                )
    if kind == "breathe" and "period" in params:
        p = params["period"]
        _check_finite(kind, p, what="period")
        if not _is_tracer(p) and not float(np.asarray(p)) > 0.0:
            raise ValueError(f"deformation 'breathe': period must be > 0, got {p}")
    if "origin" in params and not _is_tracer(params["origin"]):
        o = params["origin"]
        if not isinstance(o, int | float | np.floating | np.integer) or not math.isfinite(float(o)):
            raise ValueError(f"deformation {kind!r}: origin must be a finite number, got {o!r}")
    return cls(start, end, **params)
