"""Tests of jshadow.lights: lat-long reading, environment SH, sphere lights (analytic and SRF)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES

from jshadow import lights
from jshadow.entities import Environment
from jshadow.lights import environment_sh, read_latlong, sphere_light_dot, sphere_light_sh, sphere_light_srf
from jshadow.scaling import f_k, mk_table, mk_zonal_table
from jshadow.sh import clamped_cosine, sh_basis

ASSET = "/work/shared/assets/envmaps/studio_small_03_512x256.hdr"


# ---- reading -------------------------------------------------------------------------------------


def _write_rgbe(path, pixels, rle):
    """Write (H, W, 4) uint8 RGBE pixels as a Radiance file (flat or new-style RLE scanlines)."""
    h, w = pixels.shape[:2]
    out = bytearray(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {h} +X {w}\n".encode())
    for row in pixels:
        if not rle:
            out += row.tobytes()
            continue
        out += bytes([2, 2, w >> 8, w & 255])
        for ch in range(4):
            vals = row[:, ch]
            out += bytes([128 + 3, vals[0]])  # a run of 3 ...
            out += bytes([w - 3, *vals[3:]])  # ... then literals
    path.write_bytes(bytes(out))


@pytest.mark.parametrize("rle", [False, True])
def test_read_rgbe_roundtrip(tmp_path, rle):
    rng = np.random.default_rng(1)
    h, w = 4, 8
    px = rng.integers(128, 256, size=(h, w, 4), dtype=np.uint8)
    px[..., 3] = rng.integers(120, 140, size=(h, w))
    if rle:
        px[:, 1:3] = px[:, :1]  # the first 3 pixels of each row are a run
    px[0, 5, 3] = 0  # e = 0 encodes black
    p = tmp_path / "x.hdr"
    _write_rgbe(p, px, rle)
    img = read_latlong(p)
    ref = (px[..., :3] + 0.5) * np.ldexp(1.0, px[..., 3].astype(int) - 136)[..., None]
    ref[0, 5] = 0.0
    assert img.dtype == np.float32 and img.shape == (h, w, 3)
    np.testing.assert_allclose(img, ref, rtol=1e-6)


def test_read_shared_asset():
    img = read_latlong(ASSET)
    assert img.shape == (256, 512, 3) and img.dtype == np.float32
    assert np.all(np.isfinite(img)) and img.min() >= 0 and img.max() > 10


def test_read_errors(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="nope.hdr.*not found"):
        read_latlong(tmp_path / "nope.hdr")
    bad = tmp_path / "bad.hdr"
    bad.write_bytes(b"hello")
    with pytest.raises(ValueError, match="bad.hdr.*cannot read"):
        read_latlong(bad)
    square = tmp_path / "square.hdr"
    _write_rgbe(square, np.full((8, 8, 4), 128, np.uint8), rle=False)
    with pytest.raises(ValueError, match=r"square.hdr.*\(H, 2H, 3\)"):
        read_latlong(square)
    ok = tmp_path / "ok.hdr"
    _write_rgbe(ok, np.full((2, 4, 4), 128, np.uint8), rle=False)
    monkeypatch.setattr(lights, "_read_rgbe", lambda p: np.full((2, 4, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="ok.hdr.*non-finite"):
        read_latlong(ok)


# ---- environment ---------------------------------------------------------------------------------


def test_constant_environment_is_exact_and_gives_pi_l(rng):
    env = Environment(radiance=jnp.asarray([1.0, 2.0, 0.5], jnp.float32))
    c = environment_sh(env, 4)
    assert c.shape == (16, 3) and c.dtype == jnp.float32
    ref = np.zeros((16, 3), np.float32)
    ref[0] = math.sqrt(4 * math.pi) * np.array([1.0, 2.0, 0.5])
    np.testing.assert_allclose(c, ref, rtol=1e-7)
    normals = jnp.asarray(rng.normal(size=(5, 3)), jnp.float32)
    normals = normals / jnp.linalg.norm(normals, axis=-1, keepdims=True)
    e = clamped_cosine(normals, 4) @ c  # irradiance ∫ L max(0, n·ω) dω
    np.testing.assert_allclose(e, math.pi * np.tile([1.0, 2.0, 0.5], (5, 1)), rtol=1e-5)


def _brute_env(env, n, sub, rotation_y=0.0):
    """∫ radiance_at(ω) Y(R_y ω) dω over sub×sub cells per pixel, exact cell solid angles (float64)."""
    h, w = env.image.shape[:2]
    th_e = np.linspace(0, math.pi, h * sub + 1)
    ph_e = np.linspace(0, 2 * math.pi, w * sub + 1)
    th, ph = 0.5 * (th_e[1:] + th_e[:-1]), 0.5 * (ph_e[1:] + ph_e[:-1])
    dcos = np.cos(th_e[:-1]) - np.cos(th_e[1:])
    T, P = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.cos(T), -np.sin(T) * np.sin(P)], -1)
    L = np.asarray(env.radiance_at(jnp.asarray(d)))
    c, s = math.cos(rotation_y), math.sin(rotation_y)
    rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    y = np.asarray(sh_basis(jnp.asarray(d @ rot.T), n))
    wgt = dcos[:, None] * (2 * math.pi / (w * sub))
    return np.einsum("tp,tpi,tpc->ic", np.broadcast_to(wgt, T.shape), y, L)


@pytest.mark.usefixtures("x64")
def test_hdr_projection_matches_brute_force_quadrature(rng):
    img = jnp.asarray(rng.uniform(0, 3, size=(8, 16, 3)))
    env = Environment(radiance=jnp.asarray([1.0, 0.5, 2.0]), image=img, kind="hdr")
    ref = _brute_env(env, 4, 24)
    got = environment_sh(env, 4, samples_per_pixel=3)
    np.testing.assert_allclose(got, ref, atol=2e-3 * np.abs(ref).max())
    assert (
        np.abs(np.asarray(environment_sh(env, 4, samples_per_pixel=1)) - ref).max() < 0.05 * np.abs(ref).max()
    )
    # rotation about +y by a whole number of pixels = the image rolled by that many columns
    shift = 3
    rot = environment_sh(env, 4, samples_per_pixel=3, rotation_y=2 * math.pi * shift / 16)
    rolled = Environment(radiance=env.radiance, image=jnp.roll(img, shift, axis=1), kind="hdr")
    np.testing.assert_allclose(rot, environment_sh(rolled, 4, samples_per_pixel=3), atol=1e-5)
    np.testing.assert_allclose(
        rot, _brute_env(env, 4, 24, 2 * math.pi * shift / 16), atol=2e-3 * np.abs(ref).max()
    )


@pytest.mark.usefixtures("x64")
def test_hdr_projection_is_differentiable_in_image_and_radiance(rng):
    img = jnp.asarray(rng.uniform(0, 1, size=(4, 8, 3)))

    def fn(scale, im):
        return environment_sh(Environment(radiance=scale, image=im, kind="hdr"), 3).sum()

    g_s, g_i = jax.grad(fn, argnums=(0, 1))(jnp.ones(3), img)
    assert bool(jnp.all(jnp.isfinite(g_i))) and float(jnp.abs(g_i).sum()) > 0
    np.testing.assert_allclose(
        g_s, environment_sh(Environment(jnp.ones(3), img, "hdr"), 3).sum(0), rtol=1e-12
    )


@pytest.mark.usefixtures("x64")
def test_sky_projection_matches_brute_force():
    env = Environment(radiance=jnp.asarray([1.0, 0.8, 0.6]), kind="sky")
    got = environment_sh(env, 4)
    # sky (1 + 2 cos θ)/3 above the horizon: zonal about +y, brute force in (cos θ_y) by GL
    x, w = np.polynomial.legendre.leggauss(64)
    y, wy = 0.5 * (x + 1), 0.5 * w
    ph = (np.arange(64) + 0.5) * 2 * math.pi / 64
    Y, P = np.meshgrid(y, ph, indexing="ij")
    s = np.sqrt(1 - Y**2)
    d = np.stack([s * np.cos(P), Y, s * np.sin(P)], -1)
    basis = np.asarray(sh_basis(jnp.asarray(d), 4))
    ref = np.einsum("tp,tpi->i", ((1 + 2 * Y) / 3) * wy[:, None] * (2 * math.pi / 64), basis)
    np.testing.assert_allclose(got, ref[:, None] * np.array([1.0, 0.8, 0.6]), atol=1e-12)
    assert float(got[0, 0]) == pytest.approx(2 * math.sqrt(math.pi) / 3, abs=1e-12)


def test_environment_sh_inside_jit(rng):
    img = jnp.asarray(rng.uniform(0, 1, size=(6, 12, 3)), jnp.float32)
    ones = jnp.ones(3, jnp.float32)
    for env in [Environment(ones, img, "hdr"), Environment(ones, None, "sky")]:
        jitted = jax.jit(lambda e: environment_sh(e, 3, rotation_y=0.3))(env)
        np.testing.assert_allclose(jitted, environment_sh(env, 3, rotation_y=0.3), rtol=1e-5, atol=1e-6)


def test_environment_validation():
    with pytest.raises(ValueError, match="samples_per_pixel"):
        environment_sh(Environment(jnp.ones(3), jnp.ones((2, 4, 3)), "hdr"), 4, samples_per_pixel=0)
    with pytest.raises(ValueError, match="unknown environment kind"):
        environment_sh(Environment(jnp.ones(3), None, "sun"), 4)
    with pytest.raises(ValueError, match="bands"):
        environment_sh(Environment(jnp.ones(3)), 0)


# ---- sphere lights -------------------------------------------------------------------------------


def _frame(axis):
    """Rotation whose third column is ``axis``."""
    a = np.asarray(axis, float)
    t = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(a, t)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(a, u), a], axis=1)


def _brute_cap(axis, alpha, n):
    """∫_cap Y dω with GL in θ on [0, α] (exact edge) × uniform φ, in a frame around axis."""
    x, w = np.polynomial.legendre.leggauss(48)
    th, wt = 0.5 * alpha * (x + 1), 0.5 * alpha * w
    ph = (np.arange(32) + 0.5) * 2 * math.pi / 32
    T, P = np.meshgrid(th, ph, indexing="ij")
    local = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)
    y = np.asarray(sh_basis(jnp.asarray(local @ _frame(axis).T), n))
    return np.einsum("tp,tpi->i", (wt * np.sin(th))[:, None] * (2 * math.pi / 32), y)


@pytest.mark.usefixtures("x64")
def test_sphere_light_is_the_analytic_cap(rng):
    center, radius = jnp.asarray([0.3, 2.0, -0.4]), jnp.asarray(0.5)
    pts = jnp.asarray(rng.normal(size=(3, 3)))
    got = sphere_light_sh(center, radius, jnp.asarray([1.0, 2.0, 3.0]), pts, 4)
    assert got.shape == (3, 16, 3)
    for p, g in zip(np.asarray(pts), np.asarray(got)):
        rel = np.asarray(center) - p
        dist = np.linalg.norm(rel)
        ref = _brute_cap(rel / dist, math.asin(0.5 / dist), 4)
        np.testing.assert_allclose(g, ref[:, None] * np.array([1.0, 2.0, 3.0]), atol=1e-12)
    # inside the light: radiance from everywhere
    inside = sphere_light_sh(center, radius, jnp.ones(3), center + 0.1, 4)
    np.testing.assert_allclose(inside[:, 0], np.eye(16)[0] * math.sqrt(4 * math.pi), atol=1e-14)


def test_small_light_is_accurate_in_float32():
    # d = 1000 r: 1 − cos α = 5e-7 would be lost in float32 if computed as 1 − cos α
    c = sphere_light_sh(
        jnp.asarray([0, 0, 1000.0], jnp.float32),
        jnp.float32(1.0),
        jnp.ones(3, jnp.float32),
        jnp.zeros(3, jnp.float32),
        2,
    )
    t = 1 - math.sqrt(1 - 1e-6)
    assert float(c[0, 0]) == pytest.approx(2 * math.pi * t / math.sqrt(4 * math.pi), rel=1e-5)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_sphere_light_batch_shapes(shape, rng):
    pts = jnp.asarray(rng.normal(size=(*shape, 3)), jnp.float32)
    out = sphere_light_sh(
        jnp.asarray([0.0, 3.0, 0.0], jnp.float32), jnp.float32(0.5), jnp.ones(3, jnp.float32), pts, 4
    )
    assert out.shape == (*shape, 16, 3) and out.dtype == jnp.float32


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_sphere_light_dot_is_the_inner_product_with_its_sh(x64, shape, rng):
    # receivers outside, on the surface of and inside the light; w one shared row and per receiver
    center, radius = jnp.asarray([0.2, 2.0, -0.1]), jnp.asarray(0.6)
    pts = center + jnp.asarray(rng.normal(size=(*shape, 3))) * jnp.asarray(
        rng.uniform(0.1, 3.0, size=(*shape, 1))
    )
    pts = pts.reshape(-1, 3).at[0].set(center + jnp.asarray([0.0, -0.6, 0.0])).reshape(pts.shape)
    cap = sphere_light_sh(center, radius, jnp.ones(1), pts, 4)[..., 0]
    for w in (jnp.asarray(rng.normal(size=16)), jnp.asarray(rng.normal(size=(*shape, 16)))):
        got = sphere_light_dot(center, radius, pts, w, 4)
        assert got.shape == shape
        np.testing.assert_allclose(got, jnp.sum(cap * w, -1), rtol=1e-12, atol=1e-12)

    def both(p, pts):  # gradients: light position/radius and receivers, generic and at d = r
        dot = sphere_light_dot(p[:3], p[3], pts, w, 4).sum()
        ref = jnp.sum(sphere_light_sh(p[:3], p[3], jnp.ones(1), pts, 4)[..., 0] * w)
        return dot, ref

    p = jnp.concatenate([center, radius[None]])
    for arg in (0, 1):
        g = jax.jit(jax.jacrev(both, argnums=arg))(p, pts)
        assert np.all(np.isfinite(g[0]))
        np.testing.assert_allclose(g[0], g[1], rtol=1e-10, atol=1e-10)


@pytest.mark.usefixtures("x64")
def test_sphere_light_gradients():
    @jax.jit
    def fn_w(p, pts):  # a weighted sum, so that no coefficient's gradient cancels
        c = sphere_light_sh(p[:3], p[3], jnp.ones(3), pts, 4)[..., 0]
        return jnp.sum(c * jnp.arange(1.0, 17.0), axis=-1)

    p = jnp.asarray([0.2, 2.0, -0.1, 0.4])
    # receivers: generic, at the centre, on the surface, generic
    pts = jnp.asarray([[0.0, 0.0, 0.0], [0.2, 2.0, -0.1], [0.2, 1.6, -0.1], [0.5, 1.0, 0.3]])
    jf = np.asarray(jax.jacfwd(fn_w)(p, pts))
    jr = np.asarray(jax.jacrev(fn_w)(p, pts))
    jp = np.asarray(jax.jacrev(fn_w, argnums=1)(p, pts))
    assert np.all(np.isfinite(jf)) and np.all(np.isfinite(jp))
    np.testing.assert_allclose(jf, jr, atol=1e-10)
    h = 1e-6
    fd = np.stack([(fn_w(p.at[i].add(h), pts) - fn_w(p.at[i].add(-h), pts)) / (2 * h) for i in range(4)], 1)
    np.testing.assert_allclose(jf[[0, 3]], fd[[0, 3]], rtol=1e-6, atol=1e-6)  # generic receivers
    assert np.abs(jf[0]).sum() > 0 and np.abs(jp[0]).sum() > 0


# ---- the SRF path --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def srf_tables():
    with jax.enable_x64(True):
        kw = dict(n=4, num=16, d_min=0.2, d_max=16.0, dtype=jnp.float64)
        return {
            "plain": mk_table(kind="radiance", **kw),
            "jacobian": mk_table(kind="radiance_jacobian", **kw),
            "plain_sphere": mk_table(kind="radiance", model="sphere", **kw),
        }


def _on_axis_irradiance(l_sh, normal):
    return float((clamped_cosine(normal, 4) @ l_sh)[0])


def _jacobian_untruncated(k):
    """On-axis irradiance of the Jacobian-warped hemisphere without SH truncation (GL quadrature).

    Substituting u = f_{1/k}(θ): E = 2π ∫_0^{π/2} cos(f_k(u)) sin u du.
    """
    x, w = np.polynomial.legendre.leggauss(200)
    u, wu = 0.25 * math.pi * (x + 1), 0.25 * math.pi * w
    return 2 * math.pi * float(np.sum(wu * np.cos(np.asarray(f_k(jnp.asarray(u), k))) * np.sin(u)))


@pytest.mark.usefixtures("x64")
def test_srf_variants_against_the_analytic_cap(srf_tables):
    # receiver facing a unit-radiance light of radius 1 at distance d (k = 1/d), 4 bands
    normal = jnp.asarray([0.0, 0.0, 1.0])
    rows = {}
    for d in [1.5, 2.0, 4.0, 10.0]:
        k = 1.0 / d
        c, pt = jnp.asarray([0.0, 0.0, d]), jnp.zeros(3)
        vals = {
            name: _on_axis_irradiance(sphere_light_srf(c, 1.0, jnp.ones(3), pt, 4, t), normal)
            for name, t in srf_tables.items()
        }
        rows[d] = dict(
            exact=math.pi * k * k,  # π sin²α
            analytic_sh=_on_axis_irradiance(sphere_light_sh(c, 1.0, jnp.ones(3), pt, 4), normal),
            plain_untruncated=math.pi * k * k / (k * k + (1 - k) ** 2),  # π sin² f_k(π/2)
            jacobian_untruncated=_jacobian_untruncated(k),
            **vals,
        )
    print("\non-axis irradiance, unit-radiance light of radius 1 at distance d (4 SH bands):")
    for d, r in rows.items():
        print(f"  d={d:5}: " + ", ".join(f"{key}={v:.4f}" for key, v in r.items()))
    r10 = rows[10.0]
    # DESIGN.md §1.3: at k = 0.1 the true value is 0.031 and the Jacobian variant gives 6.27. Reproduced
    # without truncation; through 4-band SH the Jacobian variant gives about 6.7 (≈ 2π · 1.06, the
    # 4-band clamped cosine's overshoot at its pole).
    assert r10["exact"] == pytest.approx(0.0314, abs=1e-4)
    assert r10["jacobian_untruncated"] == pytest.approx(6.27, abs=0.01)
    assert 6.27 < r10["jacobian"] < 6.8
    # the Jacobian variant does not dim with distance
    assert rows[4.0]["jacobian"] / rows[10.0]["jacobian"] < 1.2
    assert rows[1.5]["jacobian_untruncated"] / rows[10.0]["jacobian_untruncated"] > 0.7
    for d, r in rows.items():
        assert r["analytic_sh"] == pytest.approx(r["exact"], rel=0.07), d  # truncation of the cosine only
    # the plain warp dims, but warping the truncated hemisphere spreads its ringing over the sphere:
    # at d = 10 it is off by more than the whole signal (here even negative)
    assert rows[1.5]["plain"] / rows[4.0]["plain"] > 4.0
    assert abs(r10["plain"] - r10["exact"]) > 5 * r10["exact"]


def test_zonal_srf_matches_the_closed_form_cap_within_one_percent(rng):
    # issue 9's sphere light through the field path: the radiance sampled on a shell of 1.5 light
    # radii (a cap of 41.8°), extrapolated with the concentric-sphere model in 48 zonal bands and
    # truncated to 4 afterwards, against the exact 4-band cap of sphere_light_sh. The same path with
    # a full 5-band table is off by far more (BENCHMARKS.md "Accuracy beyond the paper")
    table = mk_zonal_table(48)
    five = mk_table(n=5, num=32, d_min=0.2, d_max=16.0, kind="radiance", model="sphere")
    dirs = rng.normal(size=(9, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    errs, errs5 = [], []
    for d, u in zip([1.2, 1.6, 2.0, 3.0, 4.0, 6.0, 10.0, 16.0, 24.0], dirs, strict=True):
        pts = jnp.asarray([[0.3, -0.2, 0.1]])
        centre = pts[0] + d * 0.7 * jnp.asarray(u)  # light of radius 0.7
        radiance = jnp.asarray([1.0, 0.5, 2.0])
        want = np.asarray(sphere_light_sh(centre, 0.7, radiance, pts, 4))
        got = np.asarray(sphere_light_srf(centre, 0.7, radiance, pts, 4, table, 1.5))
        got5 = np.asarray(sphere_light_srf(centre, 0.7, radiance, pts, 4, five, 1.5))
        errs.append(np.abs(got - want).max() / np.abs(want).max())
        errs5.append(np.abs(got5 - want).max() / np.abs(want).max())
    print(
        "zonal SRF, max coefficient error / max coefficient:",
        np.round(errs, 5),
        "5-band:",
        np.round(errs5, 3),
    )
    assert max(errs) < 0.01, errs
    assert max(errs5) > 0.5  # 10 and more light radii away the 5-band table is off by the whole signal


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_zonal_srf_batches_and_has_finite_gradients_at_singular_points(shape, rng):
    # receivers outside, on the surface of, inside and at the centre of the light
    table = mk_zonal_table(16, num=16)
    center, radius = jnp.asarray([0.2, 2.0, -0.1], jnp.float32), jnp.float32(0.6)
    pts = center + jnp.asarray(rng.normal(size=(*shape, 3)), jnp.float32) * 2.0
    flat = pts.reshape(-1, 3).at[0].set(center + jnp.asarray([0.0, -0.6, 0.0])).reshape(pts.shape)
    out = sphere_light_srf(center, radius, jnp.ones(3, jnp.float32), flat, 4, table, 1.5)
    assert out.shape == (*shape, 16, 3) and out.dtype == jnp.float32
    singular = jnp.stack(
        [center, center + jnp.asarray([0.0, -0.6, 0.0]), center + jnp.asarray([0.0, 0.0, 0.3])]
    )

    def f(p, q):
        return jnp.sum(sphere_light_srf(p[:3], p[3], jnp.ones(1), q, 4, table, 1.5) ** 2)

    params = jnp.concatenate([center, radius[None]])
    for q in (flat, singular):
        g = jax.grad(f, argnums=(0, 1))(params, q)
        assert all(bool(jnp.all(jnp.isfinite(x))) for x in g)


def test_srf_validation(srf_tables):
    occ = mk_table(n=2, num=2)
    with pytest.raises(ValueError, match="radiance"):
        sphere_light_srf(jnp.zeros(3), 1.0, jnp.ones(3), jnp.ones(3), 2, occ)
