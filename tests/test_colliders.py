"""Colliders: distance functions against numpy/trimesh, Coulomb friction on an incline against the exact
discrete answer (physics.md 1(g)), continuous detection of a fast particle, moving colliders, bad input."""

import math
import pathlib
import sys

import numpy as np
import pytest
import trimesh
import warp as wp

import cloth_warp as cw
from cloth_warp.collision import collider_distance, penetration_depths
from cloth_warp.model import quat_multiply

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "benchmarks"))  # (a case shared with a benchmark)

G = 9.81


def shapes_model():
    b = cw.ModelBuilder()
    b.add_particle((0.0, 5.0, 0.0))
    q = cw.quat_from_axis_angle((1.0, 2.0, 0.5), 35.0)
    b.add_plane(normal=(0.3, 1.0, -0.2), point=(0.1, -0.2, 0.3))
    b.add_sphere((0.2, 0.1, -0.1), 0.4)
    b.add_capsule((0.0, 0.2, 0.1), 0.25, 0.6, axis=(1.0, 1.0, 0.0))
    b.add_box((0.1, 0.0, 0.2), (0.8, 0.5, 0.3), rotation=q)
    b.add_cylinder((-0.1, 0.1, 0.0), 0.35, 0.2, axis=(0.2, 1.0, 0.4))
    box = trimesh.creation.box(extents=(0.6, 0.4, 0.5))
    b.add_collider_mesh(box.vertices, box.faces, position=(0.05, 0.1, -0.05), rotation=q)
    return b.finalize("cpu")


def test_shape_distances_match_numpy():
    """Check each shape's kernel distance and normal against an independent numpy (trimesh for meshes) evaluation."""
    m = shapes_model()
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.9, 0.9, size=(400, 3))
    for k, col in enumerate(m.colliders):
        d, n = collider_distance(m, k, pts)
        ref = col.distance(pts)
        assert np.allclose(d, ref, atol=2e-5), (col.shape, np.abs(d - ref).max())
        # normal = gradient of the distance (central differences), away from the medial axis / edges
        eps = 1e-4
        grad = np.stack([(col.distance(pts + eps * e) - col.distance(pts - eps * e)) / (2 * eps) for e in np.eye(3)], 1)
        smooth = np.abs(np.linalg.norm(grad, axis=1) - 1.0) < 1e-3
        assert smooth.sum() > 100, col.shape
        assert np.allclose(n[smooth], grad[smooth], atol=2e-3), (col.shape, np.abs(n[smooth] - grad[smooth]).max())
        assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-4)


