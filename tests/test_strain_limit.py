"""Provot strain limiting: the limit holds after every step, for every integrator, without adding momentum."""

import numpy as np
import pytest
import warp as wp

import cloth_warp as cw
from conftest import run_steps

LIMIT = 0.1
# The limiter sweeps until no spring exceeds the limit by more than its tolerance (1e-3 strain).
TOLERANCE = 1.0e-3

HEAVY_SOFT = cw.FabricMaterial(name="heavy-soft", areal_density=0.5, stretch_stiffness=30.0, shear_stiffness=3.0, bend_stiffness=1e-6)


def hanging_cloth(device, resolution=24):
    b = cw.ModelBuilder()
    c = b.add_cloth_grid(resolution=(resolution, resolution), size=(1.0, 1.0), material=HEAVY_SOFT)
    b.pin(c.select("corner:top_left"))
    b.pin(c.select("corner:top_right"))
    return b.finalize(device)


def structural_strain(model, state):
    sp = model.spring_indices.numpy()
    kind = model.spring_kind.numpy()
    x = state.particle_q.numpy()
    s = sp[kind == cw.SpringKind.STRUCTURAL]
    return float((np.linalg.norm(x[s[:, 0]] - x[s[:, 1]], axis=1) / model.spring_rest_length.numpy()[kind == cw.SpringKind.STRUCTURAL] - 1.0).max())


@pytest.mark.parametrize(
    "name, substeps",
    [("symplectic_euler", 20), ("explicit_euler", 40), ("midpoint", 20), ("rk4", 10), ("implicit_euler", 8)],
)
def test_strain_limit_holds_after_every_step(device, name, substeps):
    """Check max structural strain <= limit + 1e-3 after every step of a heavy cloth hanging from two corners."""
    model = hanging_cloth(device)
    solver = cw.make_solver(name, model, strain_limit=LIMIT)
    worst = []
    frames = 20
    run_steps(solver, model, frames * substeps, 1.0 / (60 * substeps), record=lambda k, s: worst.append(structural_strain(model, s)))
    assert max(worst) <= LIMIT + TOLERANCE, max(worst)
    # The set-up is meaningful: without the limiter the same cloth stretches far beyond the limit.
    free = run_steps(cw.make_solver(name, model, strain_limit=None), model, frames * substeps, 1.0 / (60 * substeps))
    assert structural_strain(model, free) > 3 * LIMIT


def test_strain_limit_keeps_center_of_mass_motion(device, rng):
    """Check the limiter (mass-weighted, internal) leaves the centre of mass of a free sheet unchanged."""
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(8, 8), size=(0.5, 0.5), material=HEAVY_SOFT)
    model = b.finalize(device)
    state = model.state()
    v = rng.normal(scale=2.0, size=(model.particle_count, 3)).astype(np.float32)  # tears the sheet apart
    state.particle_qd.assign(v)
    m = model.particle_mass.numpy()[:, None]
    dt, steps = 1.0 / 600.0, 60
    com = {}
    for limit in (None, LIMIT):
        s = model.state()
        s.assign(state)
        s = run_steps(cw.SolverSymplecticEuler(model, strain_limit=limit), model, steps, dt, state=s)
        x = s.particle_q.numpy()
        com[limit] = ((m * x).sum(0) / m.sum(), (m * s.particle_qd.numpy()).sum(0) / m.sum())
        if limit:
            assert structural_strain(model, s) <= LIMIT + TOLERANCE
    np.testing.assert_allclose(com[LIMIT][0], com[None][0], atol=1e-5)
    np.testing.assert_allclose(com[LIMIT][1], com[None][1], atol=1e-4)


def test_forward_and_taped_limiter_paths_agree(device, rng):
    """Check the in-place forward sweeps (thread per spring) equal the taped out-of-place sweeps (thread per particle)."""
    model = hanging_cloth(device, resolution=8)
    x = model.particle_q.numpy()
    pinned = model.particle_pinned.numpy() != 0
    moved = x + rng.normal(scale=0.05, size=x.shape).astype(np.float32)
    moved[pinned] = x[pinned]
    solver = cw.SolverSymplecticEuler(model, strain_limit=LIMIT, strain_limit_iterations=6, strain_limit_tolerance=None)
    results = []
    for taped in (False, True):
        x_in = wp.array(moved, dtype=wp.vec3, device=device, requires_grad=taped)
        out = model.state(requires_grad=taped)
        solver.strain_limiter.apply(solver, x_in, wp.zeros_like(x_in), out, 0.01)
        results.append(out.particle_q.numpy())
    np.testing.assert_allclose(results[0], results[1], atol=1e-6)
