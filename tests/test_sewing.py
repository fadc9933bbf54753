"""The sewing pass (cloth_warp.sewing): seams closed at the start are welded, their particles moving as one point."""

import numpy as np
import pytest
import warp as wp

import cloth_warp as cw
from cloth_warp.sewing import WELD_DISTANCE, SewingPass, seam_ends, seam_gap, welded_point_roots


def two_panels(gap_cm=0.05, size_cm=10.0):
    """Two square panels side by side in the plane z = 0, `gap_cm` apart, the right edge of "a" sewn to the left edge
    of "b" (centimetres, GarmentCode's specification)."""
    def panel(x):
        s = size_cm
        return {"translation": [x, 100.0, 0.0], "rotation": [0.0, 0.0, 0.0], "vertices": [[0, 0], [s, 0], [s, s], [0, s]],
                "edges": [{"endpoints": [0, 1]}, {"endpoints": [1, 2]}, {"endpoints": [2, 3]}, {"endpoints": [3, 0]}]}

    return {"pattern": {"panels": {"a": panel(0.0), "b": panel(size_cm + gap_cm)},
                        "stitches": [[{"panel": "a", "edge": 1}, {"panel": "b", "edge": 3}]]},
            "properties": {"units_in_meter": 100}}


def hanging_sewn(gap_cm=0.05, size_cm=10.0, edge=0.025, material="cotton", requires_grad=False):
    """Panel "a" pinned along its top, "b" hanging from it by the seam only."""
    b = cw.ModelBuilder()
    ref = b.add_cloth_pattern(two_panels(gap_cm, size_cm), edge_length=edge, material=material, name="panels")
    x = np.asarray(b.particle_positions)
    top = ref.indices()[(x[ref.indices(), 1] > 1.0 + size_cm / 100.0 - 1e-3) & (x[ref.indices(), 0] < size_cm / 100.0 - 1e-3)]
    b.pin(top)
    return b.finalize("cpu", requires_grad=requires_grad), ref


def run_gaps(model, frames=20, weld=True):
    solver = cw.SolverImplicitEuler(model)
    if not weld:
        solver.passes = tuple(p for p in solver.passes if p.name != "sewing")
    sim = cw.Simulator(model, solver, fps=60, substeps=2)
    ends = seam_ends(model)
    gaps = []
    for _ in range(frames):
        sim.step_frame()
        gaps.append(seam_gap(model, sim.positions(), ends))
    return np.array(gaps)


def test_a_closed_seam_stays_closed_under_load_where_its_springs_alone_open():
    """Check a 60 cm denim panel hanging from another by a seam closed at the start (0.5 mm): welded, the sewn points
    stay one point (< 1 um apart) in every frame; with the seam springs alone (the pass removed) the seam carries the
    hanging panel's weight by stretching, measured 0.6-1.0 mm open."""
    model, ref = hanging_sewn(size_cm=60.0, edge=0.05, material="denim")
    solver = cw.SolverImplicitEuler(model)
    assert solver.pass_named("sewing") is not None and solver.pass_named("sewing").welded_points == len(ref.seams)
    welded = run_gaps(model)
    springs = run_gaps(model, weld=False)
    assert welded.max() < 1e-6, welded.max()
    assert springs[5:].min() > 0.4e-3, springs  # the evidence that the weld does something
    assert springs.max() < 5e-3  # (and that the springs do hold it: the comparison is fair)


def test_the_weld_keeps_momentum_and_a_pinned_particle_holds_its_point():
    """Check one application of the pass on random positions and velocities: each welded point's particles end at one
    position with one velocity; a free point keeps its mass-weighted mean position and momentum; a point with a pinned
    particle goes where that particle is, with its velocity; unsewn particles are copied."""
    model, ref = hanging_sewn()
    pinned = model.particle_pinned.numpy().copy()
    ends = seam_ends(model)
    pinned[ends[0, 0]] = 1  # pin one sewn particle (the model's pins are all on panel a's top, not sewn)
    model.particle_pinned.assign(pinned)
    rng = np.random.default_rng(3)
    n = model.particle_count
    x = (model.particle_q.numpy() + rng.normal(scale=2e-3, size=(n, 3))).astype(np.float32)
    v = rng.normal(size=(n, 3)).astype(np.float32)
    sewing = SewingPass(model)
    xo, vo = (wp.zeros(n, dtype=wp.vec3) for _ in range(2))
    sewing.apply(model.particle_q, wp.array(x, dtype=wp.vec3), wp.array(v, dtype=wp.vec3), None, 1e-3, xo, vo)
    xo, vo = xo.numpy(), vo.numpy()
    m = model.particle_mass.numpy()
    roots = welded_point_roots(model)
    for r in np.unique(roots[roots >= 0]):
        g = np.nonzero(roots == r)[0]
        np.testing.assert_allclose(xo[g], xo[g[:1]].repeat(len(g), 0), atol=1e-7)
        np.testing.assert_allclose(vo[g], vo[g[:1]].repeat(len(g), 0), atol=1e-6)
        held = g[pinned[g] != 0]
        if len(held):
            np.testing.assert_allclose(xo[g[0]], x[held[0]], atol=1e-7)
            np.testing.assert_allclose(vo[g[0]], v[held[0]], atol=1e-6)
        else:
            np.testing.assert_allclose(xo[g[0]], (m[g, None] * x[g]).sum(0) / m[g].sum(), atol=1e-6)
            np.testing.assert_allclose((m[g, None] * vo[g]).sum(0), (m[g, None] * v[g]).sum(0), rtol=1e-5, atol=1e-7)
    free = roots < 0
    np.testing.assert_array_equal(xo[free], x[free])
    np.testing.assert_array_equal(vo[free], v[free])


