"""SH rotation: re-projection of the rotated function, group laws, batch shapes, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from jshadow._numerics import eps, safe_acos, safe_atan2
from jshadow.sh import project, rotate, rotate_zyz, rotate_zyz_cs, rotation_matrix, sh_basis, sphere_grid


def _random_rot(seed, shape=()):
    r = Rotation.random(int(np.prod(shape)) or 1, random_state=seed).as_matrix()
    return r.reshape(*shape, 3, 3)


def _axis_rot(axis, angle):
    return Rotation.from_rotvec(np.asarray(axis, dtype=np.float64) * angle).as_matrix()


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("n", range(1, 9))
def test_equals_reprojection_of_rotated_function(n):
    rng = np.random.default_rng(n)
    R = _random_rot(n)
    c = rng.normal(size=n * n)
    d, w = sphere_grid(n, 2 * n - 1)
    # g(ω) = f(Rᵀ ω); row-vector form: Rᵀ ω_k = (ω_kᵀ R)ᵀ
    g = sh_basis(d @ R, n) @ c
    want = project(g, d, w, n)
    D = rotation_matrix(jnp.asarray(R), n)
    np.testing.assert_allclose(D @ c, want, atol=1e-12)
    np.testing.assert_allclose(rotate(jnp.asarray(c), jnp.asarray(R)), want, atol=1e-12)


@pytest.mark.usefixtures("x64")
def test_feature_moves_with_the_rotation():
    # f peaked at +z (a clamped-cosine-like lobe): after rotating by R its peak is at R ẑ.
    n = 6
    d, w = sphere_grid(8, 16)
    c = project(jnp.maximum(d[:, 2], 0.0) ** 4, d, w, n)
    R = _axis_rot([1.0, 0, 0], np.pi / 2)  # ẑ -> -ŷ
    g = rotate(c, jnp.asarray(R))
    probe = jnp.asarray([[0, -1.0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    vals = sh_basis(probe, n) @ g
    assert vals[0] > 0.5 and abs(float(vals[1])) < 0.1 and abs(float(vals[2])) < 0.1


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("n", [2, 4, 8])
def test_group_laws(n):
    R1, R2 = _random_rot(7, (2,))
    D1, D2 = rotation_matrix(jnp.asarray(R1), n), rotation_matrix(jnp.asarray(R2), n)
    tol = eps(jnp.float64, 100)
    np.testing.assert_allclose(rotation_matrix(jnp.asarray(R1 @ R2), n), D1 @ D2, atol=tol)
    np.testing.assert_allclose(D1 @ D1.T, np.eye(n * n), atol=tol)
    np.testing.assert_allclose(rotation_matrix(jnp.asarray(R1.T), n), D1.T, atol=tol)
    np.testing.assert_allclose(rotation_matrix(jnp.eye(3), n), np.eye(n * n), atol=tol)
    # block-diagonal per band
    band = np.repeat(np.arange(n), 2 * np.arange(n) + 1)
    assert np.all(np.asarray(D1)[band[:, None] != band[None, :]] == 0)


@pytest.mark.usefixtures("x64")
def test_band1_is_permuted_rotation():
    # f(ω) = a·ω has band-1 coefficients sqrt(4π/3)·(a_y, a_z, a_x); f(Rᵀω) = (R a)·ω.
    R = _random_rot(3)
    a = np.array([0.3, -1.2, 0.7])
    perm = [1, 2, 0]
    c = np.zeros(4)
    c[1:] = np.sqrt(4 * np.pi / 3) * a[perm]
    want = np.sqrt(4 * np.pi / 3) * (R @ a)[perm]
    np.testing.assert_allclose(rotate(jnp.asarray(c), jnp.asarray(R))[1:], want, atol=1e-14)


@given(q=st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1))
def test_hypothesis_random_rotations_orthogonal_float32(q):
    R = jnp.asarray(Rotation.from_quat(np.asarray(q)).as_matrix().astype(np.float32))
    D = rotation_matrix(R, 4)
    np.testing.assert_allclose(D @ D.T, np.eye(16), atol=eps(jnp.float32, 10))
    c = jnp.arange(16, dtype=jnp.float32) / 16
    np.testing.assert_allclose(rotate(c, R), D @ c, atol=eps(jnp.float32, 10))


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_batch_shapes(shape):
    R = jnp.asarray(_random_rot(11, shape).astype(np.float32))
    c = jnp.asarray(np.random.default_rng(0).normal(size=(*shape, 16)).astype(np.float32))
    D = rotation_matrix(R, 4)
    assert D.shape == (*shape, 16, 16) and D.dtype == jnp.float32
    out = rotate(c, R)
    assert out.shape == (*shape, 16)
    tol = eps(jnp.float32, 10)
    np.testing.assert_allclose(out, jnp.einsum("...ij,...j->...i", D, c), atol=tol)
    # a single coefficient vector broadcasts against a batch of rotations
    assert rotate(c.reshape(-1, 16)[0], R).shape == (*shape, 16)


def _loss(axis, theta):
    R = _rot_jax(axis, theta)
    c = jnp.linspace(-1.0, 1.0, 25, dtype=R.dtype)
    return jnp.sum(rotate(c, R) ** 3) + jnp.sum(rotation_matrix(R, 5) ** 3)


# one compilation for every parametrisation below (axis and angle are traced arguments)
_grad_loss = jax.jit(jax.grad(_loss, argnums=1))
_jac_rotmat = jax.jit(jax.jacrev(lambda R: rotation_matrix(R, 5)))


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("axis", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, -1.0]])
@pytest.mark.parametrize("angle", [0.0, np.pi / 2, np.pi])
def test_gradients_finite_at_axes_and_identity(axis, angle):
    g = _grad_loss(jnp.asarray(axis), jnp.asarray(angle))
    assert np.isfinite(g)
    jr = _jac_rotmat(jnp.asarray(_axis_rot(axis, angle)))
    assert jr.shape == (25, 25, 3, 3) and np.all(np.isfinite(jr))


def _frame_from_dir(d):
    """Spherical frame [e_θ | −e_φ | −u] of a unit direction u = d (world = frame @ local)."""
    theta, phi = safe_acos(d[2]), safe_atan2(d[1], d[0])
    st, ct, sp, cp = jnp.sin(theta), jnp.cos(theta), jnp.sin(phi), jnp.cos(phi)
    x = jnp.stack([ct * cp, ct * sp, -st])
    y = jnp.stack([sp, -cp, jnp.zeros_like(sp)])
    return jnp.stack([x, y, -jnp.stack([st * cp, st * sp, ct])], axis=-1)


_jac_frame_rotate = jax.jit(jax.jacrev(lambda d, c: rotate(c, _frame_from_dir(d))))


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("d", [[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, -1.0, 0]])
def test_gradient_finite_for_frames_built_at_poles(d):
    d = jnp.asarray(d)
    c = jnp.linspace(0.5, 2.0, 16)
    R = _frame_from_dir(d)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    jac = _jac_frame_rotate(d, c)
    assert jac.shape == (16, 3) and np.all(np.isfinite(jac))


def _rot_jax(axis, theta):
    """Rodrigues' formula (differentiable in theta)."""
    k = jnp.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return jnp.eye(3) + jnp.sin(theta) * k + (1 - jnp.cos(theta)) * (k @ k)


