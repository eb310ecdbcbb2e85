"""Work skipped where a scene does not need it: rows evaluated only where active, and the cone test
that decides which receivers a sphere light's lookups can skip.

Claims tested: ``over_active`` equals ``where(active, fn(rows), fill)`` for any mask (none, all,
random), any chunk count (including ones that do not divide the rows) and a trailing output shape,
its values and derivatives (grad and jvp) are those of the full evaluation, and it runs ``fn`` on
the chunks holding active rows only; ``cone_may_meet_sphere`` is conservative against rays cast
densely over the light's cap (never False where a ray meets the sphere before the light), True
inside either sphere, and skips most receivers far from the shadow; ``light_visible_fractions``
and ``environment_visible_fraction`` (with own vertices' exact rays) give the same values and
derivatives with and without the skipping, on planes large enough for several chunks;
``fan_may_meet_sphere`` is conservative against the fan's directions.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_light_images import IMAGES, LIGHT, _icosphere_world, _light_scene

from jshadow._active import chunk_count, over_active
from jshadow.entities import SphereLight, receivers_at_time
from jshadow.geometry import cone_may_meet_sphere, fan_may_meet_sphere
from jshadow.sampling import stratified_sphere_cone
from jshadow.scene import (
    environment_visible_fraction,
    light_visible_fractions,
    occluder_images,
    own_rows_at_time,
    scene_images,
    scene_lighting,
)


def _fn(x, y):
    return jnp.stack([jnp.sin(x[:, 0]) * y, x[:, 1] ** 2 + y], -1)  # (M, 2) from (M, 2), (M,)


@pytest.mark.parametrize("chunks", [1, 3, 7, 16])
@pytest.mark.parametrize("kind", ["none", "all", "random"])
def test_over_active_equals_the_masked_full_evaluation(chunks, kind, rng):
    n = 50
    x = jnp.asarray(rng.normal(size=(n, 2)))
    y = jnp.asarray(rng.normal(size=n))
    active = {"none": np.zeros(n, bool), "all": np.ones(n, bool), "random": rng.uniform(size=n) < 0.3}[kind]
    active = jnp.asarray(active)
    got = over_active(_fn, active, (x, y), -2.0, chunks=chunks)
    want = jnp.where(active[:, None], _fn(x, y), -2.0)
    assert got.shape == (n, 2) and got.dtype == want.dtype
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-12, atol=0)
    jitted = jax.jit(lambda a, x, y: over_active(_fn, a, (x, y), -2.0, chunks=chunks))
    np.testing.assert_allclose(np.asarray(jitted(active, x, y)), np.asarray(want), rtol=1e-12, atol=0)


def test_over_active_derivatives_are_the_full_evaluations(rng):
    n = 40
    x = jnp.asarray(rng.normal(size=(n, 2)))
    y = jnp.asarray(rng.normal(size=n))
    active = jnp.asarray(rng.uniform(size=n) < 0.4)
    w = jnp.asarray(rng.normal(size=(n, 2)))

    def ours(x, y):
        return jnp.sum(w * over_active(_fn, active, (x, y), 1.0, chunks=4))

    def full(x, y):
        return jnp.sum(w * jnp.where(active[:, None], _fn(x, y), 1.0))

    for a, b in zip(jax.grad(ours, (0, 1))(x, y), jax.grad(full, (0, 1))(x, y), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)
    dx, dy = jnp.asarray(rng.normal(size=(n, 2))), jnp.asarray(rng.normal(size=n))
    _, t_ours = jax.jvp(ours, (x, y), (dx, dy))
    _, t_full = jax.jvp(full, (x, y), (dx, dy))
    np.testing.assert_allclose(float(t_ours), float(t_full), rtol=1e-5)


def test_over_active_runs_only_the_chunks_it_needs(rng):
    """A function that marks the rows it saw: with 5 active rows among 100 in 10 chunks, one chunk
    of 10 rows runs (the active rows are compacted to the front)."""
    n = 100
    seen = []

    @jax.jit
    def run(active, scale):
        def fn(i):  # closes over a traced array, as the renderer's lookups close over the images
            jax.debug.callback(lambda v: seen.append(np.asarray(v)), i)
            return scale * i.astype(jnp.float32)

        return over_active(fn, active, (jnp.arange(n),), 1.0, chunks=10)

    active = np.zeros(n, bool)
    active[rng.choice(n, 5, replace=False)] = True
    out = run(jnp.asarray(active), jnp.float32(2.0))
    jax.effects_barrier()
    assert len(seen) == 1 and seen[0].shape == (10,)
    assert set(np.flatnonzero(active)) <= set(seen[0].tolist())
    np.testing.assert_array_equal(np.asarray(out), np.where(active, 2.0 * np.arange(n), 1.0))


def test_over_active_checks_its_rows():
    with pytest.raises(ValueError, match="leading size"):
        over_active(_fn, jnp.ones(4, bool), (jnp.ones((4, 2)), jnp.ones(5)), 0.0)
    with pytest.raises(ValueError, match="chunk_count"):
        chunk_count(10, chunks=0)
    assert chunk_count(16384) == 16 and chunk_count(100) == 1 and chunk_count(2048) == 4


def test_cone_test_is_conservative_against_dense_rays(rng):
    n = 3000
    pts = rng.uniform(-4, 4, size=(n, 3))
    lc, lr = np.array([0.5, 3.0, -0.4]), 0.6
    c, r = np.array([0.2, 1.2, 0.3]), 0.5
    mask = np.asarray(cone_may_meet_sphere(pts, lc, lr, c, r))
    # rays over the light's cap, densely (the cap's directions as the renderer samples them, finer)
    d = np.asarray(stratified_sphere_cone(jnp.asarray(lc - pts), jnp.asarray(np.full(n, lr)), (24, 48)))
    rel = pts[:, None, :] - c
    b = np.einsum("nkc,nkc->nk", rel, d)
    meets = (b * b - (np.sum(rel * rel, -1) - r * r) > 0) & (b < 0)
    nearer = np.linalg.norm(c - pts, axis=-1) < np.linalg.norm(lc - pts, axis=-1)
    needed = (meets.any(-1) & nearer) | (np.linalg.norm(pts - c, axis=-1) <= r)
    assert not np.any(needed & ~mask), "a receiver whose rays meet the sphere was skipped"
    # and it skips: most receivers that no ray of the fine cap reaches are marked free
    assert np.mean(mask[~needed]) < 0.2
    inside_light = np.asarray(cone_may_meet_sphere(lc[None] + 0.1, lc, lr, lc + [0.0, -2.0, 0.0], r))
    assert not inside_light[0]  # inside the light, but the sphere is farther than the light's centre
    inside = np.asarray(cone_may_meet_sphere(c[None] + 0.1, lc, lr, c, r))
    assert inside[0]


def test_fan_test_is_conservative_against_its_directions(rng):
    n = 3000
    pts = rng.uniform(-4, 4, size=(n, 3))
    axis = np.array([0.3, 0.9, -0.3])
    axis /= np.linalg.norm(axis)
    half = 0.25
    c, r = np.array([0.2, 1.2, 0.3]), 0.5
    mask = np.asarray(fan_may_meet_sphere(pts, axis, half, c, r))
    # directions filling the cone about the axis (its rim included)
    d = np.asarray(stratified_sphere_cone(jnp.asarray(axis * 10.0), 10.0 * np.sin(half), (16, 48)))
    rim = np.cos(half) * axis + np.sin(half) * np.cross(axis, [1.0, 0.0, 0.0]) / np.linalg.norm(
        np.cross(axis, [1.0, 0.0, 0.0])
    )
    d = np.concatenate([d, rim[None]], 0)
    rel = pts - c
    b = rel @ d.T
    meets = (b * b - (np.sum(rel * rel, -1)[:, None] - r * r) > 0) & (b < 0)
    needed = meets.any(-1) | (np.linalg.norm(pts - c, axis=-1) <= r)
    assert not np.any(needed & ~mask)
    assert np.mean(mask[~needed]) < 0.2


def test_cone_test_has_no_derivative_and_no_nan():
    def f(p):
        return jnp.sum(cone_may_meet_sphere(p, jnp.zeros(3), 0.5, jnp.zeros(3), 0.5).astype(jnp.float32))

    for p in (jnp.zeros((1, 3)), jnp.asarray([[0.0, 0.0, 1e-30]]), jnp.asarray([[0.0, 2.0, 0.0]])):
        g = jax.grad(f)(p)
        assert np.all(np.asarray(g) == 0)


def test_light_fractions_with_and_without_skipping_agree():
    """A 48² plane (4 chunks, most receivers far from the shadow): same fractions and same
    derivatives with respect to the light's centre, the mesh's vertices and the receivers."""
    occ, _ = _icosphere_world(subdiv=2)
    scene = _light_scene(occ, IMAGES, n=48)
    pts, nrm = scene.receivers.points, scene.receivers.normals
    w = jnp.asarray(np.random.default_rng(1).uniform(0.5, 1.5, pts.shape[0]), jnp.float32)

    def loss(light_c, unit, p, cull):
        o = dataclasses.replace(scene.occluders[0], unit_vertices=unit)
        light = SphereLight(light_c, LIGHT.radius, LIGHT.radiance)
        s = dataclasses.replace(scene, occluders=(o,), lights=(light,))
        images = (occluder_images(o, 0.0, s),)
        return jnp.sum(w * light_visible_fractions(s, images, p, nrm, cull=cull)[0])

    args = (LIGHT.center, occ.unit_vertices, pts)
    v1, g1 = jax.value_and_grad(loss, (0, 1, 2))(*args, True)
    v0, g0 = jax.value_and_grad(loss, (0, 1, 2))(*args, False)
    assert float(v0) < float(jnp.sum(w)) - 1.0  # there is a shadow
    np.testing.assert_allclose(float(v1), float(v0), rtol=1e-6)
    for a, b in zip(g1, g0, strict=True):
        scale = float(jnp.max(jnp.abs(b)))
        assert scale > 0
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-4 * scale)
    mask = cone_may_meet_sphere(pts, LIGHT.center, LIGHT.radius, occ.center, occ.radius)
    assert float(jnp.mean(mask)) < 0.5  # the test scene skips most of its receivers


def test_environment_fractions_with_and_without_skipping_agree():
    """The sun map's 32 lamps (4 fans) over a 48² plane and the mesh's own vertices: with exact rays
    for the own vertices, the same fractions and receiver derivatives either way; without them the
    own vertices are ``inside`` (shaded by the n-band path) and not looked up (fraction 1), the rest
    the same. Most of the receivers are skipped for at least one fan."""
    from test_environment_lights import SPLIT, _sun_scene

    for rays in (True, False):
        method = dataclasses.replace(SPLIT, environment_lights=32)
        if rays:
            method = dataclasses.replace(method, self_visibility="rays")
        scene = _sun_scene(method, n=48, self_shadow=True)
        images, lights = scene_images(scene, 0.0), scene_lighting(scene).env_lights
        own = own_rows_at_time(scene, 0.0)
        pts, nrm = receivers_at_time(scene, 0.0)
        _, inside = environment_visible_fraction(scene, images, lights, pts, nrm, own, cull=False)
        out = ~np.asarray(inside)
        assert np.all(out) if rays else np.sum(~out) == pts.shape[0] - 48 * 48
        rng = np.random.default_rng(2)
        w = jnp.asarray(rng.uniform(0.5, 1.5, (pts.shape[0], 3)) * out[:, None], jnp.float32)

        def loss(shift, cull, own=own, pts=pts, nrm=nrm, w=w, scene=scene, images=images, lights=lights):
            f, _ = environment_visible_fraction(scene, images, lights, pts + shift, nrm, own, cull=cull)
            return jnp.sum(w * f), f

        shift = jnp.zeros(3, jnp.float32)
        (v1, f1), g1 = jax.value_and_grad(loss, has_aux=True)(shift, True)
        (v0, f0), g0 = jax.value_and_grad(loss, has_aux=True)(shift, False)
        assert float(v0) < float(jnp.sum(w)) - 1.0  # there is a shadow
        np.testing.assert_allclose(float(v1), float(v0), rtol=1e-6)
        scale = float(jnp.max(jnp.abs(g0)))
        assert scale > 0
        np.testing.assert_allclose(np.asarray(g1), np.asarray(g0), rtol=1e-4, atol=1e-4 * scale)
        np.testing.assert_allclose(np.asarray(f1)[out], np.asarray(f0)[out], atol=1e-6)
        np.testing.assert_array_equal(np.asarray(f1)[~out], 1.0)
    fan, occ = lights.fan, scene.occluders[0]
    skipped = []
    for g in range(lights.axes.shape[0]):
        d, ax = lights.directions[g * fan : (g + 1) * fan], lights.axes[g]
        half = jnp.arccos(jnp.clip(jnp.min(d @ ax), -1.0, 1.0))
        skipped.append(1.0 - float(jnp.mean(fan_may_meet_sphere(pts, ax, half, occ.center, occ.radius))))
    assert max(skipped) > 0.5, skipped
