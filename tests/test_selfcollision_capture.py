"""Self-collision's capturable path: a step recorded once as a CPU graph (wp.ScopedCapture) and replayed gives,
bit for bit, what the same path gives run eagerly, close to the host path and without intersecting
triangles; fixed-capacity buffers that are too small report the need, grow and give the run of large
enough ones; impacts left after the CCD sweeps form rigid impact zones on the device, as the host path's.

The driver: the implicit integrator proposes each step's end (eagerly, outside the graph); the graph
holds the self-collision pass only: begin_step, a first round, and a second round from the same start
(as the solver's limiter / collision rounds: it resumes on the pairs the first round changed)."""

import numpy as np
import pytest
import warp as wp
from intersections import intersecting_pairs

import cloth_warp as cw
from cloth_warp.selfcollision import SelfCollision

DT = 1.0 / 120.0
FLAT = cw.quat_from_axis_angle((1, 0, 0), -90.0)


def two_sheets(res: int = 16, drop_speed: float = 1.0, tilt: float = 12.0, device: str = "cpu"):
    """A 0.3 m trampoline (res^2, its border pinned) and a tilted 0.2 m sheet 2 cm above it falling at
    `drop_speed` [m/s]: one cloth model, so the sheets meet through self-collision only."""
    b = cw.ModelBuilder()
    lower = b.add_cloth_grid(resolution=(res, res), size=(0.3, 0.3), rotation=FLAT, position=(-0.15, 0.0, 0.15))
    for edge in ("edge:left", "edge:right", "edge:top", "edge:bottom"):
        b.pin(lower.select(edge))
    tilted = cw.quat_from_axis_angle((1, 0, 0), -90.0 + tilt)
    b.add_cloth_grid(resolution=(res, res), size=(0.2, 0.2), rotation=tilted, position=(-0.1, 0.02, 0.1),
                     velocity=(0.0, -drop_speed, 0.0))
    b.enable_self_collision(thickness=0.004)
    return b.finalize(device)


class Driver:
    """Steps a model with its implicit integrator and a SelfCollision pass on fixed arrays, eagerly or by
    replaying a graph of the pass recorded at the first step."""

    def __init__(self, model, sc: SelfCollision, rounds: int = 2):
        self.model, self.sc, self.rounds = model, sc, rounds
        self.solver = cw.SolverImplicitEuler(model, strain_limit=None)
        self.states = [model.state(), model.state()]
        self.control = model.control()
        n = model.particle_count
        self.x_start, self.x_end, self.v_end, self.x_out, self.v_out = (wp.zeros(n, dtype=wp.vec3, device=model.device) for _ in range(5))
        self.graph = None

    def collide(self):
        self.sc.begin_step()
        for _ in range(self.rounds):
            self.sc.apply(self.x_start, self.x_end, self.v_end, DT, self.x_out, self.v_out)

    def capture(self):
        """Record the pass (after an eager call has allocated its buffers; its counts and the broad phase it registered
        are dropped, so the replay builds where the eager run does)."""
        self.collide()
        self.sc.reset_counts()
        self.sc._forget_registration()
        with wp.ScopedCapture(device=self.model.device) as cap:
            self.collide()
        self.graph = cap.graph

    def propose(self):
        s0 = self.states[0]
        wp.copy(self.x_start, s0.particle_q)
        self.solver.integrate(s0, self.x_end, self.v_end, self.control, DT)

    def finish(self):
        s1 = self.states[1]
        wp.copy(s1.particle_q, self.x_out)
        wp.copy(s1.particle_qd, self.v_out)
        self.states.reverse()

    def step(self, graph: bool = False):
        self.propose()
        if graph:
            if self.graph is None:
                self.capture()
            wp.capture_launch(self.graph)
        else:
            self.collide()
        self.finish()

    def positions(self) -> np.ndarray:
        return self.states[0].particle_q.numpy()