@pytest.mark.usefixtures("x64")
def test_gradient_three_ways():
    axis = jnp.asarray([0.48, -0.6, 0.64])
    c = jnp.asarray(np.random.default_rng(5).normal(size=16))

    def f(theta):
        return rotate(c, _rot_jax(axis, theta))

    t0 = jnp.asarray(0.7)
    jf, jr = jax.jacfwd(f)(t0), jax.jacrev(f)(t0)
    h = 1e-6
    fd = (f(t0 + h) - f(t0 - h)) / (2 * h)
    np.testing.assert_allclose(jf, jr, atol=1e-12)
    np.testing.assert_allclose(jf, fd, atol=1e-8)
    # d/dθ D(R(θ)) at θ = 0 is the band-wise generator: antisymmetric
    gen = jax.jacfwd(lambda t: rotation_matrix(_rot_jax(axis, t), 4))(jnp.asarray(0.0))
    np.testing.assert_allclose(gen, -gen.T, atol=1e-12)


def test_bad_input():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        rotation_matrix(jnp.eye(2), 3)
    with pytest.raises(ValueError, match="positive integer"):
        rotation_matrix(jnp.eye(3), 0)
    with pytest.raises(ValueError, match="floating"):
        rotate(jnp.ones(4), jnp.eye(3, dtype=jnp.int32))
    with pytest.raises(ValueError, match="square"):
        rotate(jnp.ones(5), jnp.eye(3))


# ---- rotate_zyz (Euler angles) ----------------------------------------------------------------------


def _zyz(a, b, g):
    z, y = Rotation.from_euler("z", a), Rotation.from_euler("y", b)
    return (z * y * Rotation.from_euler("z", g)).as_matrix()


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("n", [1, 2, 4, 5, 8])
def test_rotate_zyz_equals_rotate_of_the_euler_matrix(n):
    rng = np.random.default_rng(10 + n)
    c = rng.normal(size=(6, n * n))
    a, b, g = rng.uniform(-4, 4, (3, 6))
    b[:2] = [0.0, np.pi]  # the gimbal-lock angles
    want = rotate(jnp.asarray(c), jnp.asarray(np.stack([_zyz(*x) for x in zip(a, b, g, strict=True)])))
    np.testing.assert_allclose(rotate_zyz(jnp.asarray(c), a, b, g), want, atol=1e-12)
    mats0 = np.stack([_zyz(x, y, 0.0) for x, y in zip(a, b, strict=True)])
    want0 = rotate(jnp.asarray(c), jnp.asarray(mats0))
    np.testing.assert_allclose(rotate_zyz(jnp.asarray(c), a, b), want0, atol=1e-12)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_rotate_zyz_batch_shapes(shape):
    rng = np.random.default_rng(3)
    c = jnp.asarray(rng.normal(size=(*shape, 16)), jnp.float32)
    a, b = (jnp.asarray(rng.uniform(-3, 3, shape), jnp.float32) for _ in range(2))
    out = rotate_zyz(c, a, b)
    assert out.shape == (*shape, 16) and out.dtype == jnp.float32
    mats = np.asarray([_zyz(x, y, 0.0) for x, y in zip(np.ravel(a), np.ravel(b), strict=True)])
    want = rotate(c, jnp.asarray(mats.reshape(*shape, 3, 3), jnp.float32))
    np.testing.assert_allclose(out, want, atol=2e-5)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("beta", [0.0, np.pi / 2, np.pi])
