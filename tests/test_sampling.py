"""Statistical and closed-form tests of the direction samplers (jshadow.sampling).

Projected spherical caps (Peters & Dachsbacher 2019) are checked as papers/projected-caps-algorithm.md
§9 does: the density integrates to 1 (cap-adapted quadrature that integrates exactly up to the
horizon), χ² of samples against the density, samples inside the cap and above the horizon, the
max/min density ratio against the supplement's bound, zero variance with the closed-form mean.
χ² thresholds are Šidák-corrected over all χ² tests of this module.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES
from scipy import stats

from jshadow._numerics import eps
from jshadow.entities import Environment, dir_to_latlong
from jshadow.sampling import (
    CapCase,
    cosine_hemisphere_pdf,
    environment_pdf,
    environment_sampler,
    projected_cap_case,
    projected_cap_density_bound,
    projected_cap_pdf,
    projected_solid_angle,
    random_cosine_hemisphere,
    random_environment,
    random_projected_cap,
    random_sphere_cone,
    sample_cosine_hemisphere,
    sample_environment,
    sample_projected_cap,
    sample_sphere_cone,
    segment_area,
    segment_area_inverse,
    sphere_cone_pdf,
)

N_CHI2_TESTS = 7  # χ² tests in this module
NUM = 1 << 16  # samples per configuration (one size: jit caches hit across tests)
ALPHA = 1.0 - (1.0 - 0.01) ** (1.0 / N_CHI2_TESTS)  # Šidák: family-wise 1 %

# (|c|/r, elevation of the centre above the tangent plane in degrees, expected case)
CASES = [
    (3.0, 40.0, CapCase.FULL),
    (3.0, 10.0, CapCase.CLIP_ABOVE),
    (1.2, -30.0, CapCase.CLIP_BELOW),  # mostly below the horizon
    (20.0, -1.0, CapCase.CLIP_BELOW),
]


def rotation(seed):
    q = np.random.default_rng(seed).normal(size=(3, 3))
    q, _ = np.linalg.qr(q)
    return q * np.sign(np.linalg.det(q))


def config(dist_over_r, elev_deg, r=0.7, seed=0):
    """Normal, centre vector and radius in a random world orientation."""
    e = np.radians(elev_deg)
    rot = rotation(seed)
    n = rot @ np.array([0.0, 0.0, 1.0])
    c = rot @ (dist_over_r * r * np.array([np.cos(e), 0.0, np.sin(e)]))
    return n, c, r


def cap_frame(n, c, r):
    wd = c / np.linalg.norm(c)
    alpha = np.arcsin(r / np.linalg.norm(c))
    p = n - (n @ wd) * wd
    if np.linalg.norm(p) < 1e-12:  # n along the axis: any perpendicular
        p = np.cross(wd, [1.0, 0.0, 0.0] if abs(wd[0]) < 0.9 else [0.0, 1.0, 0.0])
        p = p - (p @ wd) * wd
    e1 = p / np.linalg.norm(p)
    e2 = np.cross(wd, e1)
    return wd, e1, e2, alpha


def cap_integral(fn, n, c, r, psi_edges=None, phi_edges=None, n_psi=48, n_phi=48):
    """∫ fn(ω) dω over the visible cap (cap ∩ upper hemisphere), per (ψ, φ) bin around ω_d.

    For each azimuth φ the visible ψ-range is an interval that ends exactly at the horizon
    (z(ψ) = ρ cos(ψ − ψ*)), so Gauss–Legendre in ψ sees a smooth integrand. In φ, Gauss–Legendre
    on segments split at the kinks where the horizon meets the cap's rim. One call of ``fn``.
    """
    wd, e1, e2, alpha = cap_frame(n, c, r)
    wdz, wdx = n @ wd, n @ e1
    psi_edges = np.array([0.0, alpha]) if psi_edges is None else psi_edges
    phi_edges = np.array([0.0, 2 * np.pi]) if phi_edges is None else phi_edges
    # kinks: ψ*(φ) ± π/2 = α  ⇔  cos φ = ∓wdz/(wdx tan α)
    kinks = []
    for sgn in (1.0, -1.0):
        den = wdx * np.tan(alpha)
        cphi = -sgn * wdz / den if den > 0 else np.inf
        if abs(cphi) < 1:
            kinks += [np.arccos(cphi), 2 * np.pi - np.arccos(cphi)]
    gx, gw = np.polynomial.legendre.leggauss(n_psi)
    fx, fw = np.polynomial.legendre.leggauss(n_phi)
    phis, wphi, jbin = [], [], []
    for j in range(len(phi_edges) - 1):
        a, b = phi_edges[j], phi_edges[j + 1]
        cuts = np.sort(np.concatenate([[a, b], [k for k in kinks if a < k < b]]))
        for lo, hi in zip(cuts[:-1], cuts[1:]):
            phis.append(lo + 0.5 * (hi - lo) * (fx + 1))
            wphi.append(0.5 * (hi - lo) * fw)
            jbin.append(np.full(n_phi, j))
    phis, wphi, jbin = np.concatenate(phis), np.concatenate(wphi), np.concatenate(jbin)
    psi_star = np.arctan2(wdx * np.cos(phis), wdz)
    lo = np.maximum(psi_edges[:-1, None], psi_star[None] - np.pi / 2)  # (bins ψ, φ nodes)
    hi = np.minimum(psi_edges[1:, None], psi_star[None] + np.pi / 2)
    ln = np.maximum(hi - lo, 0.0)
    psi = lo[..., None] + 0.5 * ln[..., None] * (gx + 1.0)  # (ψ bins, φ nodes, ψ nodes)
    cp, sp = np.cos(phis)[None, :, None], np.sin(phis)[None, :, None]
    d = np.cos(psi)[..., None] * wd + (np.sin(psi) * cp)[..., None] * e1 + (np.sin(psi) * sp)[..., None] * e2
    f = padded(fn, d) * np.sin(psi)
    per_node = np.sum(0.5 * ln[..., None] * gw * f, axis=-1) * wphi  # (ψ bins, φ nodes)
    out = np.zeros((len(psi_edges) - 1, len(phi_edges) - 1))
    for j in range(len(phi_edges) - 1):
        out[:, j] = per_node[:, jbin == j].sum(axis=1)
    return out


def padded(fn, d, bucket=1 << 16):
    """fn on directions d (..., 3), padded to a multiple of ``bucket`` rows so that jit caches hit."""
    flat = d.reshape(-1, 3)
    m = -(-len(flat) // bucket) * bucket
    pad = np.concatenate([flat, np.tile([[0.0, 0.0, 1.0]], (m - len(flat), 1))])
    return np.asarray(fn(pad))[: len(flat)].reshape(d.shape[:-1])


def to_cap_coords(d, n, c, r):
    wd, e1, e2, alpha = cap_frame(n, c, r)
    psi = np.arctan2(np.linalg.norm(np.cross(d, wd), axis=-1), d @ wd)
    phi = np.mod(np.arctan2(d @ e2, d @ e1), 2 * np.pi)
    return psi, phi


def chi2_pvalue(observed, expected, min_expected=5.0):
    """χ² p-value, pooling cells with expected count < min_expected into one cell."""
    observed, expected = observed.ravel(), expected.ravel()
    small = expected < min_expected
    o = np.append(observed[~small], observed[small].sum())
    e = np.append(expected[~small], expected[small].sum())
    keep = e > 0
    assert np.all(o[~keep] == 0), "samples where the density integrates to zero"
    o, e = o[keep], e[keep]
    stat = np.sum((o - e) ** 2 / e)
    return stats.chi2.sf(stat, len(o) - 1)


# --------------------------------------------------------------------------------------------


@pytest.mark.usefixtures("x64")
def test_segment_area_and_inverse():
    x = np.linspace(-1.0, 1.0, 4001)
    want = np.arccos(x) - x * np.sqrt(1 - x * x)
    got = np.asarray(segment_area(jnp.asarray(x)))
    np.testing.assert_allclose(got, want, atol=1e-14)
    # near 1 the series must beat the cancelling direct formula: compare with mpmath-free Taylor in ε
    e = np.array([1e-4, 1e-6, 1e-8])
    series = 4 * np.sqrt(2) / 3 * e**1.5 * (1 - 3 * e / 20)
    np.testing.assert_allclose(np.asarray(segment_area(jnp.asarray(1 - e))), series, rtol=1e-7)
    xi = np.asarray(segment_area_inverse(jnp.asarray(want)))
    np.testing.assert_allclose(xi, x, atol=1e-10)
    w = np.linspace(0, np.pi, 1001)
    np.testing.assert_allclose(np.asarray(segment_area(segment_area_inverse(jnp.asarray(w)))), w, atol=1e-13)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("dist,elev,case", CASES)
def test_projected_cap_pdf_integrates_to_one(dist, elev, case):
    n, c, r = config(dist, elev, seed=int(abs(dist * 10 + elev)))
    assert int(projected_cap_case(n, c, r)) == case
    total = cap_integral(lambda d: projected_cap_pdf(jnp.asarray(d), n, c, r), n, c, r)
    np.testing.assert_allclose(total.sum(), 1.0, atol=1e-6)
    # and zero outside the visible cap
    rng = np.random.default_rng(1)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    wd, _, _, alpha = cap_frame(n, c, r)
    outside = (d @ wd < np.cos(alpha) - 1e-9) | (d @ n < -1e-9)
    assert np.all(padded(lambda w: projected_cap_pdf(w, n, c, r), d[outside]) == 0.0)
    # projected solid angle: closed form vs quadrature of max(0, n·ω) over the cap
    omega_q = cap_integral(lambda d: np.maximum(d @ n, 0.0), n, c, r).sum()
    np.testing.assert_allclose(float(projected_solid_angle(n, c, r)), omega_q, rtol=1e-7)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("dist,elev,case", CASES[:3])
def test_projected_cap_chi2(dist, elev, case):
    n, c, r = config(dist, elev, seed=7)
    num = NUM
    s = random_projected_cap(jax.random.PRNGKey(3), n, c, r, num)
    d = np.asarray(s.direction)
    assert np.all(np.asarray(s.valid))
    _, _, _, alpha = cap_frame(n, c, r)
    t_edges = np.linspace(0.0, 1.0, 13)
    psi_edges = np.arccos(1.0 - t_edges * (1.0 - np.cos(alpha)))
    phi_edges = np.linspace(0.0, 2 * np.pi, 25)
    if case == CapCase.CLIP_BELOW:
        dens = lambda w: projected_cap_pdf(jnp.asarray(w), n, c, r)  # noqa: E731
    else:  # the ideal density, independent of the implementation's pdf
        omega = cap_integral(lambda w: np.maximum(w @ n, 0.0), n, c, r).sum()
        dens = lambda w: np.maximum(w @ n, 0.0) / omega  # noqa: E731
    expected = num * cap_integral(dens, n, c, r, psi_edges, phi_edges, n_psi=12, n_phi=8)
    psi, phi = to_cap_coords(d, n, c, r)
    observed, _, _ = np.histogram2d(psi, phi, bins=[psi_edges, phi_edges])
    assert chi2_pvalue(observed, expected) > ALPHA
    # negative control: the uniform cone's samples must fail the same test
    cone = np.asarray(random_sphere_cone(jax.random.PRNGKey(4), c, r, num).direction)
    cone = cone[cone @ n > 0]
    psi, phi = to_cap_coords(cone, n, c, r)
    observed, _, _ = np.histogram2d(psi, phi, bins=[psi_edges, phi_edges])
    if case != CapCase.FULL or True:
        assert chi2_pvalue(observed, expected * len(cone) / num) < 1e-6


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("dist,elev,case", CASES)
def test_projected_cap_samples_in_cap_and_pdf_consistent(dist, elev, case):
    n, c, r = config(dist, elev, seed=11)
    s = random_projected_cap(jax.random.PRNGKey(0), n, c, r, NUM)
    d = np.asarray(s.direction)
    wd, _, _, alpha = cap_frame(n, c, r)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-14)
    assert np.all(d @ n >= -1e-15)
    assert np.all(d @ wd >= np.cos(alpha) - 1e-13)
    pdf_again = np.asarray(projected_cap_pdf(s.direction, n, c, r))
    inner = d @ wd > np.cos(alpha) + 1e-9  # boundary samples may round either way (measure zero)
    np.testing.assert_allclose(pdf_again[inner], np.asarray(s.pdf)[inner], rtol=1e-9)
    np.testing.assert_allclose(np.asarray(s.pdf), np.asarray(s.pdf_proj) * (d @ n), rtol=1e-9, atol=1e-300)


@pytest.mark.usefixtures("x64")
def test_projected_cap_density_ratio_bound():
    """max/min of p⊥ is the supplement's bound (Eq. 4), and ≤ √2 once |c|/r ≥ 2."""
    u = jnp.asarray(np.random.default_rng(0).random((NUM, 2)))
    u = u.at[0].set(jnp.asarray([1.0 - 1e-12, 0.5]))  # the top point (d_x = t_x, d_y = 0): the max
    worst = 0.0
    for dist in (2.0, 3.0, 10.0):
        for elev in np.linspace(-0.98, -0.02, 9) * np.degrees(np.arcsin(1 / dist)):
            n, c, r = config(dist, elev, seed=5)
            s = sample_projected_cap(u, n, c, r)
            p = np.asarray(s.pdf_proj)
            ratio = p.max() / p.min()
            bound = float(projected_cap_density_bound(n, c, r))
            assert ratio <= bound * (1 + 1e-9)
            assert ratio >= bound * 0.98  # the bound is attained
            worst = max(worst, ratio)
    assert worst <= np.sqrt(2) + 1e-9
    assert worst > 1.38  # the curve approaches √2 near |c|/r = 2
    n, c, r = config(1.2, -30.0)  # closer than one radius: may exceed √2 but stays under the bound
    assert float(projected_cap_density_bound(n, c, r)) > np.sqrt(2)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("dist,elev", [(3.0, 40.0), (1.5, 80.0), (50.0, 5.0), (3.0, 10.0), (1.1, 2.0)])