def box_distance(points, centre, extents):
    """Signed distance [m] of points to an axis-aligned box (numpy)."""
    q = np.abs(points - centre) - np.asarray(extents) / 2
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mesh_distance_is_signed_right_halfway_between_facing_surfaces(seed):
    """Check a mesh of two parts facing each other across a narrow gap (a body's arm and chest) signs the points in the
    gap outside, halfway across it too (over faces, over the triangles' diagonals, at the corners), and those in the
    parts inside, with the distance of the nearest part: Warp's pseudo-normal sums the normals of every face within a
    tie band of the nearest (1e-3 of the mean edge, here 0.7 mm), and halfway across the gap those cancel."""
    rng = np.random.default_rng(seed)
    gap = rng.uniform(0.002, 0.02)
    extents = (0.6, 0.1, 0.6)
    centres = [np.array([0.0, -0.05, 0.0]), np.array([0.0, gap + 0.05, 0.0])]
    rot = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    both = trimesh.util.concatenate([trimesh.creation.box(extents=extents).apply_translation(c) for c in centres])
    b = cw.ModelBuilder()
    b.add_collider_mesh(both.vertices @ rot.T, both.faces)
    b.add_particle((0.0, 1.0, 0.0))
    m = b.finalize("cpu")
    u = rng.uniform(-0.3, 0.3, 300)
    w = np.concatenate([rng.uniform(-0.3, 0.3, 100), u[100:200], -u[200:]])  # anywhere, over either diagonal
    corners = np.array([(x, z) for x in (-0.3, 0.3) for z in (-0.3, 0.3)])
    u, w = np.concatenate([u, corners[:, 0]]), np.concatenate([w, corners[:, 1]])
    off = np.concatenate([np.zeros(len(u) // 2), rng.uniform(-gap / 4, gap / 4, len(u) - len(u) // 2)])
    gap_points = np.stack([u, gap / 2 + off, w], axis=1)
    inside = np.concatenate([rng.uniform((-0.28, -0.09, -0.28), (0.28, -0.002, 0.28), (50, 3)),
                             rng.uniform((-0.28, gap + 0.002, -0.28), (0.28, gap + 0.09, 0.28), (50, 3))])
    local = np.concatenate([gap_points, inside])
    d, _ = collider_distance(m, 0, local @ rot.T)
    exact = np.minimum(*(box_distance(local, c, extents) for c in centres))
    np.testing.assert_allclose(d, exact, atol=2e-6)


def incline_model(theta_deg, mu_s, mu_k, *, mesh=False, cloth=False, thickness=0.004):
    """A plane (or a two-triangle mesh) through the origin tilted by theta about z; a particle (or a flat
    8x8 cloth) resting on it at the contact thickness."""
    th = math.radians(theta_deg)
    normal = np.array([-math.sin(th), math.cos(th), 0.0])
    downhill = np.array([-math.cos(th), -math.sin(th), 0.0])
    b = cw.ModelBuilder()
    common = dict(thickness=thickness, static_friction=mu_s, kinetic_friction=mu_k)
    if mesh:
        quad = np.array([[-3, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3]], float)
        b.add_collider_mesh(quad, [[0, 2, 1], [0, 3, 2]], rotation=cw.quat_from_axis_angle((0, 0, 1), theta_deg), **common)
    else:
        b.add_plane(normal=normal, **common)
    lift = normal * thickness
    if cloth:
        # the grid's local xy-plane laid flat (-90 deg about x), then tilted with the incline
        flat_then_tilt = quat_multiply(cw.quat_from_axis_angle((0, 0, 1), theta_deg), cw.quat_from_axis_angle((1, 0, 0), -90.0))
        # no air drag: implicit drag would damp the per-step normal approach velocity g cos h and so the friction
        b.add_cloth_grid(resolution=(8, 8), size=(0.4, 0.4), material=cw.materials.COTTON.replace(drag_coefficient=0.0), position=tuple(lift), rotation=tuple(flat_then_tilt))
    else:
        b.add_particle(tuple(lift), mass=0.01)
    return b.finalize("cpu"), normal, downhill


def discrete_slide(theta_deg, mu_s, mu_k, h, steps):
    """Exact velocity-level friction with symplectic Euler from rest (physics.md 1(g)): (distance, speed)."""
    th = math.radians(theta_deg)
    v = s = 0.0
    for _ in range(steps):
        vt = v + G * math.sin(th) * h
        dvn = G * math.cos(th) * h
        v = 0.0 if vt <= mu_s * dvn else vt - mu_k * dvn
        s += h * v
    return s, v


@pytest.mark.parametrize("theta,mu_s,mu_k", [(10.0, 0.3, 0.3), (16.0, 0.3, 0.3), (17.5, 0.3, 0.3), (30.0, 0.3, 0.3),
                                              (20.0, 0.5, 0.3), (30.0, 0.5, 0.3)])
def test_incline_particle(theta, mu_s, mu_k):
    """Check a particle on an incline sticks iff tan(theta) <= mu_s and otherwise slides with
    a = g (sin - mu_k cos), matching the discrete closed form at h = 1 ms over 1 s (float32 round-off)."""
    m, normal, downhill = incline_model(theta, mu_s, mu_k)
    sim = cw.Simulator(m, cw.SolverSymplecticEuler(m, strain_limit=None), fps=100, substeps=10)
    x0 = sim.positions()[0]
    for _ in range(100):
        sim.step_frame()
    x = sim.positions()[0]
    v = sim.state.particle_qd.numpy()[0]
    s_ref, v_ref = discrete_slide(theta, mu_s, mu_k, 1e-3, 1000)
    s = float(np.dot(x - x0, downhill))
    sticks = math.tan(math.radians(theta)) <= mu_s
    if sticks:
        assert abs(s) < 1e-6 and np.linalg.norm(v) < 1e-6
    else:
        a = G * (math.sin(math.radians(theta)) - mu_k * math.cos(math.radians(theta)))
        assert s_ref == pytest.approx(a * 1.0**2 / 2 + a * 1e-3 * 1.0 / 2, rel=1e-9)  # x_n = a t^2/2 + a h t/2
        assert s == pytest.approx(s_ref, rel=2e-4)
        assert float(np.dot(v, downhill)) == pytest.approx(v_ref, rel=2e-4)
    # stays on the surface at the thickness, never below it, no normal velocity
    assert float(np.dot(x, normal)) == pytest.approx(0.004, abs=2e-6)
    assert abs(float(np.dot(v, normal))) < 1e-5


@pytest.mark.parametrize("mesh", [False, True], ids=["plane", "mesh"])
def test_incline_cloth(mesh):
    """Check a flat cloth on an incline (plane and tilted triangle-mesh collider) slides rigidly with the
    particle's closed form above the threshold and sticks below it (implicit Euler: for a rigid translation
    its step is the symplectic one, and cotton at h = 1 ms is beyond the explicit stability limit)."""
    for theta, sticks in ((14.0, True), (30.0, False)):
        m, normal, downhill = incline_model(theta, 0.3, 0.3, mesh=mesh, cloth=True)
        sim = cw.Simulator(m, cw.SolverImplicitEuler(m), fps=100, substeps=10)
        x0 = sim.positions()
        for _ in range(50):
            sim.step_frame()
        d = (sim.positions() - x0) @ downhill
        s_ref, _ = discrete_slide(theta, 0.3, 0.3, 1e-3, 500)
        if sticks:
            assert np.abs(d).max() < 1e-6
        else:
            assert np.allclose(d, s_ref, rtol=1e-3), (d.min(), d.max(), s_ref)
        heights = sim.positions() @ normal
        assert heights.min() > 0.004 - 1e-5 and heights.max() < 0.004 + 1e-5


def test_fast_particle_does_not_tunnel():
    """Check continuous detection: a particle at 100 m/s over a 2 mm plate with h = 0.1 s (it would end 9 m
    below the plate) stops on the plate at the thickness with no normal velocity, counted as a CCD catch."""
    b = cw.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_particle((0.25, 1.0, 0.25), velocity=(0.0, -100.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (2.0, 0.002, 2.0), thickness=0.003, friction=0.0)
    m = b.finalize("cpu")
    solver = cw.SolverSymplecticEuler(m, strain_limit=None)
    sim = cw.Simulator(m, solver, fps=10, substeps=1)
    solver.reset_pass_reports()
    sim.step_frame()
    x = sim.positions()[0]
    v = sim.state.particle_qd.numpy()[0]
    assert x[1] == pytest.approx(0.001 + 0.003, abs=1e-6)
    assert np.allclose(x[[0, 2]], 0.25, atol=1e-6)
    assert abs(v[1]) < 1e-6
    assert solver.read_pass_reports()["colliders"].counters() == {"collider_contacts": 1, "collider_ccd": 1, "collider_samples": 0}


def test_moving_collider_carries_particle():
    """Check a box rising at 1 m/s picks up a particle resting on it (no gravity): afterwards the particle
    rides at the thickness above the lid with the box's velocity."""
    b = cw.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_particle((0.0, 0.3, 0.0))
    b.add_box((0.0, 0.0, 0.0), (1.0, 0.2, 1.0), thickness=0.01, friction=0.5, keyframes=[(0.0, (0, 0, 0)), (2.0, (0, 2.0, 0))])
    m = b.finalize("cpu")
    sim = cw.Simulator(m, cw.SolverSymplecticEuler(m, strain_limit=None), fps=60, substeps=4)
    for _ in range(60):
        sim.step_frame()
    x = sim.positions()[0]
    v = sim.state.particle_qd.numpy()[0]
    lid = 0.1 + 1.0  # top of the box after 1 s
    assert x[1] == pytest.approx(lid + 0.01, abs=1e-5)
    assert v == pytest.approx([0.0, 1.0, 0.0], abs=1e-4)


def test_sphere_shot_through_hanging_cloth():
    """Check a 5 cm sphere at 20 m/s (33 cm per 1/60 s step) does not pass through a hanging cloth: the cloth
    is carried along, every free vertex stays outside the sphere by its thickness, and CCD catches are
    counted."""
    b = cw.ModelBuilder()
    cloth = b.add_cloth_grid(resolution=(24, 24), size=(0.6, 0.6), material="cotton", position=(-0.3, 0.2, 0.0))
    b.pin(cloth.select("edge:top"))
    b.add_sphere((0.0, 0.5, -0.5), 0.05, thickness=0.004, keyframes=[(0.0, (0, 0, 0)), (1.0, (0, 0, 20.0))])
    m = b.finalize("cpu")
    solver = cw.SolverImplicitEuler(m)
    sim = cw.Simulator(m, solver, fps=60, substeps=1)
    for f in range(4):
        sim.step_frame()
        t = sim.time
        assert penetration_depths(m, sim.positions(), t)[0] < 1e-5, f
    centre = m.colliders[0].pose_at(sim.time)[0]
    assert centre[2] > 0.7  # the sphere is well past the cloth's plane
    x = sim.positions()
    assert x[:, 2].max() > 0.6  # and the cloth went with it
    assert solver.read_pass_reports()["colliders"].ccd > 0


def test_taped_steps_with_colliders_have_finite_gradients():
    """Check a taped symplectic rollout through sphere and ground contact gives finite, non-zero gradients
    with respect to the initial velocity and the collider friction."""
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(6, 6), size=(0.4, 0.4), material="silk", rotation=cw.quat_from_axis_angle((1, 0, 0), -90.0),
                     position=(-0.2, 0.256, 0.2), velocity=(1.0, -0.5, 0.0))  # lands sliding: kinetic friction acts
    b.add_sphere((0.0, 0.1, 0.0), 0.15, friction=0.4)
    b.add_ground(friction=0.4)
    m = b.finalize("cpu", requires_grad=True)
    solver = cw.SolverSymplecticEuler(m, strain_limit=0.1)
    control = m.control()
    states = [m.state() for _ in range(21)]
    tape = wp.Tape()
    with tape:
        for k in range(20):
            m.update_control(control, (k + 1) * 2e-3, 2e-3)
            solver.step(states[k], states[k + 1], control, 2e-3)
    seed = np.zeros((m.particle_count, 3), np.float32)
    seed[:, 0] = 1.0  # d(sum of x)/d(...): sliding over the sphere is what friction changes
    seed[:, 1] = 1.0
    tape.backward(grads={states[-1].particle_q: wp.array(seed, dtype=wp.vec3)})
    g_v = states[0].particle_qd.grad.numpy()
    g_mu = m.collider_kinetic_friction.grad.numpy()
    assert np.all(np.isfinite(g_v)) and np.abs(g_v).max() > 0
    assert np.all(np.isfinite(g_mu)) and np.abs(g_mu).max() > 0
    assert solver.read_pass_reports()["colliders"].contacts > 0


def test_bad_collider_input():
    """Check bad collider arguments raise errors that name the collider and the problem."""
    b = cw.ModelBuilder()
    with pytest.raises(ValueError, match="radius > 0"):
        b.add_sphere((0, 0, 0), 0.0)
    with pytest.raises(ValueError, match="kinetic_friction 0.5 exceeds static_friction 0.2"):
        b.add_box((0, 0, 0), (1, 1, 1), static_friction=0.2, kinetic_friction=0.5)
    with pytest.raises(ValueError, match="three positive edge lengths"):
        b.add_box((0, 0, 0), (1, -1, 1))
    with pytest.raises(ValueError, match="non-finite"):
        b.add_collider_mesh([[0, 0, 0], [1, 0, 0], [0, float("nan"), 0]], [[0, 1, 2]])
    with pytest.raises(ValueError, match="out of range"):
        b.add_collider_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]])
    with pytest.raises(ValueError, match="keyframe times must increase"):
        b.add_sphere((0, 0, 0), 1.0, keyframes=[(1.0, (0, 0, 0)), (0.5, (0, 1, 0))])
    b.add_sphere((0, 0, 0), 1.0, name="ball")
    with pytest.raises(ValueError, match="named 'ball' exists"):
        b.add_sphere((0, 0, 0), 1.0, name="ball")