def run(model, steps: int, graph: bool, check=None, host: SelfCollision | None = None, **options):
    """Positions after each of `steps` steps; with `host`, also that pass's result on each step's same inputs."""
    sc = SelfCollision(model, **options)
    d = Driver(model, sc)
    tris = model.tri_indices.numpy().reshape(-1, 3)
    out, beside = [], []
    for _ in range(steps):
        d.propose()
        if host is not None:
            host.begin_step()
            xo, vo = wp.empty_like(d.x_out), wp.empty_like(d.v_out)
            for _ in range(d.rounds):
                host.apply(d.x_start, d.x_end, d.v_end, DT, xo, vo)
            beside.append(xo.numpy())
        if graph:
            if d.graph is None:
                d.capture()
            wp.capture_launch(d.graph)
        else:
            d.collide()
        d.finish()
        out.append(d.positions().copy())
        if check is not None:
            assert not intersecting_pairs(out[-1], tris), len(out)
    return out, sc, beside


def test_recorded_step_replays_the_eager_capturable_path_bit_for_bit():
    """Check 24 steps of a sheet dropped at 1 m/s onto a pinned one: the capturable pass recorded once with
    wp.ScopedCapture on the CPU and replayed gives bit for bit the positions of the same pass run eagerly (CPU
    launches run their threads in order, so atomics add up in the same order in both; the CCD loop and the
    broad phase's rebuild run as recorded conditional nodes), the same counters, no intersecting triangles,
    and needs no re-run. On each step's same inputs the host path agrees to 1e-6 m (it patches its broad
    phase where this path builds it again, so impulses may add up in another order: round-off, which the
    contacts of later steps would amplify, hence the per-step comparison) with the same contact counts
    within 1 %."""
    model = two_sheets()
    steps = 24
    capacity = 1 << 14  # holds this scene's candidate pairs (the overflow test starts small)
    host = SelfCollision(model)
    eager, sc_eager, host_out = run(model, steps, graph=False, host=host, capturable=True, pair_capacity=capacity)
    replay, sc_graph, _ = run(model, steps, graph=True, check=intersecting_pairs, capturable=True, pair_capacity=capacity)
    for k in range(steps):
        np.testing.assert_array_equal(replay[k], eager[k], err_msg=f"step {k}")
        np.testing.assert_allclose(eager[k], host_out[k], rtol=0.0, atol=1e-6, err_msg=f"step {k}")
    status, counts = sc_graph.read_report()
    assert not status.needs_rerun, status
    assert counts == sc_eager.read_counts()  # (the eager call made at recording time was reset)
    assert counts["self_ccd"] > 0 and counts["self_proximity"] > 0 and counts["self_sweeps"] > 0, counts
    host_counts = host.read_counts()
    for name in ("self_ccd", "self_proximity"):
        assert counts[name] == pytest.approx(host_counts[name], rel=0.01), (counts, host_counts)


def test_too_small_buffers_overflow_then_grow_to_the_result_of_large_ones():
    """Check candidate-pair buffers of 16 and an edge grid of 64 entries overflow on the first recorded step: the
    status names them with their needs (more than the capacity), the frame is flagged for a re-run; after
    grow() (powers of two above the needs), a new recording and a re-run (again while a buffer filled from a
    clipped one overflows in turn), the status is clean and the replayed run equals bit for bit an
    uncaptured run of buffers created with those capacities."""
    model = two_sheets()
    steps = 12
    sc = SelfCollision(model, capturable=True, pair_capacity=16)
    sc.grid.edges._allocate_entries(64)
    d = Driver(model, sc)
    d.propose()
    d.capture()
    wp.capture_launch(d.graph)
    status = sc.status()
    assert status.needs_rerun and {"vertex_face", "edges"} <= set(status.overflow), status
    overflowed, out, entries = set(), [], None
    for k in range(steps):
        if k:
            d.propose()
            wp.capture_launch(d.graph)
            status = sc.status()
        for _ in range(4):  # a buffer filled from a clipped one (pairs from an incomplete grid) may overflow next
            if not status.needs_rerun:
                break
            for name, (needed, capacity) in status.overflow.items():
                assert needed > capacity == sc.capacities()[name]
            overflowed |= set(status.overflow)
            assert sc.grow(status)
            caps = sc.capacities()
            for name, (needed, _) in status.overflow.items():
                assert caps[name] >= needed and caps[name] & (caps[name] - 1) == 0
            sc.reset_counts()
            d.capture()  # the arrays are new: record again, and re-run the step (its inputs are intact)
            wp.capture_launch(d.graph)
            status = sc.status()
        assert not status.needs_rerun, (k, status)
        sc.reset_counts()
        d.finish()
        out.append(d.positions().copy())
        entries = entries or {name: sc.capacities()[name] for name in ("points", "edges")}
    caps = sc.capacities()
    assert overflowed == {"vertex_face", "edge_edge", "edges"}, overflowed
    assert entries == {name: caps[name] for name in entries}  # the hash tables kept their size after the first step
    ref = SelfCollision(model, capturable=True, pair_capacity=min(caps["vertex_face"], caps["edge_edge"]))
    ref.grid.edges._allocate_entries(caps["edges"])
    ref.grid.grow(caps)
    assert ref.capacities() == caps
    d_ref = Driver(model, ref)
    for k in range(steps):
        d_ref.step()
        np.testing.assert_array_equal(d_ref.positions(), out[k], err_msg=f"step {k}")


