"""Rotation of real SH coefficient vectors.

Convention: if ``g(ω) = f(Rᵀ ω)`` (the function f carried along by the rotation R, so a feature of
f at direction ω₀ appears in g at ``R ω₀``), then ``coeffs(g) = D(R) @ coeffs(f)``. D is
block-diagonal, one (2l+1)×(2l+1) orthogonal block per band, and ``D(R₁ R₂) = D(R₁) D(R₂)``,
``D(Rᵀ) = D(R)ᵀ``.

Method ("fitting at fixed directions"): for every band, ``Y_l(Rᵀ ω) = D_lᵀ Y_l(ω)`` holds for all
ω. Evaluating it at K = 2n + 1 fixed directions ω_k, chosen once per n so that the band matrices
``B_l[k, m] = Y_lm(ω_k)`` are well conditioned (condition number below 3 for n = 4, below 11 for
n <= 12), gives ``A_l = B_l D_l`` with ``A_l[k, j] = Y_lj(Rᵀ ω_k)``, hence ``D_l = B_l⁺ A_l`` with
the pseudo-inverse ``B_l⁺`` precomputed in float64. This is exact (the system is consistent; there
is no sampling error), costs one elementwise basis evaluation at K rotated directions plus one small
constant-matrix product per band, and is a polynomial in the entries of R: values and gradients are
finite for every R (poles, axes, R = I). Band 0 is 1 and band 1 is the permutation ``P R Pᵀ`` of R,
since ``Y_1 ∝ (y, z, x)``. :func:`rotate` evaluates only the band parts of f at the rotated
directions (``f_l(Rᵀ ω_k)``) and applies ``B_l⁺``, never forming D.

If R is not orthogonal the result is still defined (the same polynomial), but it is a rotation
matrix only for orthogonal R.
"""

from __future__ import annotations

from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._basis import _basis_list, sh_bands_of
from ._grids import _np_sh_basis

__all__ = ["rotation_matrix", "rotate", "rotate_zyz", "rotate_zyz_cs", "zyz_prepare_matrix"]

# full float32 accuracy on accelerators too (no TF32/bf16 passes in these small products)
_HIGHEST = jax.lax.Precision.HIGHEST

_PERM = (1, 2, 0)  # band 1 order (Y_1-1, Y_10, Y_11) ∝ (y, z, x)


@lru_cache(maxsize=32)
def _fit_tables(n: int) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """float64 fitting directions (K, 3), K = 2n + 1, and per-band pseudo-inverses B_l⁺ (2l+1, K).

    The directions are the best-conditioned of 256 seeded random sets (deterministic per n): the
    largest condition number over the bands is below 3 for n = 4 and below 11 for n <= 12.
    """
    k = 2 * n + 1
    rng = np.random.default_rng(n)
    best, best_w = np.inf, None
    for _ in range(256):
        w = rng.normal(size=(k, 3))
        w /= np.linalg.norm(w, axis=-1, keepdims=True)
        b = _np_sh_basis(w, n)
        cond = max(np.linalg.cond(b[:, l * l : (l + 1) ** 2]) for l in range(n))
        if cond < best:
            best, best_w = cond, w
    b = _np_sh_basis(best_w, n)
    pinvs = tuple(np.linalg.pinv(b[:, l * l : (l + 1) ** 2]) for l in range(n))
    best_w.setflags(write=False)
    return best_w, pinvs


def _check_rot(R: Array) -> None:
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {R.shape}")
    if not jnp.issubdtype(R.dtype, jnp.floating):
        raise ValueError(f"R must be a floating-point array, got dtype {R.dtype}")


def _band1(R: Array) -> Array:
    """D_1 = P R Pᵀ: D_1[a, b] = R[p(a), p(b)]."""
    p = jnp.asarray(_PERM)
    return R[..., p[:, None], p[None, :]]