COLLIDER_SCENES = ["drape_sphere", "tablecloth", "incline", "sphere_shot"]


@pytest.mark.parametrize("name", COLLIDER_SCENES)
def test_collider_scenes_run_without_penetration(name, tmp_path):
    """Check each shipped collider scene (coarsened, a few frames) writes a cache with its colliders in which no
    free vertex is deeper inside a collider than its thickness (1e-5 m float slack) in any frame, and counts its
    contacts, per frame too, where they were resolved: after the step (the colliders pass) or inside the implicit solve
    (the drape over the ball and the tablecloth as shipped)."""
    from cloth_warp.runner import find_scene
    from cloth_warp.scene import build_model, load_scene

    overrides = {"cloth.grid.resolution": [16, 16]}
    scene = load_scene(find_scene(name), overrides)
    summary = cw.run_scene(scene, output=tmp_path / f"{name}.usdc", frames=12)
    in_solve = scene.get("solver.collider_contacts") == "solve"
    counter, diagnostic = ("solve_contacts", "solveContacts") if in_solve else ("collider_contacts", "colliderContacts")
    assert summary["status"] == "complete" and summary["contacts"][counter] > 0
    reader = cw.CacheReader(tmp_path / f"{name}.usdc")
    assert [c["shape"] for c in reader.colliders] == [c["type"] for c in scene.data["colliders"]]
    model = build_model(scene, "cpu")
    for frame in range(reader.start_frame, reader.end_frame + 1):
        t = (frame - reader.start_frame) / reader.fps
        depth = penetration_depths(model, reader.points(frame), t)
        assert depth.max() < 1e-5, (name, frame, depth)
    assert reader.diagnostics()[diagnostic][1].max() > 0


