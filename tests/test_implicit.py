"""Implicit Euler: Jacobi and CG against a dense numpy solve; CG vs Jacobi iterations; stiff stability."""

import numpy as np
import pytest
import warp as wp

import cloth_warp as cw
from cloth_warp.numpy_reference import NumpyCloth


def perturbed_cloth(device, rng, spring_model="choi_ko", stretch=50.0):
    """A small cloth with every force term active: compressed and stretched springs, buckling springs,
    drag with wind, global damping, a soft pin and two hard pins whose targets move. Its membrane is springs
    (membrane="springs"): the numpy reference (cloth_warp/numpy_reference.py) knows springs only; the membrane
    element has its own dense-solve and energy-gradient checks (tests/test_membrane.py)."""
    mat = cw.FabricMaterial(areal_density=0.2, stretch_stiffness=stretch, shear_stiffness=5.0, bend_stiffness=1e-4,
                            damping=1e-3, drag_coefficient=0.8)
    b = cw.ModelBuilder(global_damping=0.1)
    c = b.add_cloth_grid(resolution=(5, 4), size=(0.5, 0.4), material=mat, spring_model=spring_model, membrane="springs")
    b.pin(c.select("corner:top_left"))
    b.pin(c.select("corner:top_right"))
    b.pin(c.select("corner:bottom_left"), stiffness=20.0)
    model = b.finalize(device)
    state = model.state()
    x = state.particle_q.numpy()
    x += rng.normal(scale=0.01, size=x.shape).astype(np.float32)
    state.particle_q.assign(x)
    state.particle_qd.assign(rng.normal(scale=0.2, size=x.shape).astype(np.float32))
    control = model.control()
    target = control.pin_target.numpy()
    target[model.particle_pinned.numpy() != 0] += np.float32(0.003)
    control.pin_target.assign(target)
    control.set_wind((0.3, 0.0, 1.0))
    return model, state, control


@pytest.mark.parametrize("linear_solver", ["cg", "jacobi"])
@pytest.mark.parametrize("spring_model", ["choi_ko", "provot"])
def test_linear_solvers_match_dense_solve(device, rng, linear_solver, spring_model):
    """Check that Jacobi and CG reproduce a float64 dense solve of the same implicit system to 1e-5 relative (spring
    membrane: the numpy reference's; elements: tests/test_membrane.py::test_implicit_step_matches_a_dense_solve)."""
    model, state, control = perturbed_cloth(device, rng, spring_model)
    dt = 1.0 / 60.0
    solver = cw.SolverImplicitEuler(model, linear_solver=linear_solver, tolerance=3e-7, max_iterations=2000, check_every=1)
    dv = solver.solve(state, control, dt).numpy()
    ref = NumpyCloth(model).solve_implicit_dense(state.particle_q.numpy(), state.particle_qd.numpy(), control.pin_target.numpy(), control.wind.numpy()[0], dt)
    # The system is well conditioned here (h^2 k / m ~ 1): a 3e-7 residual (near the float32 floor of
    # the true residual) bounds the error well below 1e-5.
    err = np.linalg.norm(dv - ref) / np.linalg.norm(ref)
    assert err < 1e-5, (err, solver.last_iterations, solver.last_residual)
    assert solver.converged


def test_forces_match_numpy(device, rng):
    """Check the kernels' total force against the independent numpy implementation (spring membrane: the numpy
    reference's; element forces: tests/test_membrane.py::test_forces_are_minus_the_energy_gradient_and_damping_the_rayleigh_gradient)."""
    model, state, control = perturbed_cloth(device, rng)
    f = wp.zeros(model.particle_count, dtype=wp.vec3, device=device)
    from cloth_warp.kernels import forces as kf

    elements = cw.SolverSymplecticEuler(model).element_forces(state.particle_q, state.particle_qd, control)
    wp.launch(kf.eval_particle_forces, dim=model.particle_count,
              inputs=[model.particle_mass, model.particle_pin_stiffness, elements, state.particle_q, state.particle_qd,
                      control.pin_target, wp.vec3(*model.gravity), model.global_damping], outputs=[f], device=device)
    ref = NumpyCloth(model).forces(state.particle_q.numpy(), state.particle_qd.numpy(), control.pin_target.numpy(), control.wind.numpy()[0])
    np.testing.assert_allclose(f.numpy(), ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())