def test_unoccluded_sphere_light_zero_variance(dist, elev):
    n, c, r = config(dist, elev, r=0.3, seed=2)
    s = random_projected_cap(jax.random.PRNGKey(1), n, c, r, NUM)
    est = 1.0 / np.asarray(s.pdf_proj)  # estimator of ∫_cap max(0, n·ω) dω
    assert est.std() <= 1e-12 * est.mean()
    sin_a, cos_b = 1.0 / dist, np.sin(np.radians(elev))
    if sin_a < cos_b:  # cap above the horizon: π sin²α cos β
        np.testing.assert_allclose(est.mean(), np.pi * sin_a**2 * cos_b, rtol=1e-12)
    else:
        np.testing.assert_allclose(
            est.mean(), cap_integral(lambda d: np.maximum(d @ n, 0), n, c, r).sum(), rtol=1e-8
        )


def test_projected_cap_empty_inside_and_overhead():
    n = jnp.asarray([0.0, 1.0, 0.0])
    u = jnp.asarray([[0.3, 0.7], [0.9, 0.1]])
    empty = sample_projected_cap(u, n, jnp.asarray([0.0, -3.0, 0.0]), 1.0)
    inside = sample_projected_cap(u, n, jnp.asarray([0.1, 0.2, 0.0]), 1.0)
    for s in (empty, inside):
        assert not np.any(np.asarray(s.valid))
        assert np.all(np.asarray(s.pdf) == 0) and np.all(np.isfinite(np.asarray(s.direction)))
    over = sample_projected_cap(u, n, jnp.asarray([0.0, 4.0, 0.0]), 1.0)  # degenerate frame
    assert np.all(np.asarray(over.valid))
    np.testing.assert_allclose(np.asarray(1.0 / over.pdf_proj), np.pi / 16, rtol=eps(jnp.float32, 10))
    # centre exactly on the horizon: clipped, density still finite and positive
    hor = sample_projected_cap(u, n, jnp.asarray([3.0, 0.0, 0.0]), 1.0)
    assert np.all(np.asarray(hor.valid)) and np.all(np.asarray(hor.pdf_proj) > 0)


