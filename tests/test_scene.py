"""Scene files: validation names the key path and what is allowed; shipped scenes run and behave physically."""

import pathlib
import shutil

import numpy as np
import pytest
from analytic import elastic_catenary_sag

from cloth_warp import materials
from cloth_warp.cache import CacheReader
from cloth_warp.runner import run_scene, shipped_scenes
from cloth_warp.scene import (COLLIDER_CONTACTS, CONTACT_FRICTION, INTEGRATORS, SEWN_POINTS, SceneError, load_scene, parse_scene,
                              schema_markdown)
from cloth_warp.solvers.implicit import COLLIDER_CONTACTS as IMPLICIT_COLLIDER_CONTACTS
from cloth_warp.solvers.implicit import CONTACT_FRICTION as IMPLICIT_CONTACT_FRICTION
from cloth_warp.solvers.implicit import SEWN_POINTS as IMPLICIT_SEWN_POINTS

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = sorted((ROOT / "scenes").glob("*.toml"))
HANG = ROOT / "scenes" / "hanging_cloth.toml"


@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.stem)
def test_shipped_scenes_validate(path):
    """Check every shipped scene passes validation and has a description for `cloth-warp scenes`."""
    scene = load_scene(path)
    assert scene.get("scene.description")


def test_at_least_the_six_shipped_scenes():
    """Check the scenes the product promises are shipped."""
    assert {"hanging_cloth", "flag", "curtain", "cantilever", "catenary", "garment"} <= set(shipped_scenes())


def test_schema_names_match_the_code():
    """Check the schema's allowed integrators and presets are exactly the code's."""
    from cloth_warp.solvers import SOLVERS

    assert set(INTEGRATORS) == set(SOLVERS)
    assert COLLIDER_CONTACTS == IMPLICIT_COLLIDER_CONTACTS
    assert CONTACT_FRICTION == IMPLICIT_CONTACT_FRICTION
    assert SEWN_POINTS == IMPLICIT_SEWN_POINTS
    from cloth_warp.mannequin import MOTIONS
    from cloth_warp.scene import MANNEQUIN_MOTIONS

    assert MANNEQUIN_MOTIONS == MOTIONS
    assert set(load_scene(HANG).resolved()) >= {"cloth", "material", "solver", "output", "forces"}
    assert "material.preset" in schema_markdown() and all(p in schema_markdown() for p in materials.PRESETS)


def test_scene_reference_page_is_current():
    """Check docs/scenes.md is what the schema generates (regenerate it with the command in its header)."""
    assert (ROOT / "docs" / "scenes.md").read_text() == schema_markdown()