def _rotated_basis(R: Array, n: int) -> list[Array]:
    """[Y_j(Rᵀ ω_k) for j < n²], each (..., K), at the K fitting directions ω_k."""
    w, _ = _fit_tables(n)
    w = jnp.asarray(w, dtype=R.dtype)
    # (Rᵀ ω_k)_a = Σ_b R[b, a] ω_k,b, kept as three (..., K) arrays so everything stays elementwise
    v = [sum(R[..., b, a, None] * w[:, b] for b in range(3)) for a in range(3)]
    return _basis_list(v[0], v[1], v[2], n)


def _band_blocks(R: Array, n: int) -> list[Array]:
    """The diagonal blocks D_l (..., 2l+1, 2l+1), l = 0..n-1."""
    blocks = [jnp.ones((*R.shape[:-2], 1, 1), R.dtype)]
    if n > 1:
        blocks.append(_band1(R))
    if n > 2:
        ys = _rotated_basis(R, n)
        _, pinvs = _fit_tables(n)
        for l in range(2, n):
            a_t = jnp.stack(ys[l * l : (l + 1) ** 2], axis=-2)  # (..., j, K) = A_lᵀ
            d_t = jnp.matmul(a_t, jnp.asarray(pinvs[l].T, dtype=R.dtype), precision=_HIGHEST)  # D_lᵀ
            blocks.append(jnp.swapaxes(d_t, -1, -2))
    return blocks


@partial(jax.jit, static_argnames=("n",))
def rotation_matrix(R: Float[ArrayLike, "... 3 3"], n: int) -> Float[Array, "... n2 n2"]:
    """SH rotation matrix D(R) of n bands (block-diagonal per band).

    Args:
        R: (..., 3, 3) rotation matrices (orthogonal, det +1).
        n: number of SH bands (>= 1).

    Returns:
        (..., n², n²) matrices with ``coeffs(f ∘ Rᵀ) = D(R) @ coeffs(f)``. Exact (no sampling
        error) for any n; see the module docstring for the method. Use :func:`rotate` to apply a
        rotation without forming D.
    """
    if int(n) != n or n < 1:
        raise ValueError(f"n (number of SH bands) must be a positive integer, got {n}")
    R = jnp.asarray(R)
    _check_rot(R)
    blocks = _band_blocks(R, n)
    batch = R.shape[:-2]
    rows = []
    for l, blk in enumerate(blocks):
        left = jnp.zeros((*batch, 2 * l + 1, l * l), R.dtype)
        right = jnp.zeros((*batch, 2 * l + 1, n * n - (l + 1) ** 2), R.dtype)
        rows.append(jnp.concatenate([left, blk, right], axis=-1))
    return jnp.concatenate(rows, axis=-2)


@jax.jit
def rotate(coeffs: Float[ArrayLike, "... n2"], R: Float[ArrayLike, "... 3 3"]) -> Float[Array, "... n2"]:
    """Rotate SH coefficients: ``coeffs(f ∘ Rᵀ) = D(R) @ coeffs``, without forming D.

    Args:
        coeffs: (..., n²) coefficients of f.
        R: (..., 3, 3) rotation matrices; batch axes broadcast against those of ``coeffs``.

    Returns:
        (..., n²) coefficients of the rotated function. For bands l >= 2 this evaluates the band-l
        part of f at the K rotated fitting directions and applies ``B_l⁺`` (same method as
        :func:`rotation_matrix`).
    """
    coeffs, R = jnp.asarray(coeffs), jnp.asarray(R)
    _check_rot(R)
    n = sh_bands_of(coeffs.shape[-1])
    out = [coeffs[..., :1] + jnp.zeros(R.shape[:-2] + (1,), R.dtype)]
    if n > 1:
        d1 = _band1(R)
        out.append(
            jnp.stack([sum(d1[..., i, j] * coeffs[..., 1 + j] for j in range(3)) for i in range(3)], -1)
        )
    if n > 2:
        ys = _rotated_basis(R, n)
        _, pinvs = _fit_tables(n)
        for l in range(2, n):
            f_l = sum(coeffs[..., j, None] * ys[j] for j in range(l * l, (l + 1) ** 2))  # f_l(Rᵀ ω_k)
            out.append(jnp.matmul(f_l, jnp.asarray(pinvs[l].T, dtype=R.dtype), precision=_HIGHEST))
    return jnp.concatenate(out, axis=-1)