def test_projected_cap_float32_consistent():
    n, c, r = config(1.2, -30.0)
    n, c = jnp.asarray(n, jnp.float32), jnp.asarray(c, jnp.float32)
    s = random_projected_cap(jax.random.PRNGKey(0), n, c, r, 20000)
    assert s.direction.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(s.pdf_proj))) and np.all(np.asarray(s.pdf_proj) > 0)
    wd = np.asarray(c) / np.linalg.norm(np.asarray(c))
    assert np.all(np.asarray(s.direction) @ wd >= np.sqrt(1 - (1 / 1.2) ** 2) - 1e-5)
    est = 1.0 / np.asarray(s.pdf_proj, np.float64)
    assert (
        abs(est.mean() / float(projected_solid_angle(n, c, r)) - 1)
        < 4 * est.std() / np.sqrt(len(est)) / est.mean() + 1e-4
    )


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_batch_shapes(shape, rng):
    from conftest import random_dirs

    n = jnp.asarray(random_dirs(rng, shape, np.float32))
    c = jnp.asarray(3.0 * random_dirs(rng, shape, np.float32))
    u = jnp.asarray(rng.random((*shape, 2)), jnp.float32)
    for s in (
        sample_projected_cap(u, n, c, 1.0),
        sample_sphere_cone(u, c, 1.0),
        sample_cosine_hemisphere(u, n),
    ):
        assert s.direction.shape == (*shape, 3) and s.pdf.shape == shape and s.valid.shape == shape
    assert projected_cap_pdf(c, n, c, 1.0).shape == shape
    assert sphere_cone_pdf(c, c, 1.0).shape == shape
    if len(shape) == 3:
        r = random_projected_cap(jax.random.PRNGKey(0), n, c, 1.0, 5)
        assert r.direction.shape == (*shape, 5, 3)
        # vmap agrees with batching
        flat = jax.vmap(sample_projected_cap)(
            u.reshape(-1, 2), n.reshape(-1, 3), c.reshape(-1, 3), jnp.ones(u[..., 0].size, jnp.float32)
        )
        np.testing.assert_allclose(
            np.asarray(flat.direction),
            np.asarray(sample_projected_cap(u, n, c, 1.0).direction.reshape(-1, 3)),
            atol=1e-6,
        )