@pytest.mark.parametrize(
    "overrides, message",
    [
        # unknown keys, with a did-you-mean and the allowed keys
        ({"cloth.gird": 1}, "unknown key 'cloth.gird' (did you mean 'grid'?); allowed here: name, grid, disc, mesh"),
        ({"solver.substep": 2}, "(did you mean 'substeps'?)"),
        # wrong types
        ({"material.areal_density": "heavy"}, "material.areal_density: expected a finite number [kg/m^2], got 'heavy'"),
        ({"solver.substeps": 2.5}, "solver.substeps: expected an integer, got 2.5"),
        ({"solver.adaptive": "yes"}, "solver.adaptive: expected true or false"),
        ({"cloth.grid.resolution": [4]}, "cloth.grid.resolution: expected 2 integers"),
        ({"forces.wind": [1, 0]}, "forces.wind: expected 3 finite numbers [m/s]"),
        ({"pins": {"select": "corners"}}, "pins: expected an array of tables"),
        # out-of-range values
        ({"solver.substeps": 0}, "solver.substeps: must be >= 1, got 0"),
        ({"material.stretch_stiffness": 0.0}, "material.stretch_stiffness: must be >= 0.001 N/m, got 0.0 (allowed: [0.001, 1e9] N/m)"),
        ({"output.fps": -24}, "output.fps: must be >= 0.01 1/s"),
        ({"cloth.grid.size": [1.0, 0.0]}, "cloth.grid.size[1]: must be >= 1e-5 m"),
        # values outside a fixed set
        ({"solver.integrator": "verlet"}, "solver.integrator: 'verlet' is not allowed; allowed: implicit_euler"),
        ({"material.preset": "velvet"}, "material.preset: 'velvet' is not allowed; allowed: cotton, denim, silk"),
        ({"material.preset": "coton"}, "(did you mean 'cotton'?)"),
        ({"forces.up_axis": "X"}, "forces.up_axis: 'X' is not allowed; allowed: Y, Z"),
        ({"output.path": "out/a.abc"}, "output.path: 'out/a.abc' has an unknown extension; allowed: .usdc, .usda, .usd, .npz"),
        # missing files and inconsistent keys
        ({"cloth.mesh": "missing.obj"}, "give one of cloth.grid, cloth.disc, cloth.mesh, cloth.pattern or cloth.panels, not grid and mesh"),
        ({"pins[0].indices": [0]}, "pins[0]: give exactly one of select, indices, box (got select, indices)"),
        # colliders: required and misplaced geometry, friction order, shapes
        ({"colliders": [{"type": "sphere"}]}, "colliders[0].radius: a sphere collider needs it"),
        ({"colliders": [{"type": "box", "radius": 1.0, "size": [1, 1, 1]}]},
         "colliders[0].radius: not used by a box collider (only by sphere, capsule, cylinder)"),
        ({"colliders": [{"type": "torus"}]}, "colliders[0].type: 'torus' is not allowed; allowed: plane, sphere"),
        ({"colliders": [{"type": "plane", "static_friction": 0.2, "kinetic_friction": 0.4}]},
         "colliders[0].kinetic_friction: 0.4 exceeds the static coefficient 0.2"),
        ({"colliders": [{"type": "mesh", "mesh": "nowhere.obj"}]}, "colliders[0].mesh: file not found"),
        ({"colliders": [{"type": "plane", "axis": [0, 0, 0]}]}, "colliders[0].axis: must not be the zero vector"),
        ({"colliders": [{"type": "sphere", "radius": -1.0}]}, "colliders[0].radius: must be >= 1e-5 m"),
        ({"colliders": [{"type": "plane"}, {"type": "plane", "name": "plane0"}]}, "colliders[1].name: 'plane0' is used"),
        ({"collision.friction": -0.1}, "collision.friction: must be >= 0"),
        ({"cloth.disc": {"rings": 4}}, "cloth.disc.radius: a disc cloth needs its radius"),
        ({"cloth.disc": {"radius": 0.1}}, "cloth: give one of cloth.grid, cloth.disc, cloth.mesh, cloth.pattern or cloth.panels, not grid and disc"),
        ({"colliders": [{"type": "mannequin", "radius": 0.2}]}, "colliders[0].radius: not used by a mannequin collider"),
        ({"attachments": [{"select": "edge:top", "collider": "body"}], "colliders": [{"type": "sphere", "radius": 0.1, "name": "body"}]},
         "attachments[0].collider: 'body' is not a mesh or mannequin collider of the scene; those: none"),
        ({"attachments": [{"collider": "body"}], "colliders": [{"type": "mannequin", "name": "body"}]},
         "attachments[0]: give exactly one of select, indices, box (got none)"),
        ({"colliders": [{"type": "mannequin", "stature": 3.0}]}, "colliders[0].stature: must be <= 2.5"),
        ({"colliders": [{"type": "mannequin", "motion": "dance"}]}, "colliders[0].motion: 'dance' is not allowed; allowed: still, walk"),
        ({"measure.cusick": {"disc_radius": 0.15}}, "measure.cusick.pedestal_radius: the pedestal radius [m] is needed"),
        ({"measure.cusick": {"pedestal_radius": 0.09}}, "measure.cusick.disc_radius: give the specimen radius"),
        ({"measure.cusick": {"pedestal_radius": 0.2, "disc_radius": 0.15}}, "must exceed the pedestal radius 0.2 m"),
        ({"solver.self_contacts": "solve", "solver.integrator": "symplectic_euler"},
         'solver.self_contacts: "solve" needs solver.integrator = "implicit_euler" with solver.linear_solver = "cg"'),
        ({"solver.collider_contacts": "solve", "solver.linear_solver": "jacobi"}, 'solver.collider_contacts: "solve" needs'),
    ],
)
def test_scene_errors_name_the_key(overrides, message):
    """Check each class of bad value raises a SceneError naming the key path and what is allowed."""
    with pytest.raises(SceneError) as info:
        load_scene(HANG, overrides)
    assert message in str(info.value)


def test_missing_mesh_file_is_named(tmp_path):
    """Check a mesh path that does not exist names the key and the resolved path."""
    with pytest.raises(SceneError, match=r"cloth.mesh: file not found: .*nowhere.obj \(paths are relative to the scene file\)"):
        parse_scene('[cloth]\nmesh = "nowhere.obj"\n', tmp_path / "s.toml")