def test_bending_force_is_minus_energy_gradient(rng):
    """Check the analytic Choi-Ko triple forces equal -dE/dx (central differences in float64)."""
    model, state, control = perturbed_cloth("cpu", rng)
    ref = NumpyCloth(model)
    x = state.particle_q.numpy().astype(np.float64)
    mask = ref.law != cw.SpringLaw.LINEAR
    f = np.zeros_like(x)
    for idx, force in zip((ref.springs[mask, 0], ref.middle[mask], ref.springs[mask, 1]), ref.bending_forces(x, mask)):
        np.add.at(f, idx, force)
    fd = ref.bending_forces_fd(x)
    np.testing.assert_allclose(f, fd, atol=1e-6 * np.abs(fd).max())


def test_cg_needs_fewer_iterations_than_jacobi(device):
    """Check that CG reaches the same relative residual in fewer iterations than block Jacobi (cotton, 24^2)."""
    b = cw.ModelBuilder()
    c = b.add_cloth_grid(resolution=(24, 24), size=(1.0, 1.0), material="cotton", rotation=cw.quat_from_axis_angle((1, 0, 0), -90.0))
    b.pin(c.select("edge:top"))
    model = b.finalize(device)
    state, control = model.state(), model.control()
    dt = 1.0 / 240.0
    counts = {}
    for name in ("cg", "jacobi"):
        solver = cw.SolverImplicitEuler(model, linear_solver=name, tolerance=1e-4, max_iterations=5000, check_every=1)
        solver.solve(state, control, dt)
        assert solver.converged, (name, solver.last_residual)
        counts[name] = solver.last_iterations
    print(f"iterations to 1e-4 relative residual: {counts}")
    assert counts["cg"] < counts["jacobi"]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_capped_cg_solve_returns_the_iterate_with_the_smallest_residual(seed):
    """Check that a CG solve stopped by its cap of iterations returns the iterate whose residual was the smallest of the
    solve, and reports that residual (kernels/implicit.py restore_best_iterate): CG's residual norm is not monotone
    (here it rises in the last iterations before the cap), and a float32 solve can even grow from near its stop to
    the cap (a cloth-on-cloth incline's solve went from 4.4e-6 at iteration 101 to 6.5e-4 at 1000, on a system whose
    preconditioned spectrum is [0.004, 2.0]). The iterate is the one a solve capped at its iteration returns."""
    from cloth_warp.kernels import implicit as ki

    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(12, 12), size=(0.5, 0.5), material="denim")
    m = b.finalize("cpu")
    state, control = m.state(), m.control()
    q = state.particle_q.numpy()
    state.particle_q.assign(q + np.random.default_rng(seed).normal(scale=0.01, size=q.shape).astype(np.float32))

    def capped(cap):
        solver = cw.SolverImplicitEuler(m, max_iterations=cap, tolerance=1e-10, warm_start=False)
        dv = solver.solve(state, control, 1.0 / 60.0).numpy().copy()
        history = np.sqrt(solver.cg_scalars.numpy()[1:cap + 1, ki.CG_RR] / solver.solve_status.numpy()[ki.STATUS_REFERENCE])
        return dv, history, solver.solve_status.numpy()[ki.STATUS_RELATIVE]

    rises = 0
    for cap in range(20, 61, 8):
        dv, history, reported = capped(cap)
        best = int(np.argmin(history)) + 1
        assert reported == pytest.approx(history.min(), rel=1e-12)
        if best < cap:  # the last iterations rose: the best iterate is returned
            rises += 1
            np.testing.assert_array_equal(dv, capped(best)[0])
    assert rises > 0  # (the case is exercised)