@pytest.mark.parametrize("gap_cm", [0.2, 5.0])
def test_a_seam_open_at_the_start_is_left_to_its_springs(gap_cm):
    """Check panels sewn 2 mm or 5 cm apart (wider than the weld distance): no point is welded (closing a seam point by
    point would lock the closed part rigid), and the springs still pull the seam shut."""
    assert gap_cm * 1e-2 > WELD_DISTANCE
    model, _ = hanging_sewn(gap_cm)
    assert (welded_point_roots(model) < 0).all()
    assert cw.SolverImplicitEuler(model).pass_named("sewing") is None
    gaps = run_gaps(model, frames=40)
    assert gaps[-1] < 0.1 * gap_cm * 1e-2, gaps


def test_an_implicit_step_is_continuous_as_a_seam_closes_exactly():
    """Check an implicit step from a sewn point whose particles coincide exactly against one from 1e-7 m apart: the same
    end state to ~1e-6 m (a zero-length spring's stiffness block is k I at its rest, not zero: with zero, a welded
    seam had no stiffness in the solve, its sides parted by a centimetre a step and the weld tore the cloth beside). The
    solves go to 1e-6: at the default 1e-3 the two may stop at different CG iterations, ~1e-4 m apart."""
    model, ref = hanging_sewn()
    ends = seam_ends(model)
    x = model.particle_q.numpy().astype(np.float64)
    out = []
    for gap in (0.0, 1e-7):
        y = x.copy()
        middle = 0.5 * (y[ends[:, 0]] + y[ends[:, 1]])
        y[ends[:, 0]] = middle
        y[ends[:, 1]] = middle + np.array([gap, 0.0, 0.0])
        solver = cw.SolverImplicitEuler(model, strain_limit=None, tolerance=1e-6)
        solver.passes = ()
        s0, s1 = model.state(), model.state()
        s0.particle_q.assign(y.astype(np.float32))
        for _ in range(3):
            solver.step(s0, s1, model.control(), 1.0 / 120.0)
            s0, s1 = s1, s0
        out.append(s0.particle_q.numpy())
    np.testing.assert_allclose(out[0], out[1], atol=2e-6)


@pytest.mark.parametrize("sewn_points", ["solve", "pass"])
def test_gradients_through_the_weld_match_finite_differences(rng, sewn_points):
    """Check a taped implicit rollout of the sewn panels (the weld in every step; a crumpled start that opens the seams
    by millimetres, which the first step's weld closes): the directional derivatives of the loss in the initial
    positions, velocities, masses and the membrane elements' stiffness within 1e-2 of central differences, with each
    welded point one particle in the solve (its masses from the model's on the tape) and with the points welded after
    the solve only (and there in the springs' stiffness, the seams' included, which carry the seam). In the solve a
    welded point's seam springs carry nothing: their stiffness has zero gradient. (The explicit integrators are
    unstable on this 2.5 cm mesh at the gradient tests' step, weld or not.)"""
    from test_gradients import SOFT, Setup

    model, _ = hanging_sewn(material=SOFT, requires_grad=True)
    make = lambda m: cw.SolverImplicitEuler(m, linear_solver="cg", tolerance=1e-6, strain_limit=0.1, strain_limit_iterations=2,
                                            sewn_points=sewn_points)
    setup = Setup("cpu", "implicit_cg", rng, model=model, make=make)
    assert setup.solver.pass_named("sewing") is not None
    assert setup.solver.solves_sewn_points == (sewn_points == "solve")
    state0 = setup.state0()
    value = setup.rollout.gradient(setup.loss, state0)
    kinds = ["initial_position", "initial_velocity", "mass", "membrane_stiffness"]
    if sewn_points == "pass":
        kinds.append("stiffness_field")
    else:
        seams = model.spring_kind.numpy() == int(cw.SpringKind.SEAM)
        assert seams.any() and not model.spring_stiffness.grad.numpy()[seams].any()
    report = {k: setup.check(k, state0, value) for k in kinds}
    for name, (ad, fd) in report.items():
        assert fd > 0.0, (sewn_points, name, report)
        assert abs(ad - fd) <= 1e-2 * abs(fd), (sewn_points, name, report)