def test_keyframes_must_increase():
    """Check handle keyframes out of order are rejected with their path."""
    text = '[[handles]]\nselect = "corners"\nkeyframes = [{ time = 1.0 }, { time = 0.5 }]\n'
    with pytest.raises(SceneError, match=r"handles\[0\].keyframes: times must increase"):
        parse_scene(text)


def test_toml_syntax_error_names_line_and_column(tmp_path):
    """Check a TOML syntax error reports its line and column."""
    bad = tmp_path / "bad.toml"
    bad.write_text("[cloth]\ngrid = { resolution = [8, 8] \n")
    with pytest.raises(SceneError, match=r"TOML syntax error: .*line 2, column \d+"):
        load_scene(bad)


def test_missing_scene_file():
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene(ROOT / "scenes" / "nope.toml")


def test_set_overrides_nested_and_indexed_keys():
    """Check --set style overrides reach tables, new keys and entries of arrays of tables."""
    scene = load_scene(HANG, {"solver.substeps": 4, "forces.wind": [1.0, 0.0, 0.0], "pins[1].stiffness": 50.0,
                              "material.preset": "silk"})
    assert scene.get("solver.substeps") == 4
    assert scene.get("forces.wind") == [1.0, 0.0, 0.0]
    assert scene.data["pins"][1]["stiffness"] == 50.0
    assert scene.get("material.preset") == "silk"
    with pytest.raises(SceneError, match=r"pins\[5\] does not exist"):
        load_scene(HANG, {"pins[5].stiffness": 1.0})


def test_paths_resolve_relative_to_the_scene_file(tmp_path):
    """Check mesh and output paths in a scene resolve against the scene's folder, not the working directory."""
    (tmp_path / "assets").mkdir()
    shutil.copy(ROOT / "scenes" / "meshes" / "skirt.obj", tmp_path / "assets" / "skirt.obj")
    scene_path = tmp_path / "my.toml"
    scene_path.write_text('[cloth]\nmesh = "assets/skirt.obj"\n[[pins]]\nbox = { min = [-1, 0.999, -1], max = [1, 1.001, 1] }\n'
                          '[output]\npath = "results/my.npz"\nframes = 1\n')
    summary = run_scene(scene_path)
    assert summary["status"] == "complete"
    assert (tmp_path / "results" / "my.npz").exists()
    assert summary["particles"] == 720  # 735 OBJ vertices, the 15 seam duplicates welded


# -- the shipped scenes, each for a few frames (or to rest) with a physical assertion --------------------------

def _positions(path):
    r = CacheReader(path)
    return r, np.stack([r.points(f) for f in range(r.start_frame, r.end_frame + 1)])


def test_hanging_cloth_scene(tmp_path):
    """Check the hanging cloth falls freely at first with its two corners fixed, within the strain limit."""
    out = tmp_path / "hang.usdc"
    summary = run_scene(HANG, {"cloth.grid.resolution": [16, 16]}, output=out, frames=6)
    assert summary["status"] == "complete" and summary["frames"] == 6
    _, x = _positions(out)
    assert x.shape == (7, 17 * 17, 3)
    corners = [16 * 17, 16 * 17 + 16]  # grid row 16 = the pinned "top" corners
    np.testing.assert_array_equal(x[-1, corners], x[0, corners])
    # The free far edge falls nearly freely at first: at least 80 % of g t^2 / 2 = 4.9 cm after 0.1 s.
    assert x[0, :, 1].min() - x[-1, :, 1].min() > 0.8 * 0.5 * 9.81 * 0.1**2
    assert summary["max_strain"] <= 0.101


def test_cantilever_scene(tmp_path):
    """Check the cantilever keeps its clamp and its tip droops."""
    out = tmp_path / "c.npz"
    summary = run_scene(ROOT / "scenes" / "cantilever.toml", output=out, frames=10)
    assert summary["status"] == "complete"
    x = np.load(out)["positions"]
    assert x[-1, :, 1].min() < -0.005  # the tip has dropped by more than 5 mm (rest: y = 0)
    clamped = x[0, :, 0] <= 1e-6
    np.testing.assert_array_equal(x[-1, clamped], x[0, clamped])


