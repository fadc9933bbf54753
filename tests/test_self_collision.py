"""Self-collision: the hash-grid broad phase against brute force, the analytic CCD cases and impulse
distribution of physics.md 1(j), proximity repulsion and friction, and the shipped pile / twist / Cusick
scenes checked frame by frame by an independent triangle-triangle intersection test."""

import math

import numpy as np
import pytest
import warp as wp
from intersections import intersecting_pairs

import cloth_warp as cw
from cloth_warp.kernels import broadphase as kb
from cloth_warp.broadphase import SelfCollisionGrid, exclusive_scan, unique_edges
from cloth_warp.collision import penetration_depths
from cloth_warp.drape import drape_coefficient
from cloth_warp.runner import find_scene
from cloth_warp.scene import PASSES_ONLY, build_model, build_solver, load_scene
from cloth_warp.topology import disc_mesh

TRI = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


# -- broad phase -------------------------------------------------------------------------------------

def brute_force_pairs(x0, x1, query, target, pad, same_set):
    def boxes(el):
        lo = np.minimum(x0[el], x1[el]).min(1) - pad
        hi = np.maximum(x0[el], x1[el]).max(1) + pad
        return lo, hi

    lq, hq = boxes(query)
    lt, ht = boxes(target)
    overlap = np.all((lq[:, None] <= ht[None]) & (lt[None] <= hq[:, None]), axis=2)
    shared = (query[:, None, :, None] == target[None, :, None, :]).any(axis=(2, 3))
    keep = overlap & ~shared
    if same_set:
        keep &= np.triu(np.ones_like(keep), 1).astype(bool)
    return set(map(tuple, np.argwhere(keep).tolist()))


@pytest.mark.parametrize("seed,cell", [(0, 0.05), (1, 0.02), (2, 0.4)])
def test_hash_grid_finds_exactly_the_brute_force_pairs(seed, cell, device):
    """Check the hash grid reports exactly the vertex-face and edge-edge pairs whose swept, padded boxes
    overlap and that share no vertex (brute force over all pairs), each once, for random triangle soups
    and voxel sizes from a ninth to twice the typical element size; the pair buffers start too small
    and must grow rather than drop pairs."""
    rng = np.random.default_rng(seed)
    n, t = 300, 400
    x0 = rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)
    vel = rng.normal(0.0, 0.3, (n, 3)).astype(np.float32)
    dt = 0.1
    x1 = (x0 + dt * vel).astype(np.float32)
    # triangles of nearby points (a vertex and two of its 12 nearest), so elements are element-sized
    near = np.argsort(np.linalg.norm(x0[:, None] - x0[None], axis=2), axis=1)[:, 1:13]
    tris = np.array([[i, *rng.choice(near[i], 2, replace=False)] for i in rng.integers(0, n, t)])
    grid = SelfCollisionGrid(tris, n, device, cell_size=cell)
    pad = 0.01
    grid.update(wp.array(x0, dtype=wp.vec3, device=device), wp.array(vel, dtype=wp.vec3, device=device), dt, pad)
    edges = unique_edges(tris)
    vf = grid.vertex_face.numpy()
    ee = grid.edge_edge.numpy()
    assert len(set(map(tuple, vf.tolist()))) == len(vf) and len(set(map(tuple, ee.tolist()))) == len(ee)  # no duplicates
    assert set(map(tuple, vf.tolist())) == brute_force_pairs(x0, x1, tris, np.arange(n)[:, None], pad, False)
    assert set(map(tuple, ee.tolist())) == brute_force_pairs(x0, x1, edges, edges, pad, True)
    assert grid.vertex_face.grown + grid.edge_edge.grown > 0 and int(grid.clamped.numpy()[0]) == 0