def test_impacts_left_after_the_sweeps_form_rigid_impact_zones_on_the_device():
    """Check a sheet hitting the pinned one at 6 m/s with a single CCD sweep: impacts remain after the sweep, and the
    capturable path resolves them itself with rigid impact zones on the device (no re-run asked): the same zones,
    impacts and positions as the host path's numpy zones on each step's same inputs (both move the zones with the
    same float64 kernels; 1e-6 m allows for the order in which impulses of differently ordered candidate lists
    add up), no step unresolved, no intersecting triangles, and a recorded step replays the eager one bit for bit."""
    model = two_sheets(drop_speed=6.0, tilt=3.0)
    host = SelfCollision(model, sweeps=1, pair_capacity=1 << 15)
    options = dict(sweeps=1, capturable=True, pair_capacity=1 << 15)
    eager, sc, beside = run(model, 12, graph=False, check=True, host=host, **options)
    counts, host_counts = sc.read_counts(), host.read_counts()
    assert not sc.status().needs_rerun
    assert counts["impact_zones"] > 10 and counts["impact_zone_particles"] > 100 and counts["unresolved"] == 0, counts
    for key in ("impact_zones", "impact_zone_particles", "self_ccd", "unresolved"):
        assert counts[key] == host_counts[key], key
    for k in range(12):
        np.testing.assert_allclose(eager[k], beside[k], atol=1e-6, rtol=0, err_msg=f"step {k}")
    recorded, _, _ = run(model, 12, graph=True, **options)
    for k in range(12):
        np.testing.assert_array_equal(recorded[k], eager[k], err_msg=f"step {k}")


def test_impact_zones_resolve_inside_a_recorded_step_on_every_device(device):
    """Check the 6 m/s sheets on each device with the pass recorded as a graph (on CUDA: the zones' while -> if ->
    while conditional nodes inside the CCD loop's): every impact left after the single sweep is resolved inside
    the graph (no re-run asked, none unresolved, zones formed), no step ends with intersecting triangles, and each
    step agrees with the host path's numpy zones on the same inputs to 1e-5 m (CUDA adds impulses in any order)."""
    if device != "cpu" and not wp.is_conditional_graph_supported():
        pytest.skip("this CUDA driver records no conditional nodes")
    model = two_sheets(drop_speed=6.0, tilt=3.0, device=device)
    host = SelfCollision(model, sweeps=1, pair_capacity=1 << 15)
    recorded, sc, beside = run(model, 12, graph=True, check=True, host=host, sweeps=1, capturable=True,
                               pair_capacity=1 << 15)
    counts = sc.read_counts()
    assert not sc.status().needs_rerun
    assert counts["impact_zones"] > 10 and counts["impact_zone_particles"] > 100 and counts["unresolved"] == 0, counts
    for k in range(12):
        np.testing.assert_allclose(recorded[k], beside[k], atol=1e-5, rtol=0, err_msg=f"step {k}")