@pytest.mark.slow
def test_catenary_scene_settles_to_the_elastic_catenary(tmp_path):
    """Check the strip, once its animated ends have closed to a 1.4 m span and it has settled, sags like the
    elastic catenary (Irvine) within 0.5 % (measured: 0.6404 m vs 0.6404 m)."""
    out = tmp_path / "cat.usdc"
    summary = run_scene(ROOT / "scenes" / "catenary.toml", output=out, frames=180)
    assert summary["status"] == "complete"
    r = CacheReader(out)
    x = r.points(r.end_frame)
    cotton, width = materials.preset("cotton"), 0.05
    ref = elastic_catenary_sag(1.4, 2.0, cotton.areal_density * width * 9.81, cotton.stretch_stiffness * width)
    assert 1.5 - x[:, 1].min() == pytest.approx(ref, rel=5e-3)
    assert x[:, 0].min() == pytest.approx(-0.7, abs=1e-6) and x[:, 0].max() == pytest.approx(0.7, abs=1e-6)


def test_flag_scene_streams_downwind(tmp_path):
    """Check the flag's pole edge stays put while the wind carries the free edge out of its plane (+z); without
    wind the flag stays in its vertical plane (gravity acts in the plane, held by the in-plane stiffness)."""
    frames = 30
    out_wind, out_calm = tmp_path / "flag.npz", tmp_path / "calm.npz"
    low = {"cloth.grid.resolution": [18, 12]}
    run_scene(ROOT / "scenes" / "flag.toml", low, output=out_wind, frames=frames)
    run_scene(ROOT / "scenes" / "flag.toml", {**low, "forces.wind": [0.0, 0.0, 0.0]}, output=out_calm, frames=frames)
    wind, calm = np.load(out_wind)["positions"], np.load(out_calm)["positions"]
    pole = wind[0, :, 0] == 0.0
    np.testing.assert_array_equal(wind[-1, pole], wind[0, pole])
    free = wind[0, :, 0] > 1.19
    assert wind[-1, free, 2].mean() > 0.1  # 0.5 s of 7 m/s wind with a 1.5 m/s cross component
    assert np.abs(calm[-1, :, 2]).max() < 1e-6


def test_curtain_scene_rings_follow_their_keyframes(tmp_path):
    """Check the curtain's sliding rings are exactly where their keyframes put them and the cloth between
    them follows (the bottom hem moves right too)."""
    out = tmp_path / "curtain.npz"
    summary = run_scene(ROOT / "scenes" / "curtain.toml", {"cloth.grid.resolution": [16, 20]}, output=out, frames=30)
    assert summary["status"] == "complete" and summary["max_strain"] <= 0.101
    x = np.load(out)["positions"]
    t = 30 / 60.0
    s = (t - 0.3) / 2.0  # fraction of the slide done at 0.5 s
    for k in range(8):
        ring = np.flatnonzero((np.abs(x[0, :, 0] - (-0.8 + 0.2 * k)) < 0.011) & (x[0, :, 1] > 2.19))
        assert len(ring) == 1
        np.testing.assert_allclose(x[-1, ring, 0], -0.8 + 0.2 * k + s * 1.2 * (8 - k) / 8, atol=1e-5)
    hem = x[0, :, 1] < 0.21
    assert x[-1, hem, 0].mean() > x[0, hem, 0].mean() + 0.005


def test_garment_scene_drapes(tmp_path):
    """Check the skirt (OBJ with a UV seam) keeps its waist, its flared hem falls inward, and the seam stays
    closed in the cache (face-varying UVs without wrap-around)."""
    out = tmp_path / "skirt.usdc"
    summary = run_scene(ROOT / "scenes" / "garment.toml", output=out, frames=12)
    assert summary["status"] == "complete"
    r, x = _positions(out)
    waist = x[0, :, 1] > 0.999
    np.testing.assert_array_equal(x[-1, waist], x[0, waist])
    hem = x[0, :, 1] < 0.451
    radius = np.hypot(x[:, hem, 0], x[:, hem, 2]).mean(axis=1)
    assert radius[-1] < radius[0] - 0.005  # 0.2 s in, the hem has swung inward by more than 5 mm
    assert summary["max_strain"] <= 0.101


