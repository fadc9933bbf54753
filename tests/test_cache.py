"""USD animation caches: what DCC tools need is authored, values read back exactly, files appear atomically."""

import json
import pathlib
import shutil
import subprocess
import types

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdPhysics, UsdValidation

import cloth_warp as cw
from cloth_warp.cache import CacheReader, UsdCacheWriter, vertex_normals
from cloth_warp.outputs import partial_path
from cloth_warp.runner import run_scene

ROOT = pathlib.Path(__file__).resolve().parents[1]
HANG = ROOT / "scenes" / "hanging_cloth.toml"
SMALL = {"cloth.grid.resolution": [8, 8]}


def _grid_sim(n=8, up_axis="Y"):
    b = cw.ModelBuilder(up_axis=up_axis)
    rot = cw.quat_from_axis_angle((1, 0, 0), -90.0) if up_axis == "Y" else (0.0, 0.0, 0.0, 1.0)
    c = b.add_cloth_grid(resolution=(n, n), size=(1.0, 1.0), rotation=rot, position=(0.0, 1.0, 0.0), name="sheet")
    b.pin(c.select("corners"))
    model = b.finalize("cpu")
    return model, cw.Simulator(model, cw.SolverSymplecticEuler(model), fps=30, substeps=64)  # stable (20 diverged, unseen)


@pytest.fixture(scope="module")
def hanging_cache(tmp_path_factory):
    """A 5-frame cache of the shipped hanging-cloth scene (8 x 8) and its summary."""
    out = tmp_path_factory.mktemp("cache") / "hang.usdc"
    summary = run_scene(HANG, SMALL, output=out, frames=5, start_frame=1001)
    return out, summary


def test_positions_and_velocities_read_back_exactly(tmp_path):
    """Check every frame's points and velocities in the cache equal the simulator's float32 state bit for bit."""
    model, sim = _grid_sim()
    path = tmp_path / "exact.usdc"
    written = []
    with UsdCacheWriter(path, model, fps=30) as w:
        for _ in range(4):
            q, qd = sim.state.particle_q.numpy().copy(), sim.state.particle_qd.numpy().copy()
            written.append((q, qd))
            w.write(q, qd)
            sim.step_frame()
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/sheet"))
    for k, (q, qd) in enumerate(written):
        np.testing.assert_array_equal(np.asarray(mesh.GetPointsAttr().Get(1 + k)), q)
        np.testing.assert_array_equal(np.asarray(mesh.GetVelocitiesAttr().Get(1 + k)), qd)
    assert not np.array_equal(written[0][0], written[-1][0])  # the cloth did move


def test_stage_metadata_and_static_topology(hanging_cache):
    """Check the stage metadata DCC tools read and that topology is authored once, never time-sampled."""
    path, summary = hanging_cache
    stage = Usd.Stage.Open(str(path))
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    assert stage.GetDefaultPrim().IsA(UsdGeom.Xform)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdPhysics.GetStageKilogramsPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == stage.GetFramesPerSecond() == 60.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1001, 1006)  # initial state + 5 frames
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cloth"))
    for attr in (mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr(), mesh.GetSubdivisionSchemeAttr(),
                 mesh.GetDoubleSidedAttr()):
        assert attr.HasAuthoredValue() and attr.GetNumTimeSamples() == 0
    assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    assert mesh.GetDoubleSidedAttr().Get() is True
    counts, indices = mesh.GetFaceVertexCountsAttr().Get(), mesh.GetFaceVertexIndicesAttr().Get()
    points = mesh.GetPointsAttr()
    assert points.Get(Usd.TimeCode.Default()) is not None  # the rest pose, for time-unaware readers
    assert UsdGeom.Mesh.ValidateTopology(indices, counts, len(points.Get(Usd.TimeCode.Default())))[0]
    for name in ("points", "extent", "normals", "velocities"):
        assert [int(t) for t in mesh.GetPrim().GetAttribute(name).GetTimeSamples()] == list(range(1001, 1007))
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex


def test_extent_matches_compute_extent_and_normals_are_unit(hanging_cache):
    """Check the authored extent equals UsdGeom's own computation at every frame, and normals are unit length."""
    stage = Usd.Stage.Open(str(hanging_cache[0]))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cloth"))
    for t in range(1001, 1007):
        authored = np.asarray(mesh.GetExtentAttr().Get(t))
        computed = np.asarray(UsdGeom.Boundable.ComputeExtentFromPlugins(mesh, Usd.TimeCode(t)))
        np.testing.assert_array_equal(authored, computed)
        n = np.asarray(mesh.GetNormalsAttr().Get(t))
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)


def test_diagnostics_and_provenance(hanging_cache):
    """Check per-frame diagnostics attributes and the customLayerData stamp (status, scene, versions)."""
    path, summary = hanging_cache
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/World/cloth")
    strain = prim.GetAttribute("clothWarp:maxStrain")
    assert [int(t) for t in strain.GetTimeSamples()] == list(range(1002, 1007))  # simulated frames
    assert max(strain.Get(t) for t in range(1002, 1007)) == pytest.approx(summary["max_strain"])
    assert prim.GetAttribute("clothWarp:dt").Get(1002) == pytest.approx(1.0 / 60.0)
    assert prim.GetAttribute("clothWarp:solverIterations").Get(1002) > 0  # implicit Euler's CG
    meta = stage.GetRootLayer().customLayerData["cloth_warp"]
    assert meta["status"] == "complete" and meta["frames_written"] == 6
    assert meta["scene_path"].endswith("hanging_cloth.toml") and "[cloth]" in meta["scene_text"]
    assert set(meta["versions"]) >= {"cloth_warp", "warp", "usd", "numpy"}
    assert json.loads(meta["overrides"]) == {"cloth.grid.resolution": [8, 8]}


def test_usd_validation_reports_no_errors(hanging_cache):
    """Check usd-core's UsdValidation (all registered validators) finds nothing wrong with a cache."""
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    errors = context.Validate(Usd.Stage.Open(str(hanging_cache[0])))
    assert [e.GetMessage() for e in errors] == []


def test_usd_validation_catches_a_broken_stage():
    """Check the validator used above does report problems (a stage without metadata), so the test has teeth."""
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    assert len(context.Validate(Usd.Stage.CreateInMemory())) >= 2