# ---- rotations given by Euler angles (z-y-z) -----------------------------------------------------


def _np_rotation_matrix(R: np.ndarray, n: int) -> np.ndarray:
    """float64 NumPy D(R) (n², n²) by the same fitting method (constant tables, outside any trace)."""
    w, pinvs = _fit_tables(n)
    y = _np_sh_basis(w @ np.asarray(R, np.float64), n)  # rows: Y(Rᵀ ω_k)
    d = np.zeros((n * n, n * n))
    for l in range(n):
        sl = slice(l * l, (l + 1) ** 2)
        d[sl, sl] = pinvs[l] @ y[:, sl]
    return d


def _np_rz(alpha: float) -> np.ndarray:
    c, s = np.cos(alpha), np.sin(alpha)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@lru_cache(maxsize=16)
def _zyz_tables(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Constant tables of :func:`rotate_zyz` (float64): |m| (n²,), the partner index of m ↔ −m and
    its sign, so that ``D(R_z(α)) c = cos(|m|α) c + sin(|m|α) sign · c[partner]``; and D(Q) with
    Q = R_x(−90°) (Q e_z = e_y, so ``R_y(β) = Q R_z(β) Qᵀ``)."""
    alpha = 0.7
    d = _np_rotation_matrix(_np_rz(alpha), n)
    mabs = np.zeros(n * n, np.int32)
    partner = np.arange(n * n, dtype=np.int32)
    sign = np.zeros(n * n)
    for l in range(n):
        for m in range(-l, l + 1):
            i, j = l * l + l + m, l * l + l - m
            mabs[i] = abs(m)
            if m != 0:
                partner[i] = j
                sign[i] = d[i, j] / np.sin(abs(m) * alpha)
    rebuilt = np.cos(mabs * alpha)[:, None] * np.eye(n * n)
    rebuilt[np.arange(n * n), partner] += np.sin(mabs * alpha) * sign
    if not np.allclose(rebuilt, d, atol=1e-9):  # the real-SH convention is what this assumes
        raise AssertionError("D(R_z) does not have the cos/sin(|m|α) structure")
    q = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # R_x(−90°)
    dq = _np_rotation_matrix(q, n)
    for arr in (mabs, partner, sign, dq):
        arr.setflags(write=False)
    return mabs, partner, sign, dq


def _apply_rz(c: Array, cos1: Array, sin1: Array, n: int) -> Array:
    """``D(R_z(α)) c`` from cos α and sin α (batch axes of the angle broadcast against c's)."""
    mabs, partner, sign, _ = _zyz_tables(n)
    # cos(mα), sin(mα) for m < n by the angle-addition recurrence (no transcendental at all)
    cs, sn = [jnp.ones_like(cos1)], [jnp.zeros_like(sin1)]
    for _ in range(1, n):
        cs, sn = cs + [cs[-1] * cos1 - sn[-1] * sin1], sn + [sn[-1] * cos1 + cs[-1] * sin1]
    cos_ma, sin_ma = jnp.stack(cs, -1), jnp.stack(sn, -1)  # (..., n)
    # constant 0/1 and signed-permutation matrices instead of gathers (XLA:CPU gathers are slow)
    expand = jnp.asarray(np.eye(n)[mabs].T, c.dtype)  # (n, n²)
    swap = np.zeros((n * n, n * n))
    swap[partner, np.arange(n * n)] = sign  # (c @ swap)[i] = sign_i c[partner_i]
    cos_m = jnp.matmul(cos_ma, expand, precision=_HIGHEST)
    sin_m = jnp.matmul(sin_ma, expand, precision=_HIGHEST)
    return cos_m * c + sin_m * jnp.matmul(c, jnp.asarray(swap, c.dtype), precision=_HIGHEST)


def rotate_zyz_cs(
    coeffs: Float[ArrayLike, "... n2"],
    cos_sin_alpha: tuple[Float[ArrayLike, "..."], Float[ArrayLike, "..."]],
    cos_sin_beta: tuple[Float[ArrayLike, "..."], Float[ArrayLike, "..."]],
    cos_sin_gamma: tuple[Float[ArrayLike, "..."], Float[ArrayLike, "..."]] | None = None,
    prepared: bool = False,
) -> Float[Array, "... n2"]:
    """:func:`rotate_zyz` with each Euler angle given by its (cosine, sine) pair.

    For callers that already hold them (a direction's components give cos θ, sin θ, cos φ, sin φ
    with a division each), this skips every trigonometric function. The pairs are not
    renormalised: pass (cos, sin) of a real angle.

    ``prepared=True`` (only without γ): ``coeffs`` are already ``coeffs @ zyz_prepare_matrix(n)``
    (the constant first step of the y rotation, e.g. folded into a table of coefficients that
    many rotations read), which saves one n²×n² product per rotation.
    """
    coeffs = jnp.asarray(coeffs)
    n = sh_bands_of(coeffs.shape[-1])
    pairs = [cos_sin_alpha, cos_sin_beta] + ([cos_sin_gamma] if cos_sin_gamma is not None else [])
    dtype = jnp.result_type(coeffs.dtype, *(jnp.asarray(v).dtype for p in pairs for v in p))
    ca, sa = (jnp.asarray(v, dtype) for v in cos_sin_alpha)
    cb, sb = (jnp.asarray(v, dtype) for v in cos_sin_beta)
    c = coeffs.astype(dtype)
    dq = jnp.asarray(_zyz_tables(n)[3], dtype)
    if prepared and cos_sin_gamma is not None:
        raise ValueError("prepared=True applies to rotations without γ only")
    if cos_sin_gamma is not None:
        cg, sg = (jnp.asarray(v, dtype) for v in cos_sin_gamma)
        c = _apply_rz(c, cg, sg, n)
    if not prepared:
        c = jnp.matmul(c, dq, precision=_HIGHEST)  # D(Q)ᵀ c (row-vector form)
    c = _apply_rz(c, cb, sb, n)
    c = jnp.matmul(c, dq.T, precision=_HIGHEST)  # D(Q) c
    return _apply_rz(c, ca, sa, n)


def zyz_prepare_matrix(n: int) -> np.ndarray:
    """The constant (n², n²) float64 matrix that :func:`rotate_zyz_cs` (``prepared=False``) first
    multiplies row-vector coefficients by: ``D(Q)ᵀ`` with ``Q = R_x(−90°)``, read-only."""
    return _zyz_tables(int(n))[3]


def rotate_zyz(
    coeffs: Float[ArrayLike, "... n2"],
    alpha: Float[ArrayLike, "..."],
    beta: Float[ArrayLike, "..."],
    gamma: Float[ArrayLike, "..."] | None = None,
) -> Float[Array, "... n2"]:
    """Rotate SH coefficients by ``R = R_z(α) R_y(β) R_z(γ)`` (angles in radians): ``D(R) @ coeffs``.

    Same convention as :func:`rotate` (``coeffs(f ∘ Rᵀ)``), cheaper when the rotation is known by
    its Euler angles: two z rotations cost a cosine and a sine of ``mα`` per order (no basis
    evaluation), and the y rotation is ``D(Q) D(R_z(β)) D(Q)ᵀ`` with the constant D(Q) of
    ``Q = R_x(−90°)`` (two n²×n² products with a constant block-diagonal matrix). ``gamma=None``
    skips the last z rotation. Batch axes of the angles broadcast against those of ``coeffs``.
    Smooth in the angles (values and gradients finite everywhere); at β = 0 or π the split of a
    z rotation between α and γ is of course arbitrary.
    """
    coeffs = jnp.asarray(coeffs)
    dtype = jnp.result_type(coeffs.dtype, jnp.asarray(alpha).dtype)
    cs = [(jnp.cos(a), jnp.sin(a)) for a in (jnp.asarray(x, dtype) for x in (alpha, beta))]
    csg = None if gamma is None else (jnp.cos(jnp.asarray(gamma, dtype)), jnp.sin(jnp.asarray(gamma, dtype)))
    return rotate_zyz_cs(coeffs.astype(dtype), cs[0], cs[1], csg)
