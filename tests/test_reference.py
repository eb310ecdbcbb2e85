"""The Monte Carlo reference against closed forms and an independent ray caster (Embree).

Per-receiver z-tests use a Šidák-corrected threshold (family-wise 1 %, never below 3 standard
errors); sample counts are chosen so that occlusion events are frequent enough for the normal
approximation of the binomial to hold.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh
from scipy import stats

from jshadow.entities import (
    Environment,
    MeshOccluder,
    Method,
    Receivers,
    Scene,
    SphereLight,
    SphereOccluder,
)
from jshadow.geometry import icosphere
from jshadow.reference import ReferenceResult, _occluded, _visible, reference


def z_threshold(m, family_alpha=0.01):
    per = 1.0 - (1.0 - family_alpha) ** (1.0 / m)
    return max(3.0, stats.norm.isf(per / 2))


def plane(n_side, half, dtype=np.float64, y=0.0):
    g = np.linspace(-half, half, n_side)
    x, z = np.meshgrid(g, g)
    pts = np.stack([x.ravel(), np.full(x.size, y), z.ravel()], -1).astype(dtype)
    nrm = np.tile(np.array([0.0, 1.0, 0.0], dtype), (len(pts), 1))
    return Receivers(
        jnp.asarray(pts), jnp.asarray(nrm), jnp.asarray([0.8, 0.6, 0.4], dtype), (n_side, n_side)
    )


def f64(**kw):
    return Scene(method=Method(dtype="float64"), **kw)


def sphere_mesh_occluder(center, radius, dtype):
    m = icosphere(2)
    return MeshOccluder(
        jnp.asarray(m.vertices, dtype),
        jnp.asarray(m.faces),
        jnp.asarray(center, dtype),
        jnp.asarray(radius, dtype),
    )


@pytest.mark.usefixtures("x64")
def test_unoccluded_sphere_light_exact():
    """Cap above the horizon: E = π L sin²α cos β at every receiver, with zero variance."""
    rec = plane(4, 1.5)
    c, r, rad = np.array([0.5, 3.0, -0.2]), 0.4, np.array([1.0, 2.0, 3.0])
    sc = f64(receivers=rec, lights=(SphereLight(jnp.asarray(c), jnp.asarray(r), jnp.asarray(rad)),))
    res = reference(sc, 64, jax.random.PRNGKey(0))
    assert isinstance(res, ReferenceResult)
    v = c - np.asarray(rec.points)
    d = np.linalg.norm(v, axis=-1)
    want = (np.pi * (r / d) ** 2 * v[:, 1] / d)[:, None] * rad
    np.testing.assert_allclose(np.asarray(res.irradiance), want, rtol=1e-12)
    assert np.max(np.asarray(res.irradiance_stderr)) <= 1e-12 * np.max(want)
    np.testing.assert_allclose(np.asarray(res.radiance), np.asarray(rec.albedo) / np.pi * want, rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(res.points), np.asarray(rec.points))
    for a in res:
        assert a.shape == (16, 3) and a.dtype == jnp.float64


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("stratify", [False, True])
def test_sphere_occluder_constant_environment(stratify):
    """E = π L (1 − sin²α cos β) under a constant environment, per receiver within the z bound;
    independent samples: the standard error is the binomial one; strata: smaller."""
    rec = plane(4, 1.0)
    c, r, env = np.array([0.2, 1.0, 0.1]), 0.5, np.array([1.0, 0.5, 2.0])
    sc = f64(
        receivers=rec,
        occluders=(SphereOccluder(jnp.asarray(c), jnp.asarray(r)),),
        environment=Environment(jnp.asarray(env)),
    )
    spp = 4096
    res = reference(sc, spp, jax.random.PRNGKey(1), stratify=stratify)
    v = c - np.asarray(rec.points)
    d = np.linalg.norm(v, axis=-1)
    want = (np.pi * (1 - (r / d) ** 2 * v[:, 1] / d))[:, None] * env
    got, se = np.asarray(res.irradiance), np.asarray(res.irradiance_stderr)
    assert np.all(se > 0)
    z = (got - want) / se
    assert np.max(np.abs(z[:, 0])) < z_threshold(len(z))
    # all channels see the same visibility: the estimate is the grey one times the colour
    np.testing.assert_allclose(got / env, np.repeat(got[:, :1] / env[0], 3, axis=1), rtol=1e-12)
    # the standard error is the binomial one: π L √(p(1 − p)/spp), p = occluded fraction of π
    p = (np.pi - want[:, 0]) / np.pi
    binomial = np.pi * np.sqrt(p * (1 - p) / spp)
    if stratify:  # strata reduce the error (estimated from 64 independent block means)
        assert np.mean(se[:, 0] / binomial) < 0.8
    else:
        np.testing.assert_allclose(se[:, 0], binomial, rtol=0.15)


@pytest.mark.usefixtures("x64")
def test_lights_do_not_occlude_and_far_occluders_do_not_shadow_lights():
    rec = plane(2, 0.5)
    light = SphereLight(jnp.asarray([0.0, 2.0, 0.0]), jnp.asarray(0.5), jnp.asarray([1.0, 1.0, 1.0]))
    dark = SphereLight(jnp.asarray([0.0, 1.0, 0.0]), jnp.asarray(0.3), jnp.asarray([0.0, 0.0, 0.0]))
    behind = SphereOccluder(jnp.asarray([0.0, 4.0, 0.0]), jnp.asarray(1.0))  # beyond the light
    sc = f64(receivers=rec, lights=(light, dark), occluders=(behind,), environment=Environment(jnp.ones(3)))
    res = reference(sc, 64, jax.random.PRNGKey(2))
    pts = np.asarray(rec.points)
    v = np.array([0.0, 2.0, 0.0]) - pts
    d = np.linalg.norm(v, axis=-1)
    e_light = np.pi * (0.5 / d) ** 2 * v[:, 1] / d
    # the environment is blocked by the far occluder only (the dark light does not occlude)
    vb = np.array([0.0, 4.0, 0.0]) - pts
    db = np.linalg.norm(vb, axis=-1)
    e_env = np.pi * (1 - (1.0 / db) ** 2 * vb[:, 1] / db)
    got, se = np.asarray(res.irradiance)[:, 0], np.asarray(res.irradiance_stderr)[:, 0]
    assert np.all(np.abs(got - e_light - e_env) < z_threshold(4) * se)


def embree_hits(vertices, faces, origins, dirs):
    sc = rtcs.EmbreeScene()
    TriangleMesh(sc, np.asarray(vertices, np.float32)[np.asarray(faces)])
    return sc.run(np.asarray(origins, np.float32), np.asarray(dirs, np.float32)) >= 0


def test_visibility_matches_embree(rng):
    """The reference's visibility (in-jit brute force, and the host path that culls by the
    bounding ball and compacts the candidate rays) against Embree on the same rays."""
    occ = sphere_mesh_occluder([0.1, 1.0, 0.0], 0.6, np.float32)
    v, f = occ.vertices(0.0), occ.faces
    o = np.tile(rng.uniform(-1.5, 1.5, size=(64, 1, 3)) * [1, 0, 1], (1, 64, 1)).astype(np.float32)
    target = np.array([0.1, 1.0, 0.0]) + 0.7 * rng.normal(size=(64, 64, 3)) / np.sqrt(3)  # near the rim
    d = target - o
    d[:, ::2] = rng.normal(size=(64, 32, 3))  # and rays in all directions
    d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)
    geo = _geo_with_mesh(v, f)
    theirs = embree_hits(v, f, o.reshape(-1, 3), d.reshape(-1, 3))
    assert 0.1 < theirs.mean() < 0.9  # a meaningful mix of hits and misses
    ours = np.asarray(_occluded(geo, jnp.asarray(o), jnp.asarray(d), jnp.inf)).ravel()
    assert np.mean(ours != theirs) <= 1e-3  # grazing rays may differ by float32 rounding
    tmax = np.full(d.shape[:-1], np.inf, np.float32)
    ones = np.ones(d.shape, np.float32)
    host = [(np.array([0.1, 1.0, 0.0]), 0.6)]
    culled = ~_visible(geo, host, o, d, tmax, np.zeros(tmax.shape, bool), ones)
    np.testing.assert_array_equal(culled.ravel(), ours)
    # a segment that ends before the mesh is never occluded
    short = ~_visible(
        geo, host, o, d, np.full(tmax.shape, 0.05, np.float32), np.zeros(tmax.shape, bool), ones
    )
    assert not np.any(short)


def _geo_with_mesh(v, f):
    from jshadow.reference import _Geometry

    z3, z = jnp.zeros((0, 3), jnp.float32), jnp.zeros((0,), jnp.float32)
    return _Geometry(z3, z, ((v, f),), z3, z, z3, None, None, jnp.asarray(1e-5, jnp.float32))


def test_mesh_occluder_matches_embree_estimate(rng):
    """A mesh occluder under a constant environment: the reference against an independent
    cosine-weighted estimate whose visibility comes from Embree."""
    rec = plane(3, 0.8, np.float32)
    occ = sphere_mesh_occluder([0.0, 0.9, 0.1], 0.5, np.float32)
    sc = Scene(method=Method(), receivers=rec, occluders=(occ,), environment=Environment(jnp.ones(3)))
    res = reference(sc, 2048, jax.random.PRNGKey(3))
    pts = np.asarray(rec.points, np.float64)
    m = 20000
    u = rng.random((len(pts), m, 2))
    rad, phi = np.sqrt(u[..., 0]), 2 * np.pi * u[..., 1]
    d = np.stack([rad * np.cos(phi), np.sqrt(1 - u[..., 0]), rad * np.sin(phi)], -1)  # normal +y
    o = np.broadcast_to(pts[:, None, :] + [0.0, 1e-4, 0.0], d.shape)
    hit = embree_hits(occ.vertices(0.0), occ.faces, o.reshape(-1, 3), d.reshape(-1, 3)).reshape(len(pts), m)
    e_embree = np.pi * (1 - hit.mean(1))
    se_embree = np.pi * hit.std(1) / np.sqrt(m)
    got, se = (
        np.asarray(res.irradiance, np.float64)[:, 0],
        np.asarray(res.irradiance_stderr, np.float64)[:, 0],
    )
    z = (got - e_embree) / np.sqrt(se**2 + se_embree**2)
    assert np.max(np.abs(z)) < z_threshold(len(z))
    assert np.all(got < np.pi * 0.99)  # every receiver is partly shadowed


def test_self_shadow_receivers_on_convex_mesh():
    """Vertices of a convex mesh see their whole normal hemisphere: E = π L exactly, which fails
    if ray origins are not offset off the surface."""
    rec = plane(2, 3.0, np.float32, y=-1.0)
    occ = sphere_mesh_occluder([0.0, 1.0, 0.0], 0.5, np.float32)
    sc = Scene(
        method=Method(),
        receivers=rec,
        occluders=(occ,),
        environment=Environment(jnp.asarray([1.0, 1.0, 1.0])),
        self_shadow=True,
    )
    res = reference(sc, 64, jax.random.PRNGKey(4))
    n_v = occ.unit_vertices.shape[0]
    assert res.irradiance.shape == (4 + n_v, 3)
    e_v = np.asarray(res.irradiance)[4:]
    np.testing.assert_allclose(e_v, np.pi, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(res.points)[4:], np.asarray(occ.vertices(0.0)), rtol=1e-6)


def test_determinism_and_chunk_independence():
    rec = plane(3, 1.0, np.float32)
    sc = Scene(
        method=Method(),
        receivers=rec,
        occluders=(SphereOccluder(jnp.asarray([0.0, 1.0, 0.0]), jnp.asarray(0.5)),),
        lights=(SphereLight(jnp.asarray([1.0, 0.4, 0.0]), jnp.asarray(0.5), jnp.asarray([2.0, 2.0, 2.0])),),
        environment=Environment(jnp.ones(3), kind="sky"),
    )
    a = reference(sc, 100, jax.random.PRNGKey(7))
    b = reference(sc, 100, jax.random.PRNGKey(7), chunk=4)
    c = reference(sc, 100, jax.random.PRNGKey(8))
    np.testing.assert_allclose(np.asarray(a.irradiance), np.asarray(b.irradiance), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(a.irradiance_stderr), np.asarray(b.irradiance_stderr), rtol=1e-5)
    assert not np.allclose(np.asarray(a.irradiance), np.asarray(c.irradiance))
    assert np.all(np.isfinite(np.asarray(a.irradiance))) and np.all(np.asarray(a.irradiance_stderr) > 0)


@pytest.mark.usefixtures("x64")
def test_sky_environment_closed_form():
    """Unoccluded overcast sky on an upward receiver: E = ∫ (1 + 2 cos θ)/3 cos θ dω = 7π/9."""
    sc = f64(receivers=plane(2, 1.0), environment=Environment(jnp.asarray([1.0, 1.0, 1.0]), kind="sky"))
    res = reference(sc, 4096, jax.random.PRNGKey(5))
    got, se = np.asarray(res.irradiance)[:, 0], np.asarray(res.irradiance_stderr)[:, 0]
    assert np.all(np.abs(got - 7 * np.pi / 9) < z_threshold(4) * se)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("heuristic", ["power", "balance"])
def test_hdr_environment_mis_closed_form(heuristic):
    """Lat-long map, unoccluded, receiver normal +y: E = Σ_ij L_ij ∫_pixel cos θ dω exactly."""
    rng = np.random.default_rng(0)
    h, w = 8, 16
    img = rng.random((h, w, 3)) ** 3
    img[1, 4] *= 40.0  # a small bright source
    mult = np.array([1.0, 2.0, 0.5])
    env = Environment(jnp.asarray(mult), jnp.asarray(img), kind="hdr")
    sc = f64(receivers=plane(2, 1.0), environment=env)
    res = reference(sc, 2048, jax.random.PRNGKey(6), heuristic=heuristic)
    th = np.pi * np.arange(h + 1) / h
    band = np.where(np.arange(h) < h // 2, 0.5 * (np.sin(th[1:]) ** 2 - np.sin(th[:-1]) ** 2), 0.0)
    want = np.einsum("ijc,i->c", img, band * 2 * np.pi / w) * mult
    got, se = np.asarray(res.irradiance), np.asarray(res.irradiance_stderr)
    assert np.all(np.abs(got - want) < z_threshold(12) * se)
    assert np.all(se < 0.05 * want)


def test_input_validation():
    sc = Scene(method=Method(), receivers=plane(2, 1.0, np.float32), environment=Environment(jnp.ones(3)))
    with pytest.raises(ValueError, match="spp"):
        reference(sc, 0, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="chunk"):
        reference(sc, 4, jax.random.PRNGKey(0), chunk=0)
    with pytest.raises(ValueError, match="heuristic"):
        reference(sc, 4, jax.random.PRNGKey(0), heuristic="max")
    with pytest.raises(ValueError, match="frame"):
        reference(sc, 4, jax.random.PRNGKey(0), frame=3)


@pytest.mark.usefixtures("x64")
def test_sphere_light_shadowed_by_sphere(rng):
    """Umbra: exactly zero light. Penumbra: against an independent numpy estimate (uniform cone
    sampling of the light, analytic ray–sphere test)."""
    lc, lr, oc, orad = np.array([0.0, 3.0, 0.0]), 0.5, np.array([0.0, 1.5, 0.0]), 0.4
    pts = np.array([[0.0, 0.0, 0.0], [0.35, 0.0, 0.0], [0.5, 0.0, 0.2], [0.75, 0.0, -0.1]])
    rec = Receivers(jnp.asarray(pts), jnp.asarray(np.tile([0.0, 1.0, 0.0], (4, 1))), jnp.ones(3), None)
    light = SphereLight(jnp.asarray(lc), jnp.asarray(lr), jnp.asarray([1.0, 1.0, 1.0]))
    sc = f64(receivers=rec, lights=(light,), occluders=(SphereOccluder(jnp.asarray(oc), jnp.asarray(orad)),))
    res = reference(sc, 4096, jax.random.PRNGKey(9))
    got, se = np.asarray(res.irradiance)[:, 0], np.asarray(res.irradiance_stderr)[:, 0]
    assert got[0] == 0.0 and se[0] == 0.0  # centre of the umbra
    m = 400_000
    want, want_se = [], []
    for p in pts:
        c = lc - p
        dist = np.linalg.norm(c)
        axis = c / dist
        omc = 1 - np.sqrt(1 - (lr / dist) ** 2)
        ct = 1 - rng.random(m) * omc
        st = np.sqrt(1 - ct * ct)
        ph = 2 * np.pi * rng.random(m)
        t1 = np.cross(axis, [1.0, 0.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(axis, t1)
        d = ct[:, None] * axis + (st * np.cos(ph))[:, None] * t1 + (st * np.sin(ph))[:, None] * t2
        b = d @ (oc - p)
        blocked = (b > 0) & (b * b - (np.sum((oc - p) ** 2) - orad**2) >= 0)
        f = np.where(blocked, 0.0, np.maximum(d[:, 1], 0.0)) * 2 * np.pi * omc
        want.append(f.mean())
        want_se.append(f.std() / np.sqrt(m))
    want, want_se = np.array(want), np.array(want_se)
    assert np.all(want[1:] > 0.002) and np.all(want[1:] < 0.9 * np.pi * (lr / 3.0) ** 2)  # penumbrae
    z = (got - want) / np.sqrt(se**2 + want_se**2 + 1e-300)
    assert np.max(np.abs(z[1:])) < z_threshold(3)