def test_broad_phase_patch_finds_the_close_pairs_of_a_full_build():
    """Check the capturable path's device-side patch: after a build, a few particles' end points moved past the
    margin are patched (no build), and the close pairs then are, as a set, those of a full build on the same
    registered trajectories (the escaped particles' new velocities, the others' old ones), so the patch neither
    loses nor invents a pair; more escaped particles than ``patch_limit`` build the broad phase again."""
    model = two_sheets()
    sc = SelfCollision(model, capturable=True, pair_capacity=1 << 14)
    d = Driver(model, sc)
    for _ in range(10):  # the sheets meet
        d.step()
    d.propose()
    x = d.x_start
    vbar = (d.x_end.numpy() - x.numpy()) / DT
    pad = 0.5 * sc.thickness
    f = sc._fixed_buffers()

    def close_sets():
        return [{tuple(p) for p in f.close[kind].numpy()[: int(f.close_count[kind].numpy()[0])]} for kind in (0, 1)]

    rng = np.random.default_rng(3)
    for limit, escaped in ((32, 6), (4, 6)):
        sc.patch_limit = limit
        sc._build_fixed(x, wp.array(vbar, dtype=wp.vec3), DT, pad)
        built = close_sets()
        assert sum(len(s) for s in built) > 0
        sc.reset_counts()
        moved = vbar.copy()
        ids = rng.choice(np.arange(16 * 16, model.particle_count), escaped, replace=False)  # the falling sheet's particles
        push = rng.normal(size=(escaped, 3))
        moved[ids] += 3.0 * sc.margin / DT * push / np.linalg.norm(push, axis=1, keepdims=True)
        sc._refresh_fixed(x, wp.array(moved, dtype=wp.vec3), DT, pad)
        counts = sc.read_counts()
        patched = close_sets()
        registered = wp.clone(sc.grid.fixed_reference)
        np.testing.assert_array_equal(registered.numpy()[ids], moved[ids].astype(np.float32))
        if escaped > limit:
            assert counts["broad_phase_builds"] == 1 and counts["broad_phase_patches"] == 0, counts
            continue
        assert counts["broad_phase_builds"] == 0 and counts["broad_phase_patches"] == 1, counts
        assert patched != built  # the moved particles changed the candidates
        sc._build_fixed(x, registered, DT, pad)
        assert close_sets() == patched
        assert not sc.status().needs_rerun