def test_nvidia_usd_validate_passes_on_a_shipped_scene(tmp_path):
    """Check NVIDIA's asset validator (usd-validation-nvidia, a test extra) exits 0 on the garment scene's cache."""
    exe = shutil.which("nvidia_usd_validate")
    if exe is None:
        pytest.skip("usd-validation-nvidia is not installed (pip install -e '.[test]')")
    out = tmp_path / "garment.usdc"
    run_scene(ROOT / "scenes" / "garment.toml", output=out, frames=2)
    result = subprocess.run([exe, str(out)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr


def test_uv_seam_survives_as_face_varying_st(tmp_path):
    """Check a mesh welded at its UV seam writes indexed face-varying st whose triangles do not wrap around."""
    out = tmp_path / "skirt.usdc"
    run_scene(ROOT / "scenes" / "garment.toml", output=out, frames=1)
    stage = Usd.Stage.Open(str(out))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/skirt"))
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying and st.IsIndexed()
    n_points = len(mesh.GetPointsAttr().Get(Usd.TimeCode.Default()))
    corners = np.asarray(st.ComputeFlattened()).reshape(-1, 3, 2)
    assert n_points == 720 and len(corners) == 1344  # 48 x 15 particles after welding, 48 x 14 x 2 triangles
    span = corners[:, :, 0].max(axis=1) - corners[:, :, 0].min(axis=1)
    assert span.max() < 1.5 / 48  # one column of the texture: no triangle spans the seam
    assert corners[:, :, 0].max() == pytest.approx(1.0) and corners[:, :, 0].min() == pytest.approx(0.0)


def test_usda_by_extension_and_crate_by_default(tmp_path):
    """Check .usda writes text, .usdc and .usd write crate, and all three read back the same frames."""
    model, sim = _grid_sim(4)
    q, qd = sim.state.particle_q.numpy(), sim.state.particle_qd.numpy()
    for suffix, magic in ((".usda", b"#usda"), (".usdc", b"PXR-USDC"), (".usd", b"PXR-USDC")):
        path = tmp_path / f"c{suffix}"
        with UsdCacheWriter(path, model, fps=24) as w:
            w.write(q, qd)
        assert path.read_bytes()[: len(magic)] == magic
        np.testing.assert_array_equal(CacheReader(path).points(1), q)


def test_z_up_is_stamped_not_rotated(tmp_path):
    """Check a Z-up model writes upAxis Z and its own coordinates (gravity was set along -z)."""
    model, sim = _grid_sim(4, up_axis="Z")
    sim.step_frame()
    path = tmp_path / "z.usdc"
    with UsdCacheWriter(path, model, fps=24) as w:
        w.write(sim.state.particle_q.numpy(), sim.state.particle_qd.numpy())
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    x = CacheReader(path).points(1)
    # One 1/30 s frame of fall along -z (g t^2 / 2 = 5.4 mm for free particles); y untouched beyond the cloth's pull.
    assert -x[:, 2].max() > -1e-6 and -x[:, 2].min() > 0.8 * 0.5 * 9.81 / 30**2
    assert np.allclose(x[:, 1], model.rest_positions[:, 1], atol=1e-3)


def test_file_appears_atomically_and_saves_periodically(tmp_path):
    """Check nothing exists under the final name while frames are written (only the partial file, which is
    saved every save_every frames), and an existing cache is replaced only when the new one is complete."""
    model, sim = _grid_sim(4)
    path = tmp_path / "atomic.usdc"
    path.write_bytes(b"old cache")
    q, qd = sim.state.particle_q.numpy(), sim.state.particle_qd.numpy()
    w = UsdCacheWriter(path, model, fps=24, save_every=2)
    sizes = []
    for _ in range(6):
        w.write(q, qd)
        assert path.read_bytes() == b"old cache"
        sizes.append(partial_path(path).stat().st_size)
    assert sizes[1] < sizes[3] < sizes[5]  # the crate file grows at each periodic save
    w.close()
    assert not partial_path(path).exists()
    assert CacheReader(path).frame_count == 6


def test_interrupted_run_leaves_a_valid_cache(tmp_path):
    """Check Ctrl-C (KeyboardInterrupt) mid-run closes the cache with the frames done and status 'interrupted'."""
    out = tmp_path / "cut.usdc"

    def interrupt_at_three(frame, total, summary):
        if frame == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt) as info:
        run_scene(HANG, SMALL, output=out, frames=50, progress=interrupt_at_three)
    assert info.value.summary["status"] == "interrupted" and info.value.summary["frames"] == 3
    reader = CacheReader(out)
    assert reader.frame_count == 4 and reader.metadata["status"] == "interrupted"
    assert not partial_path(out).exists()


def test_diverged_run_keeps_only_finite_frames(tmp_path):
    """Check a run that blows up stops with a diagnosis and a cache of the good frames, none of them NaN."""
    out = tmp_path / "boom.usdc"
    summary = run_scene(HANG, {**SMALL, "solver.integrator": "explicit_euler", "solver.strain_limit": 0.0,
                               "material.preset": "denim"}, output=out, frames=40)
    assert summary["status"] == "diverged"
    assert "diverged in frame" in summary["message"] and summary["diagnosis"]["suggested_dt"] > 0
    reader = CacheReader(out)
    assert reader.metadata["status"] == "diverged" and reader.frame_count == summary["frames"] + 1
    for f in range(reader.start_frame, reader.end_frame + 1):
        assert np.isfinite(reader.points(f)).all()


def test_npz_cache_round_trip(tmp_path):
    """Check the .npz cache holds positions, velocities, triangles, fps and diagnostics."""
    out = tmp_path / "hang.npz"
    summary = run_scene(HANG, SMALL, output=out, frames=3)
    data = np.load(out)
    assert data["positions"].shape == (4, 81, 3) and data["velocities"].shape == (4, 81, 3)
    assert float(data["fps"]) == 60.0 and data["triangles"].shape == (128, 3)
    assert np.nanmax(data["maxStrain"]) == pytest.approx(summary["max_strain"])


def test_usd_mesh_as_cloth_input(tmp_path):
    """Check a cloth can be read back from a USD cache (face-varying st): same particles, triangles and seams."""
    out = tmp_path / "skirt.usdc"
    run_scene(ROOT / "scenes" / "garment.toml", output=out, frames=1)
    b = cw.ModelBuilder()
    cloth = b.add_cloth_mesh_file(out, prim_path="/World/skirt")
    model = b.finalize("cpu")
    assert model.particle_count == 720 and model.tri_count == 1344
    uv = cloth.topology.corner_uv
    assert (uv[:, :, 0].max(axis=1) - uv[:, :, 0].min(axis=1)).max() < 1.5 / 48
    with pytest.raises(cw.MeshError, match="no Mesh at '/World/nothing'; meshes: /World/skirt"):
        cw.ModelBuilder().add_cloth_mesh_file(out, prim_path="/World/nothing")


def test_vertex_normals_of_a_flat_grid():
    """Check area-weighted normals of a CCW grid in the xy-plane point along +z."""
    b = cw.ModelBuilder()
    c = b.add_cloth_grid(resolution=(3, 3), size=(1.0, 1.0))
    n = vertex_normals(c.topology.positions, c.topology.triangles)
    np.testing.assert_allclose(n, np.tile([0.0, 0.0, 1.0], (16, 1)), atol=1e-7)


# -- what a DCC shows: materials, per-vertex strain, round colliders, the frame rate --------------------------------

def _looks_sim(tmp_path):
    """A denim and a silk cloth over a ball on the ground, 3 frames cached."""
    from cloth_warp.cache import UsdCacheWriter

    b = cw.ModelBuilder()
    flat = cw.quat_from_axis_angle((1, 0, 0), -90.0)
    jeans = b.add_cloth_grid(resolution=(6, 6), size=(0.4, 0.4), position=(-0.2, 0.6, 0.2), rotation=flat, material="denim", name="jeans")
    b.pin(jeans.select("corner:top_left"))  # it swings and stretches
    b.add_cloth_disc(radius=0.15, rings=4, position=(0.0, 0.8, 0.0), rotation=flat, material="silk", name="scarf")
    b.add_sphere((0.0, 0.3, 0.0), 0.25, name="ball")
    b.add_ground(name="ground")
    model = b.finalize("cpu")
    sim = cw.Simulator(model, cw.SolverImplicitEuler(model), fps=30, substeps=2)
    path = tmp_path / "looks.usdc"
    with UsdCacheWriter(path, model, fps=30) as w:
        for _ in range(3):
            w.write(sim.state.particle_q.numpy(), sim.state.particle_qd.numpy())
            sim.step_frame()
    return model, sim, Usd.Stage.Open(str(path))


def _bound_color(prim):
    from pxr import UsdShade

    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    assert material, f"{prim.GetPath()} has no material"
    shader = UsdShade.Shader(material.GetSurfaceOutput().GetConnectedSources()[0][0].source.GetPrim())
    assert shader.GetIdAttr().Get() == "UsdPreviewSurface"
    return tuple(round(c, 6) for c in shader.GetInput("diffuseColor").Get())


def test_cloths_and_colliders_are_bound_to_their_own_materials(tmp_path):
    """Check each cloth is bound to a UsdPreviewSurface material of its fabric's colour (displayColor the same), the
    ball and the ground to theirs, and that cloth, ball and ground do not share a colour."""
    from cloth_warp import looks

    _, _, stage = _looks_sim(tmp_path)
    colors = {}
    for path in ("/World/jeans", "/World/scarf", "/World/colliders/ball", "/World/colliders/ground"):
        prim = stage.GetPrimAtPath(path)
        colors[path] = _bound_color(prim)
        display = tuple(round(c, 6) for c in UsdGeom.Gprim(prim).GetDisplayColorAttr().Get()[0])
        assert display == colors[path]
    assert colors["/World/jeans"] == tuple(round(c, 6) for c in looks.FABRIC_COLORS["denim"])
    assert colors["/World/scarf"] == tuple(round(c, 6) for c in looks.FABRIC_COLORS["silk"])
    assert len(set(colors.values())) == 4
    context = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    assert [e.GetMessage() for e in context.Validate(stage)] == []  # materials and bindings as usd-core expects them


def test_per_vertex_strain_is_a_time_sampled_vertex_primvar(tmp_path):
    """Check the cache carries primvars:strain per vertex and per frame (a DCC keeps vertex primvars it reads per
    frame, where it drops per-frame constants), indexed (at rest most values repeat): each vertex's largest strain
    l / L - 1 over its mesh edges."""
    from cloth_warp.cache import triangle_edges, vertex_strain

    model, _, stage = _looks_sim(tmp_path)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/jeans"))
    primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("strain")
    assert primvar and primvar.GetInterpolation() == UsdGeom.Tokens.vertex
    assert primvar.GetAttr().GetTimeSamples() == [1.0, 2.0, 3.0]
    tris = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    edges = triangle_edges(tris)
    rest = np.asarray(mesh.GetPointsAttr().Get())  # the default value: the rest pose
    x = np.asarray(mesh.GetPointsAttr().Get(3))
    expected = vertex_strain(x, edges, np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1))
    np.testing.assert_allclose(np.asarray(primvar.ComputeFlattened(3)), expected, atol=1e-6)
    assert np.abs(expected).max() > 1e-4  # the cloth did deform
    # a hand check of the definition on one stretched edge
    np.testing.assert_allclose(vertex_strain(np.array([[0, 0, 0], [1.1, 0, 0.0]]), np.array([[0, 1]]), np.array([1.0])), [0.1, 0.1],
                               atol=1e-6)