def test_determinism_and_jit():
    n, c, r = config(1.2, -30.0)
    n, c = jnp.asarray(n, jnp.float32), jnp.asarray(c, jnp.float32)
    a = random_projected_cap(jax.random.PRNGKey(5), n, c, r, 20000)
    b = random_projected_cap(jax.random.PRNGKey(5), n, c, r, 20000)
    other = random_projected_cap(jax.random.PRNGKey(6), n, c, r, 20000)
    np.testing.assert_array_equal(np.asarray(a.direction), np.asarray(b.direction))
    assert not np.allclose(np.asarray(a.direction), np.asarray(other.direction))


def test_input_validation():
    with pytest.raises(ValueError, match=r"\(\.\.\., 2\)"):
        sample_projected_cap(jnp.zeros(3), jnp.zeros(3), jnp.ones(3), 1.0)
    with pytest.raises(ValueError, match="normal"):
        sample_projected_cap(jnp.zeros(2), jnp.zeros(2), jnp.ones(3), 1.0)
    with pytest.raises(ValueError, match="hdr"):
        environment_sampler(Environment(jnp.ones(3)))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        environment_sampler(jnp.ones((4, 3)))


# ---------------------------------------------------------------------------- cone, cosine, env


@pytest.mark.usefixtures("x64")
def test_cone_sampler_against_pdf():
    n, c, r = config(2.5, 30.0)
    num = NUM
    s = random_sphere_cone(jax.random.PRNGKey(1), c, r, num)
    d = np.asarray(s.direction)
    wd, _, _, alpha = cap_frame(n, c, r)
    psi, phi = to_cap_coords(d, n, c, r)
    assert np.all(psi <= alpha + 1e-12)
    t = (1 - np.cos(psi)) / (1 - np.cos(alpha))  # uniform in solid angle ⇒ t, φ uniform
    assert stats.kstest(t, "uniform").pvalue > ALPHA
    assert stats.kstest(phi / (2 * np.pi), "uniform").pvalue > ALPHA
    np.testing.assert_allclose(np.asarray(s.pdf), 1 / (2 * np.pi * (1 - np.cos(alpha))), rtol=1e-10)
    assert float(sphere_cone_pdf(jnp.asarray(-wd), c, r)) == 0.0
    np.testing.assert_allclose(
        cap_integral(lambda w: sphere_cone_pdf(jnp.asarray(w), c, r), wd, c, r).sum(), 1.0, rtol=1e-9
    )