def test_broad_phase_is_kept_across_steps_while_the_trajectories_stay_within_the_margin():
    """Check the capturable path keeps its broad phase from step to step, on two flat sheets at rest registered 1.95
    margins farther apart than the close reach: later steps whose start and end points all moved less than the margin
    keep it (no build, no patch): both sheets 0.99 margins toward each other (now within the reach), also with random
    drifts sideways, and its close pairs then hold every pair that comes within the close reach in the step (none is lost);
    a particle moved past the margin while the others drift away is patched, and when they then drift toward each
    other the close pairs again hold every pair within reach; another step size builds it again."""

    model = two_sheets()
    sc = SelfCollision(model, capturable=True, pair_capacity=1 << 14)
    tris = model.tri_indices.numpy().reshape(-1, 3)
    edges = sc.edges
    bary = np.array([(a, b, 1.0 - a - b) for a in np.linspace(0, 1, 13) for b in np.linspace(0, 1, 13) if a + b <= 1.0 + 1e-9])
    along = np.linspace(0.0, 1.0, 13)
    reach, margin = sc.close_reach(), sc.margin

    def within_reach(x):
        """Every pair of each kind (no shared vertex) whose elements are within the close reach at rest at x (distances
        between points sampled on the elements: never below the true distance, so each pair found is truly within;
        boxes farther apart than the reach skipped)."""
        out = [set(), set()]
        corners = [x[tris], x[edges]]
        for kind, first in enumerate(corners):
            second = x[:, None] if kind == 0 else corners[1]
            lo, hi = second.min(axis=1), second.max(axis=1)
            for a, rows in enumerate(first):
                gap = np.maximum(np.maximum(rows.min(axis=0) - hi, lo - rows.max(axis=0)), 0.0)
                near = np.flatnonzero(np.linalg.norm(gap, axis=1) <= reach)
                own = tris[a] if kind == 0 else edges[a]
                points = bary @ rows if kind == 0 else rows[0] + along[:, None] * (rows[1] - rows[0])
                for b in near:
                    other = [b] if kind == 0 else edges[b]
                    if (kind == 1 and b <= a) or set(other) & set(own):
                        continue
                    samples = x[b][None] if kind == 0 else second[b][0] + along[:, None] * (second[b][1] - second[b][0])
                    if np.min(np.linalg.norm(points[:, None] - samples[None], axis=2)) <= reach:
                        out[kind].add((a, int(b)))
        return out

    def close_set():
        f = sc._fixed
        return [{tuple(int(v) for v in p) for p in f.close[kind].numpy()[: int(f.close_count[kind].numpy()[0])]} for kind in (0, 1)]

    def refresh(x, dt=DT):
        sc.reset_counts()
        sc._refresh_fixed(wp.array(x, dtype=wp.vec3), wp.zeros(model.particle_count, dtype=wp.vec3), dt, pad)
        counts = sc.read_counts()
        return counts["broad_phase_builds"], counts["broad_phase_patches"]

    lower = np.arange(model.particle_count) < 17 * 17
    x0 = model.particle_q.numpy().astype(np.float64)
    # the upper sheet flat above the lower one (at y = 0), farther than the reach plus twice the margin less the reach's
    # excess over the thickness: boxes grown by half the thickness (and the margin) would not overlap
    x0[~lower, 1] = reach + 1.95 * margin
    toward = np.where(lower[:, None], 1.0, -1.0) * np.array([0.0, 0.99 * margin, 0.0])
    pad = 0.5 * max(sc.thickness, reach)  # as the pass grows its boxes
    sc._fixed_buffers()
    sc._build_fixed(wp.array(x0, dtype=wp.vec3), wp.zeros(model.particle_count, dtype=wp.vec3), DT, pad)
    assert within_reach(x0) == [set(), set()]
    registered = close_set()
    rng = np.random.default_rng(7)
    sideways = 0.07 * margin * rng.uniform(-1.0, 1.0, size=x0.shape) * np.array([1.0, 0.0, 1.0])
    for x in (x0 + toward, x0 + toward + sideways):
        assert refresh(x) == (0, 0)
        assert close_set() == registered
        needed = within_reach(x)
        assert needed[0] and needed[1]
        for held, kind_needed in zip(registered, needed):
            assert kind_needed <= held, len(kind_needed - held)
    # a particle of the upper sheet past the margin, the others drifting apart: patched
    escaped = 17 * 17 + 8 * 17 + 8
    apart = x0 - toward
    apart[escaped, 0] += 3.0 * margin
    assert refresh(apart) == (0, 1)
    closer = x0 + toward  # then toward each other again (the patched particle where it was patched)
    closer[escaped] = apart[escaped]
    assert refresh(closer) == (0, 0)
    for held, kind_needed in zip(close_set(), within_reach(closer)):
        assert kind_needed <= held, len(kind_needed - held)
    assert refresh(closer, 0.5 * DT) == (1, 0)  # registered for DT only