@pytest.mark.slow
def test_skirt_walk_scene_dresses_the_mannequin_and_walks(tmp_path):
    """Check the shipped skirt (a GarmentCode pattern, coarser here) is sewn onto the walking mannequin: seams closed
    to under a millimetre, its waistband rides with the body, no garment edge crosses the body and no body edge crosses
    the garment in any frame, strain within the limit."""
    import cloth_warp as cw
    from cloth_warp.patterns import Wrap
    from intersections import crossing_pairs
    from pxr import Usd, UsdGeom

    out = tmp_path / "skirt.usdc"
    scene = ROOT / "scenes" / "skirt_walk.toml"
    summary = run_scene(scene, {"cloth.edge_length": 0.04}, output=out, frames=24)
    assert summary["status"] == "complete" and summary["max_strain"] <= 0.101
    seams = cw.ModelBuilder().add_cloth_pattern(ROOT / "scenes" / "patterns" / "skirt_specification.json", edge_length=0.04,
                                                wraps=[Wrap(("front", "back"), (0.0, 0.0, 0.0))]).seams
    stage = Usd.Stage.Open(str(out))
    body = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders/body"))
    body_tris = np.asarray(body.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    cloth_tris = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/World/skirt")).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    r, x = _positions(out)
    waist = x[0, :, 1] > 0.995
    for f in range(len(x)):
        assert np.linalg.norm(x[f][seams[:, 0]] - x[f][seams[:, 1]], axis=1).max() < 1e-3
        b = np.asarray(body.GetPointsAttr().Get(r.start_frame + f), float)
        assert not crossing_pairs(x[f], cloth_tris, b, body_tris), f"frame {f}"
    assert np.ptp(x[:, waist, 1].mean(axis=1)) > 1e-3  # the walk's bob carries the waistband


def _write_dcc_body(path, seconds: float, fps: float = 30.0, start: int = 1001):
    """The mannequin's walk written as a DCC exports a character's point cache: z up, centimetres, time codes from
    `start` at `fps`, the mesh under a translated transform. Returns the sample times [s] and the y-up vertices [m]."""
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    from cloth_warp.mannequin import Mannequin

    body = Mannequin(1.75)
    times, cache = body.point_cache("walk", seconds, fps)
    stage = Usd.Stage.Open(Sdf.Layer.CreateNew(str(path)))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetStartTimeCode(start)
    stage.SetEndTimeCode(start + len(times) - 1)
    rig = UsdGeom.Xform.Define(stage, "/Character")
    shift = np.array([12.0, -7.0, 3.0])  # cm, z up
    rig.AddTranslateOp().Set(Gf.Vec3d(*shift))
    stage.SetDefaultPrim(rig.GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, "/Character/skin")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(body.triangles), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(body.triangles.reshape(-1), np.int32)))
    points = mesh.CreatePointsAttr()
    for k, x in enumerate(cache):
        z_up = np.stack([x[:, 0], -x[:, 2], x[:, 1]], axis=1) * 100.0 - shift
        points.Set(Vt.Vec3fArray.FromNumpy(z_up.astype(np.float32)), start + k)
    stage.GetRootLayer().Save()
    return times, cache