@pytest.mark.usefixtures("x64")
def test_cosine_hemisphere_against_pdf():
    n = np.array([0.3, -0.5, 0.812403840463596])
    n = n / np.linalg.norm(n)
    s = random_cosine_hemisphere(jax.random.PRNGKey(0), jnp.asarray(n), 50_000)
    d = np.asarray(s.direction)
    z = d @ n
    assert np.all(z >= 0)
    assert stats.kstest(z * z, "uniform").pvalue > ALPHA  # p(z) = 2z on [0, 1]
    np.testing.assert_allclose(np.asarray(s.pdf), z / np.pi, atol=1e-14)
    np.testing.assert_allclose(
        np.asarray(cosine_hemisphere_pdf(s.direction, jnp.asarray(n))), z / np.pi, atol=1e-14
    )
    # pdf integrates to one: Gauss-Legendre over the hemisphere in cos θ, midpoint in φ
    x, w = np.polynomial.legendre.leggauss(16)
    ct = 0.5 * (x + 1)
    ph = (np.arange(32) + 0.5) * 2 * np.pi / 32
    st = np.sqrt(1 - ct**2)
    dirs = np.stack(np.broadcast_arrays(st[:, None] * np.cos(ph), st[:, None] * np.sin(ph), ct[:, None]), -1)
    vals = np.asarray(cosine_hemisphere_pdf(jnp.asarray(dirs), jnp.asarray([0.0, 0.0, 1.0])))
    np.testing.assert_allclose(np.sum(0.5 * w[:, None] * vals) * 2 * np.pi / 32, 1.0, rtol=1e-12)