def reference_rigid_motion(x0, v, mass, free, dt):
    """Provot's rigid step of one zone in numpy (float64): about the centre of mass of its free members, omega from
    I omega = L by least squares, Rodrigues' rotation; the free members' average velocities over the step."""
    m = mass[free][:, None]
    xc = (m * x0[free]).sum(0) / m.sum()
    vc = (m * v[free]).sum(0) / m.sum()
    r = x0[free] - xc
    angular = (m * np.cross(r, v[free] - vc)).sum(0)
    inertia = (m[:, :, None] * ((r * r).sum(1)[:, None, None] * np.eye(3) - r[:, :, None] * r[:, None, :])).sum(0)
    omega = np.linalg.lstsq(inertia, angular, rcond=1e-12)[0]
    angle = np.linalg.norm(omega) * dt
    k = omega / max(np.linalg.norm(omega), 1e-300)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rot = np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx
    return (xc + dt * vc + r @ rot.T - x0[free]) / dt


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_zone_motion_matches_a_numpy_reference_and_follows_pinned_members(seed):
    """The device's rigid impact-zone motion (float64 sums per zone, shared by both paths) against a numpy reference on
    random velocities: a zone of free particles gets Provot's rigid step (linear and angular momentum), a zone with
    pinned particles that move rigidly gets exactly their rigid motion, a zone of pinned particles only and the
    particles in no zone keep their velocities. Also a collinear zone (an edge and a point on its line: a singular
    inertia tensor) stays finite and keeps its linear momentum."""
    rng = np.random.default_rng(seed)
    model = two_sheets(res=8)
    sc = SelfCollision(model)
    n = model.particle_count
    x0 = model.particle_q.numpy().astype(np.float64)
    v = rng.normal(scale=0.5, size=(n, 3))
    mass = model.particle_mass.numpy().astype(np.float64)
    pinned = model.particle_pinned.numpy() != 0
    label = np.full(n, -1)
    free_zone = rng.choice(np.flatnonzero(~pinned), 12, replace=False)
    label[free_zone] = free_zone.min()
    ring = np.array([0, 1, 2, 9, 18, 27])  # pinned border particles of the lower sheet (9 x 9), on two sides: not collinear
    assert pinned[ring].all()
    mixed = np.concatenate([ring, np.setdiff1d(np.flatnonzero(~pinned)[:9], free_zone)[:5]])
    label[mixed] = mixed.min()
    only_pinned = np.flatnonzero(pinned)[10:13]
    label[only_pinned] = only_pinned.min()
    # the pinned members move rigidly: rotation about a random axis and a translation
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(0.3) * kx + (1.0 - np.cos(0.3)) * kx @ kx
    shift = rng.normal(scale=0.01, size=3)
    centre = x0[mixed].mean(0)
    rigid = (centre + shift + (x0[mixed] - centre) @ rot.T - x0[mixed]) / DT
    v[ring] = rigid[: len(ring)]
    out = wp.array(v.astype(np.float32), dtype=wp.vec3)
    vbar = wp.array(v.astype(np.float32), dtype=wp.vec3)
    sc._zone_motion(wp.array(label.astype(np.int32), dtype=wp.int32), model.particle_q, vbar, DT, out)
    got = out.numpy().astype(np.float64)
    v32 = v.astype(np.float32).astype(np.float64)
    ref = reference_rigid_motion(x0[free_zone], v32[free_zone], mass[free_zone], np.ones(len(free_zone), bool), DT)
    np.testing.assert_allclose(got[free_zone], ref, atol=1e-5, rtol=1e-5)
    momentum = (mass[free_zone, None] * got[free_zone]).sum(0)
    np.testing.assert_allclose(momentum, (mass[free_zone, None] * v32[free_zone]).sum(0), atol=1e-6 * np.abs(momentum).max())
    np.testing.assert_allclose(got[mixed], rigid, atol=2e-3 * np.abs(rigid).max())  # pinned: float32 inputs of a 0.3 rad turn
    others = label < 0
    np.testing.assert_array_equal(got[others], v.astype(np.float32)[others])
    np.testing.assert_array_equal(got[only_pinned], v.astype(np.float32)[only_pinned])
    # a collinear zone: two particles of a row and the one between them
    line = np.array([0, 1, 2]) + 8 * 9  # a row of the free sheet (9 x 9 particles after the 9 x 9 lower one)
    label = np.full(n, -1)
    label[line] = line.min()
    out = wp.array(v.astype(np.float32), dtype=wp.vec3)
    sc._zone_motion(wp.array(label.astype(np.int32), dtype=wp.int32), model.particle_q, vbar, DT, out)
    got = out.numpy().astype(np.float64)
    assert np.isfinite(got).all()
    np.testing.assert_allclose((mass[line, None] * got[line]).sum(0), (mass[line, None] * v32[line]).sum(0), atol=1e-7)