def grid_triangles(nx, ny, h, x0=0.0):
    """A (nx+1) x (ny+1) vertex grid of spacing h [m] in the plane z = 0 from x = x0, y = 1 m down, its cells split
    along alternating diagonals: (vertices, triangles)."""
    xs, ys = np.meshgrid(x0 + h * np.arange(nx + 1), 1.0 - h * np.arange(ny + 1), indexing="xy")
    v = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    tris = []
    for j in range(ny):
        for i in range(nx):
            a, b, c, d = j * (nx + 1) + i, j * (nx + 1) + i + 1, (j + 1) * (nx + 1) + i, (j + 1) * (nx + 1) + i + 1
            tris += [(a, c, b), (b, c, d)] if (i + j) % 2 == 0 else [(a, c, d), (a, d, b)]
    return v, np.array(tris)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_welded_seam_solves_as_the_cloth_it_joins(seed):
    """Check a 24 x 16 cm sheet (membrane elements, no bending: the same triangles either way) against the same sheet cut
    into two panels along a grid line and sewn there (the cut's points coincide: welded): from a crumpled start with
    random velocities (each sewn point's particles alike), three implicit steps (solves to 1e-6, no passes but the
    weld) end every particle where the one sheet's particle ends, to 2e-6 m. The solve takes each welded point as one
    particle, its mass the point's: the seam's reduced system is the sheet's. With the points welded after the solve
    only (sewn_points="pass"), the seam springs in the system, the panels end up to 1e-4 m away."""
    h, material = 0.02, cw.materials.preset("cotton").replace(bend_stiffness=0.0, bend_stiffness_weft=0.0)
    b = cw.ModelBuilder()
    v, t = grid_triangles(12, 8, h)
    one = b.add_cloth_mesh(v, t, material=material, membrane="element", name="sheet")
    corners = one.indices(np.flatnonzero((v[:, 1] == 1.0) & ((v[:, 0] == 0.0) | (v[:, 0] == 12 * h))))
    b.pin(corners)
    sheet = b.finalize("cpu")
    b = cw.ModelBuilder()
    left, right = (b.add_cloth_mesh(*grid_triangles(6, 8, h, x0), material=material, membrane="element", name=name)
                   for x0, name in ((0.0, "left"), (6 * h, "right")))
    xl = np.asarray(b.particle_positions)[left.indices()]
    xr = np.asarray(b.particle_positions)[right.indices()]
    seam_l = left.indices(np.flatnonzero(np.isclose(xl[:, 0], 6 * h)))
    seam_r = right.indices(np.flatnonzero(np.isclose(xr[:, 0], 6 * h)))
    k = material.stretch_stiffness
    for i, j in zip(seam_l, seam_r):
        b.add_spring(int(i), int(j), k, 0.01, rest_length=1e-9, kind=cw.SpringKind.SEAM)
    xs = np.asarray(b.particle_positions)
    b.pin([i for i in range(len(xs)) if xs[i, 1] == 1.0 and xs[i, 0] in (0.0, 12 * h)])
    panels = b.finalize("cpu")
    # each sheet particle's counterparts in the panels (two along the seam)
    xp = panels.particle_q.numpy()
    x_sheet = sheet.particle_q.numpy()
    match = np.linalg.norm(xp[:, None, :] - x_sheet[None, :, :], axis=2).argmin(axis=1)
    assert np.bincount(match, minlength=len(x_sheet)).max() == 2 and len(seam_l) == 9
    rng = np.random.default_rng(seed)
    x0 = x_sheet + rng.normal(scale=3e-3, size=x_sheet.shape)
    v0 = rng.normal(scale=0.3, size=x_sheet.shape)
    x0[sheet.particle_pinned.numpy() != 0] = x_sheet[sheet.particle_pinned.numpy() != 0]
    v0[sheet.particle_pinned.numpy() != 0] = 0.0

    def run(model, x, v, **options):
        solver = cw.SolverImplicitEuler(model, strain_limit=None, collisions=False, tolerance=1e-6, **options)
        s0, s1 = model.state(), model.state()
        s0.particle_q.assign(x.astype(np.float32))
        s0.particle_qd.assign(v.astype(np.float32))
        for _ in range(3):
            solver.step(s0, s1, model.control(), 1.0 / 120.0)
            s0, s1 = s1, s0
        return s0.particle_q.numpy(), solver

    ref, _ = run(sheet, x0, v0)
    got, solver = run(panels, x0[match], v0[match])
    assert solver.solves_sewn_points and solver.pass_named("sewing").welded_points == 9
    np.testing.assert_allclose(got, ref[match], atol=2e-6)
    apart, solver = run(panels, x0[match], v0[match], sewn_points="pass")
    assert not solver.solves_sewn_points
    assert np.abs(apart - ref[match]).max() > 1e-4
