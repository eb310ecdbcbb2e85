"""Fixed-geometry frames read out of the field's table (jshadow.readout) against the general path."""

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jshadow.entities import Environment, MeshOccluder, Method, Receivers, Scene, SphereLight, SphereOccluder
from jshadow.geometry import Bend, Breathe, bounding_sphere, normalize_to_unit_sphere
from jshadow.readout import prepare_readout, shade_readout
from jshadow.runner import Renderer
from jshadow.scene import occlusion_table, scene_lighting

CENTRE = (0.1, 1.0, -0.2)
FAR_ROW, CENTRE_ROW = 81, 82  # receivers(): the plane's 81, one beyond the table, one at the centre


def receivers(dtype, n=9, size=4.0):
    """A plane of n² receivers plus four awkward ones with the plane's normal: beyond the table's
    largest distance (below the plane, facing the occluder), at the occluder's centre, on the polar
    axis below the centre (ρ = 0), and one under the light, where the light is nearer than the
    occluder."""
    xs = np.linspace(-size / 2, size / 2, n)
    x, z = np.meshgrid(xs, xs)
    pts = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], -1)
    extra = [(0.6, -9.0, -0.2), CENTRE, (CENTRE[0], 0.0, CENTRE[2]), (1.6, 2.9, 0.9)]
    pts = np.concatenate([pts, np.asarray(extra)]).astype(dtype)
    nrm = np.tile(np.asarray([0.0, 1.0, 0.0], dtype), (len(pts), 1))
    return Receivers(jnp.asarray(pts), jnp.asarray(nrm), jnp.asarray([0.8, 0.7, 0.6], dtype))


def scene_with(deform, dtype="float64", shading="ratio", self_shadow=False, frames=4, bsv_center="placed"):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh.vertices[:, 0] *= 1.4  # not a sphere: the pose changes the shadow
    unit = normalize_to_unit_sphere(jnp.asarray(mesh.vertices, dtype))
    occ = MeshOccluder(
        unit, jnp.asarray(mesh.faces, jnp.int32), jnp.asarray(CENTRE, dtype), jnp.asarray(0.6, dtype), deform
    )
    light = SphereLight(
        jnp.asarray([1.5, 3.0, 1.0], dtype), jnp.asarray(0.4, dtype), jnp.asarray([30.0, 25.0, 20.0], dtype)
    )
    env = Environment(jnp.asarray([0.6, 0.65, 0.7], dtype), kind="sky")
    method = Method(
        bsv_grid=(6, 10), directions=(16, 16), dtype=dtype, shading=shading, bsv_center=bsv_center
    )
    return Scene(method, receivers(dtype), (occ,), (light,), env, self_shadow=self_shadow, n_frames=frames)