@pytest.mark.slow
def test_a_garment_is_sewn_onto_a_users_body_from_a_dcc_point_cache(tmp_path):
    """Check a skirt (the shipped pattern, coarser here) sewn onto a body read from a USD point cache written as a DCC
    writes one (z up, centimetres, time codes from 1001 at 30 fps, under a translated transform; placed y-up by the
    collider's rotation) with its waistband attached: the body in the run's cache is the walk at each frame's time
    (linear between the 30 fps samples, to 0.1 mm), the seams are closed, the waistband stays on the body to 1e-4 m
    and rides with it, and no edge of the skirt crosses the body or the body the skirt in any frame."""
    from intersections import crossing_pairs
    from pxr import Usd, UsdGeom

    frames = 12
    times, walk = _write_dcc_body(tmp_path / "body.usdc", seconds=(frames + 2) / 60.0)
    pattern = (ROOT / "scenes" / "patterns" / "skirt_specification.json").as_posix()
    (tmp_path / "skirt.toml").write_text(
        f'[cloth]\npattern = "{pattern}"\nedge_length = 0.04\nname = "skirt"\n'
        '[[cloth.wraps]]\npanels = ["front", "back"]\n'
        '[dressing]\nseconds = 1.0\nsettle = 0.5\n'
        '[[attachments]]\nbox = { min = [-0.4, 0.995, -0.4], max = [0.4, 1.02, 0.4] }\ncollider = "body"\n'
        '[[colliders]]\ntype = "mesh"\nmesh = "body.usdc"\ndeforming = true\nname = "body"\nfriction = 0.5\n'
        'rotation = { axis = [1.0, 0.0, 0.0], angle = -90.0 }\n'
        '[collision]\nself_collision = true\n'
        '[solver]\nintegrator = "implicit_euler"\nsubsteps = 2\ncollider_contacts = "solve"\ntolerance = 1e-4\n'
        f'[output]\nframes = {frames}\nfps = 60\n')
    out = tmp_path / "skirt.usdc"
    summary = run_scene(tmp_path / "skirt.toml", output=out)
    assert summary["status"] == "complete" and summary["max_strain"] <= 0.101
    assert summary["seam_gap"] < 1e-3 and summary["attachment_gap"] < 1e-4
    stage = Usd.Stage.Open(str(out))
    body = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders/body"))
    body_tris = np.asarray(body.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    skirt_tris = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/World/skirt")).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    r, x = _positions(out)

    def body_at(tc):  # world space: the cache writes the collider's local points under its pose
        m = np.asarray(UsdGeom.Xformable(body).ComputeLocalToWorldTransform(tc), float)
        return np.asarray(body.GetPointsAttr().Get(tc), float) @ m[:3, :3] + m[3, :3]

    b0 = body_at(r.start_frame)  # (the reader reorders vertices: match them)
    match = np.concatenate([np.linalg.norm(b0[i:i + 512, None] - walk[0][None], axis=2).argmin(1) for i in range(0, len(b0), 512)])
    assert len(np.unique(match)) == len(b0) == len(walk[0])
    for f in range(len(x)):
        b = body_at(r.start_frame + f)
        k, w = divmod(f, 2)  # (60 fps frames, 30 fps samples)
        np.testing.assert_allclose(b, ((1.0 - 0.5 * w) * walk[k] + 0.5 * w * walk[k + 1])[match], atol=1e-4)
        assert not crossing_pairs(x[f], skirt_tris, b, body_tris), f"frame {f}"
    waist = x[0, :, 1] > 0.995
    assert waist.sum() > 10 and np.ptp(x[:, waist, 1].mean(axis=1)) > 1e-4  # the walk's bob carries the waistband


@pytest.mark.slow
def test_panel_skirt_scene_sews_its_inline_pattern_onto_the_walking_mannequin(tmp_path):
    """Check the shipped skirt whose pattern is written in the scene ([[cloth.panels]], [[cloth.stitches]]; coarser
    here) is sewn onto the walking mannequin: seams closed, nothing of it inside the body or crossing it in any frame,
    its waistband riding with the body."""
    from intersections import crossing_pairs
    from pxr import Usd, UsdGeom

    out = tmp_path / "panel_skirt.usdc"
    scene = ROOT / "scenes" / "panel_skirt.toml"
    summary = run_scene(scene, {"cloth.edge_length": 0.04}, output=out, frames=12)
    assert summary["status"] == "complete" and summary["max_strain"] <= 0.101
    assert summary["seam_gap"] < 1e-3
    stage = Usd.Stage.Open(str(out))
    body = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders/body"))
    body_tris = np.asarray(body.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    cloth_tris = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/World/skirt")).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    r, x = _positions(out)
    for f in range(len(x)):
        b = np.asarray(body.GetPointsAttr().Get(r.start_frame + f), float)
        assert not crossing_pairs(x[f], cloth_tris, b, body_tris), f"frame {f}"
    waist = x[0, :, 1] > 0.99
    assert waist.sum() > 10 and np.ptp(x[:, waist, 1].mean(axis=1)) > 1e-4  # the walk's bob carries the waistband


@pytest.mark.slow
def test_dress_hangs_from_its_shoulder_straps_while_walking(tmp_path):
    """Check the shipped strapped dress (coarser here), held by nothing but contact with the shoulders: the strap seams
    lie on top of the shoulders (between the neck and the arm) and stay within a centimetre of their first height while
    the body walks, every sewn point stays one point (welded: under 0.1 mm in every frame, where seam springs alone
    opened 1-3 mm under the dress's weight), no edge of the dress crosses the body or the body the dress, and the dress
    does not cross itself (every 4th frame)."""
    import cloth_warp as cw
    from cloth_warp.patterns import Wrap
    from intersections import crossing_pairs, intersecting_pairs
    from pxr import Usd, UsdGeom

    out = tmp_path / "dress.usdc"
    summary = run_scene(ROOT / "scenes" / "dress_walk.toml", {"cloth.edge_length": 0.03, "dressing.settle": 0.5},
                        output=out, frames=24)
    assert summary["status"] == "complete" and summary["max_strain"] <= 0.101
    pattern = cw.ModelBuilder().add_cloth_pattern(ROOT / "scenes" / "patterns" / "dress_specification.json", edge_length=0.03,
                                                  wraps=[Wrap(("front", "back"), (0.0, 0.0, 0.0))])
    seams = pattern.seams
    stage = Usd.Stage.Open(str(out))
    body = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders/body"))
    tris = {k: np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath(p)).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
            for k, p in (("body", "/World/colliders/body"), ("dress", "/World/dress"))}
    r, x = _positions(out)
    straps = np.unique(seams[x[0][seams[:, 0], 1] > 1.35])  # the strap seams' particles (the side seams end lower)
    assert len(straps) >= 8
    assert np.all((np.abs(x[0][straps, 0]) > 0.07) & (np.abs(x[0][straps, 0]) < 0.2))  # on the shoulders
    assert x[0][straps, 1].min() > 1.4
    for f in range(len(x)):
        assert np.linalg.norm(x[f][seams[:, 0]] - x[f][seams[:, 1]], axis=1).max() < 1e-4
        assert np.abs(x[f][straps, 1] - x[0][straps, 1]).max() < 0.01, f"frame {f}: a strap slid"
        b = np.asarray(body.GetPointsAttr().Get(r.start_frame + f), float)
        assert not crossing_pairs(x[f], tris["dress"], b, tris["body"]), f"frame {f}"
        if f % 4 == 0:  # the self-intersection check costs 1.6 s a frame here
            assert not intersecting_pairs(x[f], tris["dress"]), f"frame {f}"


@pytest.mark.slow
def test_tshirt_is_sewn_onto_the_body_and_stays_sewn_while_walking(tmp_path):
    """Check the shipped T-shirt (as shipped: its own 2.5 cm edges, its 0.5 s settle): its four panels, placed open round the torso and the arms, are sewn in
    the dressing and stay sewn (every sewn point one point in every frame: the weld), the shoulder seams stay on the
    shoulders (between the neck and the arm, above the shoulder's ridge, 1.44-1.48 m) while the body walks, the sleeves
    stay round the arms (each cuff's centre within 4 cm of the upper arm's axis), no edge of the shirt crosses the body
    or the body the shirt in any frame, the shirt does not cross itself (every 4th frame) and the strain limiter held
    in every frame."""
    from cloth_warp.mannequin import Mannequin
    from cloth_warp.patterns import mesh_pattern, read_garmentcode
    from intersections import crossing_pairs, intersecting_pairs
    from pxr import Usd, UsdGeom

    out = tmp_path / "tshirt.usdc"
    scene = ROOT / "scenes" / "tshirt_walk.toml"
    summary = run_scene(scene, output=out, frames=16)
    assert summary["status"] == "complete" and summary["strain_limit"]["missed_frames"] == 0
    assert summary["seam_gap"] < 1e-4
    r, x = _positions(out)
    gaps = r.diagnostics()["seamGap"][1]
    assert len(gaps) == len(x) - 1 and max(gaps) < 1e-4
    # (the panels are placed apart: the mesh's vertices are the particles, in order)
    mesh = mesh_pattern(read_garmentcode(ROOT / "scenes" / "patterns" / "tshirt_specification.json"), 0.025)
    shoulders = np.unique(np.concatenate([mesh.edge_vertices[("front", 3)], mesh.edge_vertices[("front", 5)]]))
    cuffs = {side: mesh.edge_vertices[(f"{side}_sleeve", 0)] for side in ("left", "right")}
    body_model = Mannequin(1.75)
    stage = Usd.Stage.Open(str(out))
    body = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders/body"))
    tris = {k: np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath(p)).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
            for k, p in (("body", "/World/colliders/body"), ("tshirt", "/World/tshirt"))}
    for f in range(len(x)):
        on_top = (np.abs(x[f][shoulders, 0]) > 0.05) & (np.abs(x[f][shoulders, 0]) < 0.23) & (x[f][shoulders, 1] > 1.4)
        assert on_top.all(), f"frame {f}: a shoulder seam left the shoulders"
        for side, cuff in cuffs.items():
            arm = body_model.segments[body_model.index[f"{side}_upper_arm"]]
            turn, shift = body_model.segment_transforms("walk", f / 60.0)[body_model.index[arm.name]]
            joint, elbow = (turn @ (np.asarray(p) * 1.75) + shift for p in (arm.joint, arm.tip))
            centre = x[f][cuff].mean(axis=0)
            axis = (elbow - joint) / np.linalg.norm(elbow - joint)
            off = centre - joint
            assert np.linalg.norm(off - (off @ axis) * axis) < 0.04, f"frame {f}: the {side} sleeve left the arm"
        b = np.asarray(body.GetPointsAttr().Get(r.start_frame + f), float)
        assert not crossing_pairs(x[f], tris["tshirt"], b, tris["body"]), f"frame {f}"
        if f % 4 == 0:
            assert not intersecting_pairs(x[f], tris["tshirt"]), f"frame {f}"