@pytest.mark.usefixtures("x64")
def test_environment_sampler_against_pdf():
    rng = np.random.default_rng(0)
    h, w = 8, 16
    img = rng.random((h, w, 3)) ** 4
    img[2, 3] = 0.0  # black pixel: never sampled
    img[5, 10] *= 50.0  # a bright "sun"
    env = Environment(jnp.asarray([1.0, 0.5, 2.0]), jnp.asarray(img), kind="hdr")
    sam = environment_sampler(env)
    num = 100_000
    s = random_environment(sam, jax.random.PRNGKey(0), (num,))
    d = np.asarray(s.direction)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    u, v = (np.asarray(a) for a in dir_to_latlong(s.direction))
    i, j = np.minimum((v * h).astype(int), h - 1), np.minimum((u * w).astype(int), w - 1)
    counts = np.zeros((h, w))
    np.add.at(counts, (i, j), 1)
    assert counts[2, 3] == 0
    luma = (img * np.array([1.0, 0.5, 2.0])) @ np.array([0.2126, 0.7152, 0.0722])
    ct = np.cos(np.pi * np.arange(h + 1) / h)
    omega = 2 * np.pi / w * (ct[:-1] - ct[1:])
    p = luma * omega[:, None]
    p /= p.sum()
    assert chi2_pvalue(counts, num * p) > ALPHA
    # the density is P_ij / Ω_ij, equal at the sample and by lookup, and integrates to one
    np.testing.assert_allclose(np.asarray(s.pdf), (p / omega[:, None])[i, j], rtol=1e-9)
    np.testing.assert_allclose(np.asarray(environment_pdf(sam, s.direction)), np.asarray(s.pdf), rtol=1e-12)
    np.testing.assert_allclose(np.sum(np.asarray(sam.pmf)), 1.0, rtol=1e-12)
    # within a pixel, directions are uniform in solid angle: cos θ uniform between the row bounds
    sel = (i == 5) & (j == 10)
    frac = (ct[5] - d[sel, 1]) / (ct[5] - ct[6])
    assert stats.kstest(frac, "uniform").pvalue > ALPHA
    # L/p is constant per pixel: the un-cosined integral ∫ L dω is estimated exactly
    lum_est = (
        np.asarray(env.radiance_at(s.direction)) @ np.array([0.2126, 0.7152, 0.0722]) / np.asarray(s.pdf)
    )
    np.testing.assert_allclose(lum_est, np.sum(luma * omega[:, None]), rtol=1e-9)
    direct = sample_environment(sam, jnp.asarray([[0.0, 0.0], [1 - 1e-12, 1 - 1e-12]]))
    assert np.all(np.asarray(direct.valid))


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("dist,elev,case", CASES[:3])
def test_projected_solid_angle_gradient(dist, elev, case):
    """dΩ⊥/d(light centre) against central differences, in every non-empty case."""
    n, c, r = config(dist, elev, seed=3)
    f = lambda cc: projected_solid_angle(n, cc, r)  # noqa: E731
    g = np.asarray(jax.grad(f)(jnp.asarray(c)))
    h = 1e-6
    fd = np.array([(float(f(c + h * e)) - float(f(c - h * e))) / (2 * h) for e in np.eye(3)])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-9)


@pytest.mark.usefixtures("x64")
def test_gradients_finite_at_singular_points():
    """Light straight overhead (degenerate tangent frame), centre on the horizon, receiver inside
    the light, cap below the horizon: finite gradients of Ω⊥, of the sampled density and of pdf."""
    n = jnp.asarray([0.0, 0.0, 1.0])
    u = jnp.asarray([0.3, 0.6])
    for c in ([0.0, 0.0, 3.0], [3.0, 0.0, 0.0], [0.1, 0.0, 0.2], [0.0, 0.0, -3.0]):
        c = jnp.asarray(c)
        for fn in (
            lambda cc: projected_solid_angle(n, cc, 1.0),
            lambda cc: sample_projected_cap(u, n, cc, 1.0).pdf_proj,
            lambda cc: projected_cap_pdf(jnp.asarray([0.6, 0.0, 0.8]), n, cc, 1.0),
        ):
            g = np.asarray(jax.grad(fn)(c))
            assert np.all(np.isfinite(g)), (c, g)