def frames_both_ways(scene, frames):
    general = Renderer(scene, static_readout=False)
    read = Renderer(scene)
    out = []
    for f in frames:
        a, _ = general.frame(f)
        b, _ = read.frame(f)
        out.append((a, b))
    assert general.readout_frames == 0
    return read, out


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize(
    "deform, shading, self_shadow",
    [
        (Breathe(0.0, 0.3, period=1.0), "ratio", False),  # the shell radius changes, the centre stays
        (Breathe(0.0, 0.3, period=1.0), "product", False),
        (None, "ratio", True),  # a rigid mesh's own vertices: a normal per receiver
        # a bend about a plane off the centre: the box centre moves, the placed centre does not
        (Bend(0.0, 1.0, axis="x", toward="y", origin=-1.0), "ratio", False),
        # a deforming mesh's own vertices move: the plane read out, they by the general path
        (Breathe(0.0, 0.3, period=1.0), "ratio", True),
    ],
    ids=["breathe", "product", "own-vertices", "off-centre-bend", "moving-own-vertices"],
)
def test_readout_frames_equal_the_general_path(deform, shading, self_shadow):
    # the readout applies the rotation to the functionals instead of the visibility and splits the
    # trilinear weights differently: the same algebra, so in float64 the same numbers to rounding
    scene = scene_with(deform, shading=shading, self_shadow=self_shadow)
    read, pairs = frames_both_ways(scene, range(4))
    assert read.readout_frames == 4 and read.readout_reason is None
    if isinstance(deform, Bend):  # not vacuous: the deformed mesh's box centre does move
        occ = scene.occluders[0]
        shift = np.asarray(bounding_sphere(occ.vertices(1.0))[0] - occ.center)
        assert np.abs(shift).max() > 0.05
    # the receiver at the centre sees the field in no defined direction: a shift of the centre within
    # rounding, which the readout ignores and the general path does not, turns it; compared apart
    rows = np.arange(len(pairs[0][0].irradiance)) != CENTRE_ROW
    for f, (a, b) in enumerate(pairs):
        np.testing.assert_allclose(np.asarray(b.points), np.asarray(a.points), rtol=0, atol=1e-15)
        e = np.asarray(a.irradiance)
        assert np.all(np.isfinite(np.asarray(b.irradiance)))
        # 1e-9: an own vertex on the occluder's polar axis reads φ from coordinates of order 1e-16
        # whose last bit the two paths round apart (3.5e-10 seen); everywhere else 1e-12 holds
        tight = dict(rtol=0, atol=1e-9 * e.max())
        np.testing.assert_allclose(np.asarray(b.irradiance)[rows], e[rows], **tight)
        np.testing.assert_allclose(np.asarray(b.radiance)[rows], np.asarray(a.radiance)[rows], **tight)
        if f == 0:  # the prepared pose: the centre row too
            np.testing.assert_allclose(np.asarray(b.irradiance), e, err_msg=f"frame {f}", **tight)
    shadowed = [np.abs(np.asarray(a.irradiance) - np.asarray(pairs[0][0].irradiance)).max() for a, _ in pairs]
    if deform is not None:  # the frames differ: the comparison is not of one frame four times
        assert max(shadowed) > 1e-3 * e.max()
    if not self_shadow:  # the receiver beyond the table's range sees no occluder
        bare = Scene(scene.method, scene.receivers, (), scene.lights, scene.environment, n_frames=4)
        free = np.asarray(Renderer(bare).frame(0)[0].irradiance)
        np.testing.assert_allclose(np.asarray(pairs[0][1].irradiance)[FAR_ROW], free[FAR_ROW], rtol=1e-12)


@pytest.mark.usefixtures("x64")
def test_a_moving_centre_is_seen_before_preparing_and_the_readout_used_at_its_own_pose():
    # with bsv_center = "box", a bend about a plane off the centre moves the deformed mesh's
    # bounding-box centre: the renderer samples it before preparing and renders every frame on the
    # general path; the readout made at one pose still gives that pose's numbers
    scene = scene_with(Bend(0.0, 1.0, axis="x", toward="y", origin=-1.0), bsv_center="box")
    read, pairs = frames_both_ways(scene, (0, 2))
    assert read.readout_frames == 0 and "centre moves" in read.readout_reason
    for a, b in pairs:
        np.testing.assert_array_equal(np.asarray(b.irradiance), np.asarray(a.irradiance))
    general = Renderer(scene, static_readout=False)
    table, n = occlusion_table(scene), scene.method.sh_bands
    bsv0, bsv1 = general._bsvs(0.0)[0], general._bsvs(1.0)[0]
    assert not np.array_equal(np.asarray(bsv0.center), np.asarray(bsv1.center))
    ro = prepare_readout(
        scene, bsv0, scene_lighting(scene), table, scene.receivers.points, scene.receivers.normals
    )
    e = np.asarray(pairs[0][0].irradiance)
    got = np.asarray(shade_readout(ro, bsv0, table, n, scene.receivers.albedo)[0])
    np.testing.assert_allclose(got, e, rtol=0, atol=1e-11 * e.max())
    # a move the sampling missed is caught at the frame: the readout is dropped, the frame rendered
    # on the general path
    r = Renderer(scene_with(Breathe(0.0, 0.3, period=1.0)))
    r.frame(0)
    assert r.readout_frames == 1
    ro, centre = r._readout
    r._readout = (ro, centre + 1e-3)
    r.frame(1)
    assert r.readout_frames == 1 and "centre moves" in r.readout_reason