@pytest.mark.parametrize("seed", [0, 1])
def test_zone_labels_on_the_device_are_the_connected_components(seed):
    """The capturable path's label propagation (flagged pairs, two rounds: zones persist and merge) ends at the
    connected components that the host path's numpy ``connected_labels`` gives, each named by its smallest particle."""
    from cloth_warp.selfcollision import connected_labels
    from cloth_warp.graphs import device_while
    from cloth_warp.kernels import selfcollide as ksc

    rng = np.random.default_rng(seed)
    model = two_sheets(res=8)
    sc = SelfCollision(model, capturable=True, pair_capacity=256)
    f = sc._fixed_buffers()
    n = model.particle_count
    tris = model.tri_indices.numpy().reshape(-1, 3)
    edges = sc.edges
    links = np.zeros((0, 2), np.int64)
    for _ in range(2):
        pairs, quads = [], []
        for kind, (count, elements) in enumerate(((40, len(tris)), (30, len(edges)))):
            first = rng.integers(0, elements, count)
            second = rng.integers(0, n if kind == 0 else len(edges), count)
            hit = (rng.random(count) < 0.3).astype(np.int32)
            p = np.column_stack([first, second]).astype(np.int32)
            f.close[kind].assign(np.concatenate([p, np.zeros((f.close[kind].shape[0] - count, 2), np.int32)]))
            f.close_count[kind].fill_(count)
            f.hits[kind].assign(np.concatenate([hit, np.zeros(f.hits[kind].shape[0] - count, np.int32)]))
            sel = p[hit != 0]
            quads.append(np.column_stack([tris[sel[:, 0]], sel[:, 1]]) if kind == 0 else np.column_stack([edges[sel[:, 0]], edges[sel[:, 1]]]))
        q = np.concatenate(quads)
        links = np.concatenate([links, np.column_stack([np.repeat(q[:, 0], 3), q[:, 1:].ravel()])])
        wp.launch(ksc.set_flag, dim=1, inputs=[1], outputs=[f.link_changed])
        device_while(f.link_changed, sc._link_zones_fixed)
        label = f.zone.numpy()
        np.testing.assert_array_equal(np.where(label == int(ksc.ZONE_NONE), -1, label), connected_labels(links, n))


def test_a_welded_sewn_point_joins_an_impact_zone_whole():
    """Check the capturable path's zone joining with welded sewn points (two panels sewn by a closed seam): a colliding
    pair that holds one particle of a sewn point brings every particle of that point into its zone, as the host path's
    rule does (the weld's links of every point a zone touches, then connected components)."""
    from test_sewing import hanging_sewn

    from cloth_warp.graphs import device_while
    from cloth_warp.kernels import selfcollide as ksc
    from cloth_warp.selfcollision import connected_labels

    model, _ = hanging_sewn()
    sc = SelfCollision(model, capturable=True, pair_capacity=64)
    assert sc.weld is not None
    roots = sc.weld.roots
    n = model.particle_count
    tris = model.tri_indices.numpy().reshape(-1, 3)
    sewn = np.flatnonzero(roots >= 0)
    tri = next(t for t in range(len(tris)) if np.isin(tris[t], sewn).sum() == 1)  # a triangle with one sewn corner
    point = next(p for p in range(n) if roots[p] < 0 and not np.isin(p, tris[tri]))
    f = sc._fixed_buffers()
    f.close[0].assign(np.concatenate([[[tri, point]], np.zeros((f.close[0].shape[0] - 1, 2), np.int64)]).astype(np.int32))
    f.close_count[0].fill_(1)
    f.hits[0].assign(np.concatenate([[1], np.zeros(f.hits[0].shape[0] - 1, np.int32)]).astype(np.int32))
    f.close_count[1].fill_(0)
    wp.launch(ksc.set_flag, dim=1, inputs=[1], outputs=[f.link_changed])
    device_while(f.link_changed, sc._link_zones_fixed)
    label = f.zone.numpy()
    label = np.where(label == int(ksc.ZONE_NONE), -1, label)
    quad = np.array([*tris[tri], point])
    links = np.column_stack([np.repeat(quad[0], 3), quad[1:]])
    rows = sc.weld.links()
    touched = np.isin(rows, links).any(axis=1)
    links = np.concatenate([links, rows[np.isin(rows[:, 1], rows[touched, 1])]])
    np.testing.assert_array_equal(label, connected_labels(links, n))
    corner = quad[np.isin(quad, sewn)][0]
    point_members = np.flatnonzero(roots == roots[corner])
    assert len(point_members) >= 2 and (label[point_members] == label[corner]).all()