def test_rotate_zyz_gradients_match_rotate(beta):
    # derivatives in the angles and coefficients agree with those through the rotation matrix,
    # including at the gimbal-lock angles (finite there: the map is smooth in the angles)
    c = jnp.asarray(np.random.default_rng(4).normal(size=25))
    w = jnp.arange(25.0)

    def via_zyz(c, a, b):
        return jnp.sum(w * rotate_zyz(c, a, b) ** 2)

    def via_matrix(c, a, b):
        ca, sa, cb, sb = jnp.cos(a), jnp.sin(a), jnp.cos(b), jnp.sin(b)
        rz = jnp.asarray([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]])
        ry = jnp.asarray([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
        return jnp.sum(w * rotate(c, rz @ ry) ** 2)

    args = (c, jnp.float64(0.3), jnp.float64(beta))
    g1 = jax.grad(via_zyz, argnums=(0, 1, 2))(*args)
    g2 = jax.grad(via_matrix, argnums=(0, 1, 2))(*args)
    for x, y in zip(g1, g2, strict=True):
        assert np.all(np.isfinite(x))
        np.testing.assert_allclose(x, y, atol=1e-10)


def test_bsv_frame_rotation_by_euler_angles_equals_fitting():
    # the field applies D(bsv_frames(θ, φ)) by Euler angles (frame_to_world); poles and equator included
    from jshadow.field import frame_to_world, frame_to_world_cs
    from jshadow.visibility import bsv_frames

    rng = np.random.default_rng(5)
    for n in (4, 5, 8):
        c = jnp.asarray(rng.normal(size=(200, n * n)), jnp.float32)
        th = jnp.asarray(np.r_[0.0, np.pi, np.pi / 2, rng.uniform(0, np.pi, 197)], jnp.float32)
        ph = jnp.asarray(rng.uniform(-np.pi, np.pi, 200), jnp.float32)
        want = rotate(c, bsv_frames(th, ph)[1])
        np.testing.assert_allclose(frame_to_world(c, th, ph), want, atol=1e-5)
        # from cosines and sines, as the field calls it
        cs = (jnp.cos(th), jnp.sin(th), jnp.cos(ph), jnp.sin(ph))
        np.testing.assert_allclose(frame_to_world_cs(c, *cs), want, atol=1e-5)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2)])
def test_rotate_zyz_cs_equals_rotate_zyz(shape):
    rng = np.random.default_rng(11)
    c = jnp.asarray(rng.normal(size=(*shape, 25)))
    a, b, g = (jnp.asarray(rng.uniform(-4, 4, shape)) for _ in range(3))
    pair = lambda x: (jnp.cos(x), jnp.sin(x))  # noqa: E731
    want = rotate_zyz(c, a, b, g)
    np.testing.assert_allclose(rotate_zyz_cs(c, pair(a), pair(b), pair(g)), want, atol=1e-13)
    np.testing.assert_allclose(rotate_zyz_cs(c, pair(a), pair(b)), rotate_zyz(c, a, b), atol=1e-13)


@pytest.mark.usefixtures("x64")
def test_rotate_zyz_cs_prepared_equals_unprepared():
    # coefficients multiplied by zyz_prepare_matrix once (the field folds it into its table) rotate
    # to the same result without that first product
    from jshadow.sh import zyz_prepare_matrix

    rng = np.random.default_rng(12)
    c = jnp.asarray(rng.normal(size=(5, 16)))
    a, b = (jnp.asarray(rng.uniform(-4, 4, 5)) for _ in range(2))
    pair = lambda x: (jnp.cos(x), jnp.sin(x))  # noqa: E731
    pre = c @ jnp.asarray(zyz_prepare_matrix(4))
    got = rotate_zyz_cs(pre, pair(a), pair(b), prepared=True)
    np.testing.assert_allclose(got, rotate_zyz(c, a, b), atol=1e-13)
    with pytest.raises(ValueError, match="without γ"):
        rotate_zyz_cs(pre, pair(a), pair(b), pair(a), prepared=True)