def test_float32_readout_agrees_to_rounding():
    scene = scene_with(Breathe(0.0, 0.3, period=1.0), dtype="float32")
    read, pairs = frames_both_ways(scene, (0, 2))
    assert read.readout_frames == 2
    rows = np.arange(len(pairs[0][0].irradiance)) != CENTRE_ROW  # in no defined direction (above)
    for a, b in pairs:
        e = np.asarray(a.irradiance)
        assert b.irradiance.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(b.irradiance)[rows], e[rows], rtol=0, atol=2e-6 * e.max())


def test_a_one_frame_scene_reads_out_from_its_second_call():
    scene = scene_with(None, dtype="float32", frames=1)
    r = Renderer(scene)
    first, _ = r.frame(0)
    assert r.readout_frames == 0  # a single frame: no preparation for nothing
    second, _ = r.frame(0)
    assert r.readout_frames == 1
    e = np.asarray(first.irradiance)
    np.testing.assert_allclose(np.asarray(second.irradiance), e, rtol=0, atol=2e-6 * e.max())


def test_scenes_the_readout_does_not_take_render_as_before():
    base = scene_with(Breathe(0.0, 0.3, period=1.0), dtype="float32")
    sphere = SphereOccluder(jnp.asarray([0.0, 1.0, 0.0], jnp.float32), jnp.float32(0.4))
    cases = {
        "2 occluders": Scene(
            base.method, base.receivers, (*base.occluders, sphere), base.lights, base.environment, n_frames=4
        ),
        "analytic sphere": Scene(
            base.method, base.receivers, (sphere,), base.lights, base.environment, n_frames=4
        ),
        "no light": Scene(base.method, base.receivers, base.occluders, (), None, n_frames=4),
    }
    for words, scene in cases.items():
        r = Renderer(scene)
        a, _ = r.frame(1)
        b, _ = Renderer(scene, static_readout=False).frame(1)
        assert r.readout_frames == 0 and words in r.readout_reason
        np.testing.assert_array_equal(np.asarray(a.irradiance), np.asarray(b.irradiance))
    off = Renderer(base, static_readout=False)
    off.frame(1)
    assert off.readout_frames == 0 and off.readout_reason is None
    with pytest.raises(TypeError, match="static_readout"):
        Renderer(base, static_readout="yes")


@pytest.mark.usefixtures("x64")
def test_the_readout_call_without_a_hashable_scene_computes_the_same():
    # a scene whose static parts cannot key the flattened call takes eqx.filter_jit of the same
    # function (runner._readout_and_shade): the frame of the flattened call, plane and moving own
    # vertices alike
    from jshadow import runner

    scene = scene_with(Breathe(0.0, 0.3, period=1.0), self_shadow=True)
    r = Renderer(scene)
    flat, _ = r.frame(2)
    assert r.readout_frames == 1 and r._flat[True]
    ro, _ = r._readout
    t = jnp.asarray(2 / 3, jnp.float64)
    out = runner._readout_and_shade(scene, r._bsvs(t), t, r._lighting, True, ro, occlusion_table(scene))
    points, _, e, _ = runner._with_receivers(scene, out)
    assert e.shape == flat.irradiance.shape and e.shape[0] > scene.receivers.points.shape[0]
    np.testing.assert_allclose(np.asarray(points), np.asarray(flat.points), rtol=0, atol=1e-15)
    np.testing.assert_allclose(
        np.asarray(e), np.asarray(flat.irradiance), rtol=0, atol=1e-12 * float(e.max())
    )