def test_dropped_cloth_comes_to_rest():
    """Check resting contact adds no energy: a 40 cm cotton square dropped 5 cm onto the ground comes to rest
    (max speed < 1 mm/s after 3 s), and after the impact the kinetic energy never grows by more than gravity
    can add in one frame."""
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(16, 16), size=(0.4, 0.4), material="cotton", rotation=cw.quat_from_axis_angle((1, 0, 0), -90.0),
                     position=(-0.2, 0.05, 0.2))
    b.add_ground(friction=0.5)
    m = b.finalize("cpu")
    sim = cw.Simulator(m, cw.SolverImplicitEuler(m), fps=60, substeps=2)
    energies = [sim.step_frame().kinetic_energy for _ in range(180)]
    stats = sim.diagnostics.measure(sim.state)
    assert stats.max_speed < 1e-3, stats
    mass = float(m.particle_mass.numpy().sum())
    peak = int(np.argmax(energies))
    growth = np.diff(energies[peak:])
    assert growth.max() <= 0.5 * mass * (9.81 / 60.0) ** 2 + 1e-9
    assert penetration_depths(m, sim.positions()).max() < 1e-5


@pytest.mark.slow
def test_cloth_draped_over_sphere_comes_to_rest():
    """Check the drape_sphere scene (16^2, self-collision off, solver as shipped: the contacts and their friction in the
    solve) comes to rest on the ball and the ground: max speed < 1 mm/s over the last 20 frames of 5 s (measured 0.64
    mm/s; 1.49 over frames 221-240, 0.27 at solver.tolerance 1e-4; with the contacts after the solve, 0.25 after 4 s).
    Before warm-started solves had to cut their starting residual (SolverImplicitEuler.warm_start_reduction), a solve
    stopped as soon as the previous dv was within tolerance, and that delay sustained a ~6 Hz limit cycle of the free
    edges at 29 mm/s."""
    from cloth_warp.scene import build_model, build_solver, load_scene

    scene = load_scene(pathlib.Path(__file__).resolve().parent.parent / "scenes" / "drape_sphere.toml",
                       {"cloth.grid.resolution": [16, 16], "collision.self_collision": False})
    m = build_model(scene, "cpu")
    sim = cw.Simulator(m, build_solver(scene, m), fps=60, substeps=2)
    speeds = [sim.step_frame().max_speed for _ in range(300)]
    assert max(speeds[-20:]) < 1e-3, speeds[-20:]
    assert penetration_depths(m, sim.positions()).max() < 1e-5
    # draped, not slid off: the cap rests on the ball, the corners on the ground
    on_ball, on_ground = (int((collider_distance(m, k, sim.positions())[0] < 0.006).sum()) for k in range(2))
    assert on_ball > 10 and on_ground >= 4, (on_ball, on_ground)