def random_soup(seed, n=300, t=400):
    """Random points in the unit cube with triangles of nearby points (element-sized elements)."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)
    near = np.argsort(np.linalg.norm(x0[:, None] - x0[None], axis=2), axis=1)[:, 1:13]
    tris = np.array([[i, *rng.choice(near[i], 2, replace=False)] for i in rng.integers(0, n, t)])
    return rng, x0, tris


@pytest.mark.parametrize("seed", [3, 4])
def test_hash_grid_patch_finds_exactly_the_pairs_of_a_fresh_build(seed, device):
    """Check the broad phase's patches: after a build with a margin, some particles' end points leave it
    (others move within it), twice; each time the earlier pairs without a freshly registered element plus
    the patch's pairs are exactly, and once each, the pairs a brute-force search finds on the registered
    boxes (each particle's trajectory at its reference velocity: the new one where it escaped), and they
    contain every pair of the new velocities' own boxes. The second patch also moves particles of the
    first one's elements, and elements the first one registered stay registered."""
    rng, x0, tris = random_soup(seed)
    n = len(x0)
    dt, pad, margin = 0.1, 0.01, 0.02
    grid = SelfCollisionGrid(tris, n, device, cell_size=0.05)
    xs = wp.array(x0, dtype=wp.vec3, device=device)
    ref = rng.normal(0.0, 0.3, (n, 3)).astype(np.float32)
    assert grid.refresh(xs, wp.array(ref, dtype=wp.vec3, device=device), dt, pad, margin) == "built"
    edges = unique_edges(tris)
    points = np.arange(n)[:, None]
    current = [set(map(tuple, grid.vertex_face.numpy().tolist())), set(map(tuple, grid.edge_edge.numpy().tolist()))]
    first_moved = None
    for escaping in (5, 8):
        vel = ref + rng.uniform(-1.0, 1.0, (n, 3)).astype(np.float32) * (0.5 * margin / dt / np.sqrt(3.0))  # within the margin
        moved = rng.choice(n, escaping, replace=False)
        if first_moved is not None:
            moved[0] = first_moved[0]  # a particle of the first patch escapes again
        vel[moved] += rng.normal(0.0, 1.0, (escaping, 3)).astype(np.float32)  # far outside it
        assert grid.refresh(xs, wp.array(vel, dtype=wp.vec3, device=device), dt, pad, margin) == "patched"
        ref[moved] = vel[moved]
        first_moved = moved
        np.testing.assert_array_equal(grid.reference_velocity.numpy(), ref)
        assert grid.refresh(xs, wp.array(vel, dtype=wp.vec3, device=device), dt, pad, margin) == "kept"
        for kind, (query, target, same, patch) in enumerate(((tris, points, False, grid.patch_vertex_face),
                                                             (edges, edges, True, grid.patch_edge_edge))):
            first, second = (f.numpy() for f in grid.fresh_flags(kind))
            kept = [p for p in current[kind] if first[p[0]] == 0 and second[p[1]] == 0]
            patched = [tuple(sorted(p)) if same else tuple(p) for p in patch.numpy().tolist()]
            found = kept + patched
            assert len(set(found)) == len(found), "a pair reported twice"
            registered = brute_force_pairs(x0, x0 + dt * ref, query, target, pad + margin, same)
            assert set(found) == registered
            assert brute_force_pairs(x0, x0 + dt * vel, query, target, pad, same) <= set(found)
            assert first.sum() > 0 and len(patched) > 0
            current[kind] = set(found)
    assert grid.builds == 1 and grid.patches == 2


# -- analytic CCD and impulses (physics.md 1(j)) --------------------------------------------------------

def point_triangle_model(device, *, pin_triangle, velocity, thickness=1.0e-3, point=(0.25, 0.25, 1.0), mass=0.5):
    b = cw.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_cloth_mesh(TRI, [[0, 1, 2]], material="denim")
    if pin_triangle:
        b.pin([0, 1, 2])
    b.add_particle(point, velocity=velocity, mass=mass)
    b.enable_self_collision(thickness=thickness, friction=0.0)
    return b.finalize(device)


def one_step(model, dt, **solver_options):
    solver = cw.SolverSymplecticEuler(model, strain_limit=None, **solver_options)
    s0, s1 = model.state(), model.state()
    solver.step(s0, s1, model.control(), dt)
    return solver, s0, s1


@pytest.mark.parametrize("n", [1, 1023, 1024, 1025, 40_000])
def test_allocation_free_scan_is_the_exclusive_prefix_sum(n, device):
    """The tiled scan the capturable broad phase records inside conditional graph nodes (where CUB's per-call
    temporary allocation is refused on CUDA) is np.cumsum shifted by one, at tile boundaries too; forced on the
    CPU as well so that it is checked without a GPU."""
    counts = np.random.default_rng(n).integers(0, 9, n).astype(np.int32)
    a = wp.array(counts, dtype=wp.int32, device=device)
    out = wp.full(n, -7, dtype=wp.int32, device=device)
    exclusive_scan(a, out, wp.zeros(-(-n // kb.SCAN_TILE), dtype=wp.int32, device=device), tiled=True)
    np.testing.assert_array_equal(out.numpy(), np.concatenate([[0], np.cumsum(counts)[:-1]]))


def test_point_triangle_ccd_finds_the_degenerate_cubic_root(device):
    """Point (0.25, 0.25, 1) falling at 100 m/s onto the triangle z = 0 with h = 0.1 s: f(t) = 1 - 100 t is
    linear (a3 = a2 = 0), the contact time is exactly 0.01 s (to the bisection's float32 resolution); after
    the step the point has not crossed the plane and separates at the set speed (0.1 thickness / h)."""
    h, thickness = 0.1, 1.0e-3
    m = point_triangle_model(device, pin_triangle=True, velocity=(0.0, 0.0, -100.0), thickness=thickness)
    sc = cw.SolverSymplecticEuler(m, strain_limit=None).pass_named("self_collision").self_collision
    x = m.particle_q
    vbar = wp.array(np.array([[0, 0, 0]] * 3 + [[0, 0, -100.0]], np.float32), dtype=wp.vec3, device=device)
    pairs, times = sc.first_contact_times(x, vbar, h)["vertex_face"]
    assert pairs.tolist() == [[0, 3]]
    assert times[0] == pytest.approx(0.01, abs=1e-6)
    solver, s0, s1 = one_step(m, h)
    z = s1.particle_q.numpy()[3, 2]
    vz = s1.particle_qd.numpy()[3, 2]
    assert z > 0.0  # a discrete test would leave it at z = -9 m
    # inelastic, plus the 10 %-of-thickness separation; float32: -100 + dv carries ~1 ulp(100) = 8e-6 m/s
    assert vz == pytest.approx(0.1 * thickness / h, abs=2e-5)
    assert solver.read_pass_reports()["self_collision"].self_ccd == 1


def test_edge_edge_ccd_time_and_point():
    """Edge (-1, 0, 1)-(1, 0, 1) moving down at 20 m/s over the fixed edge (0, -1, 0)-(0, 1, 0), h = 0.1 s:
    contact at t = 0.05 s (when the midpoints meet), found for exactly this edge pair; after the step edge A is
    still above edge B and its approach is stopped (the pinned edge takes no impulse)."""
    b = cw.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    # two thin triangles carry the two edges (their third vertices are far from the other edge)
    b.add_cloth_mesh(np.array([[-1.0, 0, 1], [1.0, 0, 1], [0.0, 3.0, 1.0]]), [[0, 1, 2]], velocity=(0.0, 0.0, -20.0))
    b.add_cloth_mesh(np.array([[0.0, -1.0, 0], [0.0, 1.0, 0], [0.0, 0.0, -3.0]]), [[0, 1, 2]])
    b.pin([3, 4, 5])
    b.enable_self_collision(thickness=1.0e-3, friction=0.0)
    m = b.finalize("cpu")
    sc = cw.SolverSymplecticEuler(m, strain_limit=None).pass_named("self_collision").self_collision
    vbar = m.particle_qd
    pairs, times = sc.first_contact_times(m.particle_q, vbar, 0.1)["edge_edge"]
    edges = sc.edges
    hit = [(tuple(edges[a]), tuple(edges[c]), t) for (a, c), t in zip(pairs.tolist(), times.tolist()) if t >= 0.0]
    assert len(hit) == 1
    e1, e2, t = hit[0]
    assert set(e1) | set(e2) == {0, 1, 3, 4}
    assert t == pytest.approx(0.05, abs=1e-6)
    solver, s0, s1 = one_step(m, 0.1)
    x1 = s1.particle_q.numpy()
    assert x1[0, 2] > 0.0 and x1[1, 2] > 0.0  # edge A stays above edge B
    mass = m.particle_mass.numpy()
    free = m.particle_pinned.numpy() == 0
    p0 = (mass[free, None] * s0.particle_qd.numpy()[free]).sum(0)
    p1 = (mass[free, None] * s1.particle_qd.numpy()[free]).sum(0)
    # the pinned edge takes no impulse: the free triangle alone must end with its approach stopped
    assert np.all(s1.particle_qd.numpy()[[0, 1], 2] >= -1e-4) and p1[2] > p0[2]


def test_impulse_conserves_momentum_and_sets_relative_normal_velocity():
    """A 0.5 kg point hits a free cloth triangle (unequal masses): the impulse conserves total linear
    momentum and changes the relative normal velocity at the contact's barycentric weights
    w = (1/2, 1/4, 1/4) by exactly the requested amount (from -100 m/s to the separation speed)."""
    h, thickness = 0.1, 1.0e-3
    m = point_triangle_model("cpu", pin_triangle=False, velocity=(0.0, 0.0, -100.0), thickness=thickness)
    solver, s0, s1 = one_step(m, h)
    mass = m.particle_mass.numpy().astype(np.float64)
    v0 = s0.particle_qd.numpy().astype(np.float64)
    v1 = s1.particle_qd.numpy().astype(np.float64)
    assert mass[3] != mass[0]
    assert np.allclose((mass[:, None] * v1).sum(0), (mass[:, None] * v0).sum(0), atol=1e-4 * 50.0)
    w = np.array([0.5, 0.25, 0.25])
    rel = v1[3, 2] - w @ v1[:3, 2]
    assert rel == pytest.approx(0.1 * thickness / h, abs=1e-3)
    # distribution: particle i moves by alpha_i J / m_i, the same J for all (alpha = (-w, 1))
    j = (v1[3, 2] - v0[3, 2]) * mass[3]
    assert np.allclose((v1[:3, 2] - v0[:3, 2]) * mass[:3], -w * j, rtol=1e-4)
    x1 = s1.particle_q.numpy()
    assert x1[3, 2] > w @ x1[:3, 2]  # still above the triangle


def test_proximity_repulsion_and_friction_are_exact():
    """A point 1 mm above a pinned triangle (thickness 4 mm: overlap d = 3 mm) approaching at 0.5 m/s and
    sliding at 1 m/s: the proximity pass changes its normal velocity by min(h k d / m, 0.1 d / h + 0.5)
    (the second: it never separates faster than 10 % of the overlap per step) and Coulomb friction slows
    the sliding by mu dv_N."""
    h, thickness, mu = 0.01, 4.0e-3, 0.3
    b = cw.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_cloth_mesh(TRI, [[0, 1, 2]])
    b.pin([0, 1, 2])
    b.add_particle((0.25, 0.25, 1.0e-3), velocity=(1.0, 0.0, -0.5), mass=0.01)
    b.enable_self_collision(thickness=thickness, friction=mu, stiffness=1.0e5)
    m = b.finalize("cpu")
    # the approach would take the point through the plane within the step (-5 mm): CCD must not be needed
    solver, s0, s1 = one_step(m, h)
    v = s1.particle_qd.numpy()[3].astype(np.float64)
    d = thickness - 1.0e-3
    dvn = min(h * 1.0e5 * d / 0.01, 0.1 * d / h + 0.5)
    assert v[2] == pytest.approx(-0.5 + dvn, rel=1e-4)
    assert v[0] == pytest.approx(1.0 - mu * dvn, rel=1e-4)
    counts = {k: v for r in solver.read_pass_reports().values() for k, v in r.counters().items()}
    assert counts["self_proximity"] == 1 and counts["self_ccd"] == 0


def test_taped_self_collision_gives_finite_gradients():
    """Check two taped steps of a small disc falling onto a pinned one 3 mm below (proximity and CCD
    active) backpropagate to finite, non-zero gradients of the initial velocities."""
    b = cw.ModelBuilder(gravity=(0.0, -9.81, 0.0))
    v, t = disc_mesh(0.05, 3)
    flat = cw.quat_from_axis_angle((1, 0, 0), -90.0)
    b.add_cloth_mesh(v, t, rotation=flat, position=(0.0, 0.003, 0.0))
    b.add_cloth_mesh(v, t, rotation=flat)
    b.pin(np.arange(len(v), 2 * len(v)))
    b.enable_self_collision(thickness=0.004)
    m = b.finalize("cpu", requires_grad=True)
    solver = cw.SolverSymplecticEuler(m, strain_limit=0.1, strain_limit_iterations=2)
    states = [m.state(requires_grad=True) for _ in range(3)]
    states[0].particle_qd.assign(np.tile([0.0, -1.0, 0.0], (m.particle_count, 1)).astype(np.float32))
    control = m.control()
    tape = wp.Tape()
    with tape:
        for k in range(2):
            solver.step(states[k], states[k + 1], control, 1.0 / 240.0)
    w = np.zeros((m.particle_count, 3), np.float32)
    w[:, 1] = 1.0  # d(sum of heights)/d(v0)
    tape.backward(grads={states[-1].particle_q: wp.array(w, dtype=wp.vec3)})
    g = states[0].particle_qd.grad.numpy()
    counts = {k: v for r in solver.read_pass_reports().values() for k, v in r.counters().items()}
    assert counts["self_proximity"] > 0
    assert np.all(np.isfinite(g)) and np.abs(g[: len(v)]).max() > 0.0


# -- drape coefficient -------------------------------------------------------------------------------

def test_drape_coefficient_limits():
    """Check the Cusick coefficient is 1 for a flat specimen (to the mesh's polygon area and the raster)
    and equals the pedestal-only value 0 when the specimen's shadow is just the pedestal's disc."""
    v, t = disc_mesh(0.15, 20)
    flat = v[:, [0, 2, 1]]  # horizontal (y up)
    assert drape_coefficient(flat, t, pedestal_radius=0.09, disc_radius=0.15) == pytest.approx(1.0, abs=3e-3)
    vp, tp = disc_mesh(0.09, 12)
    assert drape_coefficient(vp[:, [0, 2, 1]], tp, pedestal_radius=0.09, disc_radius=0.15) == pytest.approx(0.0, abs=6e-3)


# -- scenes, every frame checked ----------------------------------------------------------------------

def run_and_check(name, overrides, frames):
    scene = load_scene(find_scene(name), overrides)
    model = build_model(scene, "cpu")
    solver = build_solver(scene, model)
    sim = cw.Simulator(model, solver, fps=float(scene.get("output.fps")), substeps=int(scene.get("solver.substeps")))
    tris = model.tri_indices.numpy()
    totals = {}
    for f in range(frames):
        sim.step_frame()
        x = sim.positions()
        bad = intersecting_pairs(x, tris)
        assert not bad, (name, f, bad[:5])
        if model.collider_count:
            depth = penetration_depths(model, x, sim.time)
            thickness = np.array([c.thickness for c in model.colliders])
            assert np.all(depth <= thickness), (name, f, depth)  # never inside the collider itself
        for k, v in sim.frame_info.items():
            if isinstance(v, int) and not isinstance(v, bool):
                totals[k] = totals.get(k, 0) + v
    assert totals["unresolved"] == 0
    return model, sim, totals


@pytest.mark.slow
def test_pile_scene_never_self_intersects():
    """Check the pile scene with the passes after the step alone (coarsened to 20^2, the first 1.2 s: it falls over and
    folds onto itself) has
    no intersecting triangle pair in any frame and the layers touched (repulsions and CCD impacts)."""
    _, _, totals = run_and_check("pile", {**PASSES_ONLY, "cloth.grid.resolution": [20, 20]}, 72)
    assert totals["self_proximity"] > 1000 and totals["self_ccd"] > 0


@pytest.mark.slow
def test_twist_scene_never_self_intersects():
    """Check the twist scene (coarsened to 8 x 28, 2.4 s of wringing) stays intersection-free in every frame
    while the strip coils onto itself."""
    _, _, totals = run_and_check("twist", {"cloth.grid.resolution": [8, 28]}, 144)
    assert totals["self_proximity"] > 100


@pytest.mark.slow
def test_drape_sphere_scene_never_self_intersects():
    """Check the drape over a sphere with the passes after the step alone (coarsened to 20^2, 1.5 s: the corners fold
    onto the floor) stays intersection-free and outside both colliders in every frame."""
    run_and_check("drape_sphere", {**PASSES_ONLY, "cloth.grid.resolution": [20, 20]}, 90)


@pytest.mark.slow
def test_cusick_scene_drapes_without_intersections(tmp_path):
    """Check the Cusick drape (coarsened to 10 rings, 1 s) stays intersection-free and outside the
    pedestal in every frame, and that the run reports a drape coefficient between 0 and 1 (in the
    summary and the cache's metadata) and the self-collision counters per frame."""
    overrides = {"cloth.disc.rings": 10}
    run_and_check("cusick", overrides, 30)
    scene = load_scene(find_scene("cusick"), overrides)
    summary = cw.run_scene(scene, output=tmp_path / "cusick.usdc", frames=30)
    assert summary["status"] == "complete" and 0.0 < summary["drape_coefficient"] < 1.0
    reader = cw.CacheReader(tmp_path / "cusick.usdc")
    assert reader.metadata["drape_coefficient"] == pytest.approx(summary["drape_coefficient"])
    assert reader.diagnostics()["selfSweeps"][1].min() > 0
    assert math.isfinite(summary["drape_coefficient"])


@pytest.mark.slow
@pytest.mark.parametrize("name,resolution,frames", [("pile", 20, 72), ("drape_sphere", 20, 90)])
def test_contacts_in_the_solve_never_self_intersect(name, resolution, frames):
    """Check the pile and the drape over a sphere as shipped, the collider contacts, the self-contacts and their friction
    in the implicit solve (coarsened, the first 1.2-1.5 s), have no intersecting triangle pair and no particle inside a
    collider in any frame: the passes after the solve remain the guarantee; and the solve held self-contacts."""
    _, _, totals = run_and_check(name, {"cloth.grid.resolution": [resolution, resolution]}, frames)
    assert totals["solve_self_contacts"] > 0 and totals["solve_contacts"] > 0