def test_round_colliders_are_written_as_fine_meshes(tmp_path):
    """Check a ball is written as a mesh whose vertices lie on the sphere and whose facets stay within 0.5 mm of it
    (a DCC's own 10-segment tessellation of an implicit sphere sits 12 mm inside a 25 cm ball), its exact radius kept in
    the prim's customData."""
    from cloth_warp.cache import ROUND_SAGITTA

    _, _, stage = _looks_sim(tmp_path)
    prim = stage.GetPrimAtPath("/World/colliders/ball")
    assert prim.IsA(UsdGeom.Mesh)
    assert prim.GetCustomDataByKey("clothWarp:collider")["radius"] == pytest.approx(0.25)
    mesh = UsdGeom.Mesh(prim)
    v = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
    tris = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 0.25, atol=1e-6)
    centroid = np.linalg.norm(v[tris].mean(axis=1), axis=1)
    assert 0.25 - centroid.min() <= ROUND_SAGITTA


@pytest.mark.parametrize("shape,radius,height", [("sphere", 0.05, 0.0), ("capsule", 0.1, 0.3), ("capsule", 0.6, 0.2),
                                                   ("capsule", 0.02, 0.1), ("cylinder", 0.15, 0.2), ("cylinder", 0.9, 0.05)])
def test_round_collider_meshes_stay_within_the_sagitta(shape, radius, height):
    """Check a round collider's written mesh (axis Z, centred): closed, its vertices on the exact surface (a capsule's
    within `radius` of its axis segment of length `height`, the caps excluded as UsdGeom.Capsule's height is; a
    cylinder's on its side circle or its caps' centres at +-height/2), its extent the shape's, and no point of any
    facet (sampled on a barycentric grid: a facet's deepest point is inside it, not at its centroid) more than
    ROUND_SAGITTA inside the round surface (trimesh's capsule with a sphere's segment count sat 0.6 mm in)."""
    import trimesh

    from cloth_warp.cache import ROUND_SAGITTA, round_collider_mesh

    v, tris = round_collider_mesh(types.SimpleNamespace(shape=shape, radius=radius, height=height))
    v = v.astype(np.float64)
    assert trimesh.Trimesh(v, tris, process=True).is_watertight
    k = 12
    weights = np.array([(a / k, b / k, 1.0 - (a + b) / k) for a in range(k + 1) for b in range(k + 1 - a)])
    samples = np.einsum("sk,tkd->tsd", weights, v[tris]).reshape(-1, 3)
    axis = np.array([0.0, 0.0, 1.0])
    if shape == "cylinder":
        radial = np.linalg.norm(v[:, :2], axis=1)
        np.testing.assert_allclose(np.abs(v[:, 2]), height / 2, atol=1e-6)
        assert np.all((np.abs(radial - radius) < 1e-6) | (radial < 1e-6))
        side = samples[np.abs(samples[:, 2]) < height / 2 - 1e-6]  # (the caps are flat: exact)
        depth = radius - np.linalg.norm(side[:, :2], axis=1)
    else:
        half = height / 2

        def distance(p):  # to the axis segment (a sphere's: its centre)
            return np.linalg.norm(p - np.clip(p[:, 2:3], -half, half) * axis, axis=1)

        np.testing.assert_allclose(distance(v), radius, atol=1e-6)
        np.testing.assert_allclose([v[:, 2].min(), v[:, 2].max()], [-half - radius, half + radius], atol=1e-6)
        depth = radius - distance(samples)
    assert 0.0 < depth.max() <= ROUND_SAGITTA