def _point_cache(path, mesh, points_at, fps=24.0, seconds=1.0):
    """Write a USD point cache of trimesh `mesh` whose vertices at time t [s] are points_at(t): one time
    sample per frame from time code 1 (the stage start), metres, like an exported animated body."""
    from pxr import Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(fps)
    frames = int(round(seconds * fps))
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1 + frames)
    prim = UsdGeom.Mesh.Define(stage, "/body")
    prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(mesh.faces), 3, np.int32)))
    prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.faces.reshape(-1).astype(np.int32))))
    for k in range(frames + 1):
        prim.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points_at(k / fps), np.float32)), 1 + k)
    stage.GetRootLayer().Save()


def _growing_ball_cache(path, r0=0.15, r1=0.3):
    """An icosphere at the origin whose radius grows linearly from r0 to r1 [m] over 1 s."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    _point_cache(path, ball, lambda t: ball.vertices * (r0 + (r1 - r0) * t))
    return r0, r1


def growing_ball_scene(folder, r0: float, substeps: int) -> pathlib.Path:
    """A scene in `folder` (beside the ball's cache, body.usda): an 8 x 8 cotton sheet, 0.5 m, lying 1 cm above the ball
    of radius r0 [m] (implicit Euler, `substeps` per frame; 30 frames at 30 fps)."""
    scene = folder / "grow.toml"
    scene.write_text(f"""
[cloth]
grid = {{ resolution = [8, 8], size = [0.5, 0.5] }}
position = [-0.25, {r0 + 0.01}, 0.25]
rotation = {{ axis = [1.0, 0.0, 0.0], angle = -90.0 }}
[material]
preset = "cotton"
[[colliders]]
type = "mesh"
mesh = "body.usda"
deforming = true
friction = 0.5
[solver]
integrator = "implicit_euler"
substeps = {substeps}
[output]
frames = 30
fps = 30
""")
    return scene


def test_point_cache_collider_pushes_cloth_and_is_cached(tmp_path):
    """A deforming mesh collider read from a USD point cache (a ball growing from 15 to 30 cm radius in 1 s)
    lifts a cloth lying on it: in every frame no vertex is deeper than the thickness in the ball of that time,
    the cloth's top follows the radius, and the cache holds the ball's points per frame for DCC playback."""
    from cloth_warp.builder import read_usd_point_cache
    from cloth_warp.cache import CacheReader

    body = tmp_path / "body.usda"
    r0, r1 = _growing_ball_cache(body)
    times, points, tris = read_usd_point_cache(body)
    assert len(times) == 25 and times[0] == 0.0 and times[-1] == pytest.approx(1.0)
    assert np.linalg.norm(points[-1], axis=1).max() == pytest.approx(r1, rel=1e-6) and tris.shape[1] == 3
    scene = growing_ball_scene(tmp_path, r0, substeps=2)
    out = tmp_path / "grow.usdc"
    summary = cw.run_scene(scene, output=out)
    assert summary["status"] == "complete"
    reader = CacheReader(out)
    model = cw.scene.build_model(cw.scene.load_scene(scene), "cpu")
    tops = []
    for f in range(reader.frame_count):
        t = f / reader.fps
        x = reader.points(reader.start_frame + f)
        assert penetration_depths(model, x, t).max() < 1e-5, (f, penetration_depths(model, x, t))
        tops.append(x[:, 1].max())
    assert tops[-1] == pytest.approx(r1 + model.colliders[0].thickness, abs=0.01)  # carried up by 15 cm
    ball = [c for c in reader.colliders if c["shape"] == "mesh"][0]["prim"]
    from pxr import UsdGeom

    pts = UsdGeom.Mesh(ball).GetPointsAttr()
    assert len(pts.GetTimeSamples()) == reader.frame_count
    assert np.linalg.norm(np.asarray(pts.Get(reader.start_frame + 30)), axis=1).max() == pytest.approx(r1, rel=1e-5)


def test_point_cache_collider_carries_cloth_by_friction(tmp_path):
    """A slab read from a point cache slides along x at 0.5 m/s under a cloth lying on it (mu = 1): static
    friction against the surface's own velocity (its vertex velocities) carries the cloth along at the
    slab's speed. A contact that took the surface as still would hold the cloth back and let the slab slip
    away beneath it."""
    from cloth_warp.scene import build_model, build_solver, load_scene

    slab = trimesh.creation.box(extents=(2.0, 0.1, 2.0))
    _point_cache(tmp_path / "slab.usda", slab, lambda t: slab.vertices + np.array([0.5 * t, -0.05, 0.0]))
    scene = tmp_path / "slide.toml"
    scene.write_text("""
[cloth]
grid = { resolution = [6, 6], size = [0.3, 0.3] }
position = [-0.15, 0.005, 0.15]
rotation = { axis = [1.0, 0.0, 0.0], angle = -90.0 }
[[colliders]]
type = "mesh"
mesh = "slab.usda"
deforming = true
friction = 1.0
[solver]
integrator = "implicit_euler"
substeps = 2
""")
    sc = load_scene(scene)
    m = build_model(sc, "cpu")
    sim = cw.Simulator(m, build_solver(sc, m), fps=60, substeps=2)
    x0 = sim.positions()[:, 0].mean()
    for _ in range(36):  # 0.6 s: the slab moves 0.3 m (it starts moving at once, as the cache does)
        stats = sim.step_frame()
    x = sim.positions()
    v = sim.state.particle_qd.numpy()
    assert x[:, 0].mean() - x0 == pytest.approx(0.3, abs=0.02)
    assert v[:, 0].mean() == pytest.approx(0.5, abs=0.02) and stats.max_strain < 0.05
    assert penetration_depths(m, x, 0.6).max() < 1e-5


def _ridge_and_triangle(seed, pinned=False):
    """A closed prism whose apex is a ridge along z (faces sloping 45 degrees down from it) and a cloth triangle whose
    edge ab passes under the apex, through the prism, while all three particles lie clear of it by more than the
    thickness (c above the apex); both turned about the vertical and moved at random. Returns the model, the prism's
    world vertices and faces."""
    from cloth_warp.model import quat_to_matrix
    from cloth_warp.builder import quat_from_axis_angle

    rng = np.random.default_rng(seed)
    h, half = 0.1, 0.2
    prism = np.array([[0, 0, -half], [0, 0, half], [-h, -h, -half], [-h, -h, half], [h, -h, -half], [h, -h, half]], float)
    faces = np.array([[0, 1, 3], [0, 3, 2], [0, 4, 5], [0, 5, 1], [2, 3, 5], [2, 5, 4], [0, 2, 4], [1, 5, 3]])
    mesh = trimesh.Trimesh(prism, faces, process=False)
    trimesh.repair.fix_normals(mesh)
    y = rng.uniform(-0.02, -0.01)
    tri = np.array([[rng.uniform(-0.06, -0.045), y, -0.02], [rng.uniform(0.045, 0.06), y, -0.02], [0.0, 0.03, 0.04]])
    q = quat_from_axis_angle((0.0, 1.0, 0.0), rng.uniform(0.0, 360.0))
    move = rng.uniform(-0.5, 0.5, 3)
    turn = quat_to_matrix(q)
    b = cw.ModelBuilder()
    b.add_cloth_mesh(tri @ turn.T + move, [[0, 1, 2]], material="cotton")
    if pinned:
        b.particle_pinned[0] = True
    b.add_collider_mesh(mesh.vertices, mesh.faces, position=tuple(move), rotation=q, name="ridge", thickness=0.004)
    return b.finalize("cpu"), np.asarray(mesh.vertices) @ turn.T + move, np.asarray(mesh.faces)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("pinned", [False, True])
def test_element_samples_push_an_edge_out_of_a_mesh_ridge_its_particles_clear(seed, pinned):
    """Check the colliders pass's element samples (cloth_warp/collision.py `element_samples`, kernels/collide.py
    `collide_element_samples`): a triangle whose edge passes through a mesh ridge while its particles are clear of it
    by more than the thickness (the independent checker of tests/intersections.py finds the crossing, and the particle
    contacts alone leave it) comes out of one pass clear of the ridge: no crossing, every sample point outside by at
    least a twentieth of the thickness (pushed to a quarter: the means of a particle's samples' pushes get most of it),
    the particles moved out of the ridge, most of the approach of the edge's middle stopped, the
    third particle moved less (its share of the triangle's samples). With a particle pinned (or attached to a body) the
    element has no sample: an attached strap's elements pushed by their free particles alone were thrown out at 77 m/s. Samples at fixed points of
    the edge missed the ridge when it crossed between them (the stretch inside a 90-degree ridge 9 mm under it is 17 mm
    long): the edge's sample is where it runs inside."""
    from intersections import crossing_pairs

    from cloth_warp.collision import ColliderPass

    m, prism, faces = _ridge_and_triangle(seed, pinned)
    tris = m.tri_indices.numpy().reshape(-1, 3)
    x0 = m.particle_q.numpy().astype(np.float64)
    assert crossing_pairs(x0, tris, prism, faces)
    v = np.zeros_like(x0)
    v[:2] = (0.0, -0.3, 0.0)  # moving down, into the ridge
    dt = 0.01
    control = m.control()
    x_start = wp.array((x0 - dt * v).astype(np.float32), dtype=wp.vec3)
    x_end, v_end = wp.array(x0.astype(np.float32), dtype=wp.vec3), wp.array(v.astype(np.float32), dtype=wp.vec3)
    results = {}
    for on in (False, True):
        p = ColliderPass(m)
        p.samples_on = on
        x_out, v_out = wp.zeros_like(x_end), wp.zeros_like(v_end)
        p.apply(x_start, x_end, v_end, control, dt, x_out, v_out)
        results[on] = (x_out.numpy().astype(np.float64), v_out.numpy().astype(np.float64), p.read_report())
    x_off, _, report_off = results[False]
    assert report_off.contacts == 0 and report_off.samples == 0 and np.allclose(x_off, x0)  # the particles are clear
    x, v_new, report = results[True]
    if pinned:  # an element with a pinned (or attached) particle has no sample: it goes where the user puts it
        assert report.samples == 0 and np.allclose(x, x0)
        return
    assert report.samples > 0
    assert not crossing_pairs(x, tris, prism, faces)
    points = np.concatenate([(x[tris[:, [0, 1, 1]]] + x[tris[:, [1, 2, 0]]]).reshape(-1, 3) / 2.0,
                             np.linspace(0.0, 1.0, 41)[:, None] * (x[1] - x[0]) + x[0]])  # edge middles; the crossing edge
    normals = np.cross(prism[faces[:, 1]] - prism[faces[:, 0]], prism[faces[:, 2]] - prism[faces[:, 0]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # the prism is convex: a point's largest height over its faces' planes is at most its distance outside
    clearance = np.einsum("fd,sfd->sf", normals, points[:, None, :] - prism[faces[:, 0]][None]).max(axis=1)
    assert clearance.min() > 0.05 * 0.004
    moved = x - x0
    assert np.linalg.norm(moved[2]) < 0.5 * np.linalg.norm(moved[:2], axis=1).max()  # (a share of the triangle's samples)
    assert np.linalg.norm(moved[:2], axis=1).max() > 0.004
    up = moved[np.argmax(np.linalg.norm(moved, axis=1))]
    up /= np.linalg.norm(up)
    assert up[1] > 0.5  # out of the ridge, not along it
    before, after = v[:2].mean(axis=0) @ up, v_new[:2].mean(axis=0) @ up  # the edge's middle's approach
    assert before < -0.2 and after > 0.25 * before  # (92-100 % of it removed: shared with the triangle's samples)


@pytest.mark.parametrize("subdivisions,resolution,seed", [(2, 12, 0), (3, 16, 1), (4, 16, 2),
                                                           pytest.param(2, 24, 3, marks=pytest.mark.slow)])
def test_a_coarse_cloth_over_a_faceted_ball_comes_to_rest_where_its_elements_touch_it(subdivisions, resolution, seed):
    """Check a cloth whose edges are as long as the body's facets, dropped over a mesh ball (an icosphere, turned at
    random) onto the ground with the contacts and their friction in the solve, comes to rest though its edges and
    triangles, not its particles, touch the ball: at rest after 6 s (the median of the last 20 frames' largest speed <=
    1 mm/s, as benchmarks/bench_rest.py counts it: a free edge's flap may still swing at ~1 mm/s; without self-collision
    a fold may slip late, as one did at 3.3 s here), the element samples pushing nothing by then (they pushed while it
    wrapped the ball). Each particle the samples push keeps, as a contact in the solve, the height they left it at
    (kernels/contact.py `eval_collider_contacts`, `sample_height`); without that (`sample_holds=False`) the cloth sagged
    back into the ball for the samples to push again: 79-226 mm/s after 5 s with 9-108 samples pushed a frame in 14 of
    benchmarks/bench_sample_holds.py's 18 runs (the first two cases here among them; the first at 92-206 mm/s after 6 s),
    18 of 18 at rest with it."""
    from bench_sample_holds import faceted_ball_drape

    sim = faceted_ball_drape(subdivisions, resolution, seed)
    m = sim.model
    speeds, samples = [], []
    for _ in range(360):
        speeds.append(sim.step_frame().max_speed)
        samples.append(sim.frame_report.passes["colliders"].samples)
    assert sum(samples) > 0  # its elements cut the ball on the way
    assert sum(samples[-20:]) == 0 and np.median(speeds[-20:]) <= 1e-3, (samples[-20:], speeds[-20:])
    on_ball = int((collider_distance(m, 0, sim.positions())[0] < 0.012).sum())
    assert on_ball > resolution, on_ball  # draped over it, not slid off


DT_PASS = 1.0 / 120.0


def _valley(angle: float, seed: int):
    """An open mesh collider folded into a valley of interior `angle` [deg] (two 0.4 m x 0.2 m faces meeting along the
    crease, solid behind them), turned and placed at random; returns (model, crease point, crease direction, the two
    faces' outward normals)."""
    rng = np.random.default_rng(seed)
    half = math.radians(0.5 * angle)
    wing_a, wing_b = np.array([math.sin(half), math.cos(half), 0.0]), np.array([-math.sin(half), math.cos(half), 0.0])
    ridge = np.array([0.0, 0.0, 1.0])
    verts = np.array([[0, 0, -0.2], [0, 0, 0.2], *(0.2 * wing_a + [[0, 0, -0.2], [0, 0, 0.2]]),
                      *(0.2 * wing_b + [[0, 0, -0.2], [0, 0, 0.2]])])
    faces = np.array([[0, 3, 2], [0, 1, 3], [0, 5, 1], [0, 4, 5]])
    turn = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    move = rng.uniform(-0.5, 0.5, 3)
    q = wp.quat_from_matrix(wp.mat33(*turn.ravel().tolist()))
    b = cw.ModelBuilder()
    normals = [np.cross(ridge, wing_a), np.cross(wing_b, ridge)]  # out of the solid, into the valley
    for k in range(3):
        b.add_particle(tuple(move))
    b.add_collider_mesh(verts, faces, position=tuple(move), rotation=q, name="valley", thickness=0.004)
    return b.finalize("cpu"), move, turn @ ridge, [turn @ n for n in normals]


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("angle", [100.0, 133.0, 160.0])
def test_one_colliders_pass_clears_a_particle_of_both_sides_of_a_crease(angle, seed):
    """Check the colliders pass at a mesh's concave crease (a body's shoulder meeting its torso): a particle within the
    thickness of both sides ends one pass clear of both (to the contact band), wherever along the crease and whichever
    side is the nearer, and a second pass moves it no further (the pass is idempotent: pushed from the nearer side
    alone, a second round of the passes pushed it again from the other, undoing the strain limiter's work between)."""
    from cloth_warp.collision import ColliderPass

    m, apex, along, (n_a, n_b) = _valley(angle, seed)
    t = 0.004
    heights = [(0.6 * t, 0.65 * t), (0.65 * t, 0.6 * t), (0.9 * t, 0.9 * t)]  # over side a, side b
    x = []
    for k, (h_a, h_b) in enumerate(heights):  # the point at those heights over both planes, somewhere along the crease
        lateral = np.linalg.solve(np.array([[n_a @ n_a, n_a @ n_b], [n_a @ n_b, n_b @ n_b]]), [h_a, h_b])
        x.append(apex + (k - 1) * 0.05 * along + lateral[0] * n_a + lateral[1] * n_b)
    x = np.array(x)
    control = m.control()
    m.update_control(control, DT_PASS, DT_PASS, force=True)
    x_end = wp.array(x.astype(np.float32), dtype=wp.vec3)
    v_end = wp.zeros_like(x_end)
    p = ColliderPass(m)
    once, v_once, twice, v_twice = (wp.zeros_like(x_end) for _ in range(4))
    p.apply(x_end, x_end, v_end, control, DT_PASS, once, v_once)
    p.apply(once, once, v_once, control, DT_PASS, twice, v_twice)
    out = once.numpy().astype(np.float64)
    for n in (n_a, n_b):
        assert ((out - apex) @ n).min() >= t * (1.0 - 2.0e-3) - 1.0e-6
    assert np.linalg.norm(out - x, axis=1).max() <= t  # out to the thickness, not thrown clear
    np.testing.assert_allclose(twice.numpy(), once.numpy(), atol=1.0e-6)


def test_a_run_resumed_from_a_checkpoint_keeps_the_samples_heights():
    """Check a run resumed from a checkpoint taken while particles are held at the heights the element samples left them
    at (cloth_warp/solvers/implicit.py `sample_height`, carried in the checkpoint) goes on bit for bit as the run straight
    through; without them in the checkpoint the resumed run's held particles would land back on the ball."""
    from bench_sample_holds import faceted_ball_drape

    straight = faceted_ball_drape(2, 12, 0)
    for _ in range(40):
        straight.step_frame()
    first = faceted_ball_drape(2, 12, 0)
    for _ in range(30):
        first.step_frame()
    assert (first.solver.sample_height.numpy() > 0.0).sum() >= 3
    checkpoint = {k: (np.asarray(v).copy() if hasattr(v, "shape") else v) for k, v in first.checkpoint().items()}
    resumed = faceted_ball_drape(2, 12, 0)
    resumed.restore(checkpoint)
    for _ in range(10):
        resumed.step_frame()
    np.testing.assert_array_equal(resumed.state.particle_q.numpy(), straight.state.particle_q.numpy())
    np.testing.assert_array_equal(resumed.state.particle_qd.numpy(), straight.state.particle_qd.numpy())