@pytest.mark.slow
def test_layered_outfit_keeps_its_layers_apart_and_in_order(tmp_path):
    """Check the shipped layered outfit (a silk overskirt over the cotton skirt, coarser here): in every frame no edge of
    one garment crosses the other or the body, neither garment crosses itself, every overskirt point within 1.5 cm of
    the skirt lies on its outer side, both waistbands ride with the body and both garments' seams stay closed."""
    import cloth_warp as cw
    from cloth_warp.patterns import Wrap
    from intersections import closest_points, crossing_pairs, intersecting_pairs
    from pxr import Usd, UsdGeom

    out = tmp_path / "layered.usdc"
    summary = run_scene(ROOT / "scenes" / "layered_walk.toml", {"cloth.edge_length": 0.04, "garments[0].edge_length": 0.04,
                                                                "dressing.settle": 0.5},
                        output=out, frames=24)
    assert summary["status"] == "complete" and summary["max_strain"] <= 0.101
    stage = Usd.Stage.Open(str(out))
    meshes = {name: UsdGeom.Mesh(stage.GetPrimAtPath(path)) for name, path in
              (("skirt", "/World/skirt"), ("overskirt", "/World/overskirt"), ("body", "/World/colliders/body"))}
    tris = {k: np.asarray(m.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3) for k, m in meshes.items()}
    seams = {k: cw.ModelBuilder().add_cloth_pattern(ROOT / "scenes" / "patterns" / f"{k}_specification.json", edge_length=0.04,
                                                     wraps=[Wrap(("front", "back"), (0.0, 0.0, 0.0))]).seams for k in ("skirt", "overskirt")}
    first = None
    for f in range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1):
        x = {k: np.asarray(m.GetPointsAttr().Get(f), float) for k, m in meshes.items()}
        for a, b in (("skirt", "overskirt"), ("skirt", "body"), ("overskirt", "body")):
            assert not crossing_pairs(x[a], tris[a], x[b], tris[b]), f"{a} / {b}, frame {f}"
        for k in ("skirt", "overskirt"):
            assert not intersecting_pairs(x[k], tris[k]), f"{k}, frame {f}"
            assert np.linalg.norm(x[k][seams[k][:, 0]] - x[k][seams[k][:, 1]], axis=1).max() < 1e-3
        # layer order: overskirt points near the skirt are on the skirt's outer side (its normals turned away from the
        # skirt's vertical axis); points whose closest skirt point is on its border (not facing it) are left out
        q, dist, t = closest_points(x["overskirt"], x["skirt"], tris["skirt"])
        corners = x["skirt"][tris["skirt"][t]]
        n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        n /= np.linalg.norm(n, axis=1)[:, None]
        radial = q - x["skirt"].mean(axis=0)
        radial[:, 1] = 0.0
        n *= np.sign(np.einsum("ij,ij->i", n, radial))[:, None]
        side = np.einsum("ij,ij->i", x["overskirt"] - q, n)
        facing = (dist < 0.015) & (np.abs(side) >= 0.5 * dist)
        assert facing.sum() > 50 and (side[facing] > 0.0).all(), f"frame {f}"
        waists = [x[k][:, 1] > 0.995 if first is None else first[k] for k in ("skirt", "overskirt")]
        heights = [x[k][w, 1].mean() for k, w in zip(("skirt", "overskirt"), waists)]
        first = first or {k: w for k, w in zip(("skirt", "overskirt"), waists)}
        track = heights if f == int(stage.GetStartTimeCode()) else track + heights
    bob = np.ptp(np.reshape(track, (-1, 2)), axis=0)
    assert (bob > 1e-3).all()  # the walk's bob carries both waistbands


def test_adaptive_run_reports_its_dt_range(tmp_path):
    """Check an adaptive explicit run through a scene backs off, records the smallest dt per frame in the cache
    and reports the dt range and rejected steps in the summary."""
    out = tmp_path / "adaptive.usdc"
    summary = run_scene(HANG, {"cloth.grid.resolution": [16, 16], "solver.integrator": "symplectic_euler",
                               "solver.adaptive": True, "material.preset": "denim"}, output=out, frames=3)
    assert summary["status"] == "complete" and summary["rejected_steps"] > 0
    assert summary["dt_min"] < summary["dt_max"] <= 1.0 / 60.0
    tc, dts = CacheReader(out).diagnostics()["dt"]
    assert list(tc) == [2, 3, 4] and min(dts) == pytest.approx(summary["dt_min"], rel=1e-6)