def test_cusick_disc_has_uvs(tmp_path):
    """Check a disc cloth gets texture coordinates (projected from its plane, in [0, 1]) in the cache."""
    _, _, stage = _looks_sim(tmp_path)
    st = UsdGeom.PrimvarsAPI(UsdGeom.Mesh(stage.GetPrimAtPath("/World/scarf"))).GetPrimvar("st")
    assert st and st.GetInterpolation() == UsdGeom.Tokens.faceVarying
    uv = np.asarray(st.ComputeFlattened())
    assert uv.min() >= 0.0 and uv.max() <= 1.0 and uv.max() - uv.min() > 0.9


@pytest.mark.parametrize("fps,expected", [(60.0, (60, 1.0)), (24.0, (24, 1.0)), (29.97, (30, 30 / 29.97)), (23.976, (24, 24 / 23.976))])
def test_blender_import_helper_sets_the_cache_frame_rate(tmp_path, fps, expected):
    """Check the Blender import helper turns a cache's rate into Blender's integer fps and fps_base (Blender plays
    fps / fps_base) and reads the rate and frame range from the stage."""
    from cloth_warp.blender_import import blender_frame_rate, cache_timing

    whole, base = blender_frame_rate(fps)
    assert whole == expected[0] and base == pytest.approx(expected[1]) and whole / base == pytest.approx(fps)
    model, sim = _grid_sim()
    path = tmp_path / "rate.usdc"
    with UsdCacheWriter(path, model, fps=fps, start_frame=1001) as w:
        for _ in range(3):
            w.write(sim.state.particle_q.numpy(), sim.state.particle_qd.numpy())
    assert cache_timing(path) == (pytest.approx(fps), 1001.0, 1003.0)
    with pytest.raises(ValueError):
        blender_frame_rate(0.0)
