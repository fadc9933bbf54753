"""Gradients of taped rollouts against central finite differences, for every integrator and parameter kind.

Each check differentiates a loss L (mean squared distance of the final positions to a random target)
along the unit direction d = g / |g| of the reverse-mode gradient g, so the exact directional
derivative is |g| > 0, and compares it with a central difference along d.

eps: the rollouts run in float32; L carries a relative round-off of ~1e-6 after many steps, so a central
difference has a noise of ~1e-6 L / (eps |g|) relative. eps is chosen so that the step changes L by
1 % (eps |g| = 1e-2 L), which puts that noise near 1e-4, capped per kind so the perturbation stays
small: 0.1 relative for material fields, 1 cm/s for velocities, 0.1 m/s for wind, and 0.1 mm for
positions (their gradient is large, and bigger steps change the strain limiter's active set). The truncation error O(eps^2) of such steps is removed by Richardson extrapolation,
(4 D(eps/2) - D(eps)) / 3, which is accurate to O(eps^4).
"""

import numpy as np
import pytest
import warp as wp

import cloth_warp as cw
from meshes import strip_mesh

STEPS = 10
SOFT = cw.materials.COTTON.replace(stretch_stiffness=60.0, shear_stiffness=20.0, bend_stiffness=2.0e-5, damping=0.01,
                                    drag_coefficient=2.0)


def hanging(device, resolution=(4, 4), membrane=None):
    b = cw.ModelBuilder()
    c = b.add_cloth_grid(resolution=resolution, size=(0.4, 0.4), material=SOFT, membrane=membrane)
    b.pin(c.select("corner:top_left"))
    b.pin(c.select("corner:top_right"))
    return b.finalize(device, requires_grad=True)


# name -> (solver, dt [s], steps): explicit steps stay below the stability limit of the lightest (corner)
# particle, h omega < 2 (omega ~ 1100 / s here); every rollout covers 20-80 ms.
SOLVERS = {
    "explicit_euler": (lambda m: cw.SolverExplicitEuler(m, strain_limit=0.1, strain_limit_iterations=2), 1.0 / 3000.0, 60),
    "symplectic_euler": (lambda m: cw.SolverSymplecticEuler(m, strain_limit=0.1, strain_limit_iterations=2), 1.0 / 3000.0, 60),
    "midpoint": (lambda m: cw.SolverMidpoint(m, strain_limit=0.1, strain_limit_iterations=2), 1.0 / 3000.0, 60),
    "rk4": (lambda m: cw.SolverRK4(m, strain_limit=0.1, strain_limit_iterations=2), 1.0 / 3000.0, 60),
    "implicit_cg": (lambda m: cw.SolverImplicitEuler(m, linear_solver="cg", tolerance=1e-6, strain_limit=0.1, strain_limit_iterations=2),
                    1.0 / 120.0, STEPS),
    "implicit_jacobi": (lambda m: cw.SolverImplicitEuler(m, linear_solver="jacobi", tolerance=1e-6, max_iterations=3000, strain_limit=0.1,
                                                         strain_limit_iterations=2), 1.0 / 120.0, STEPS),
}

# parameter kind -> (how to reach its array, eps, relative). Positive material fields are perturbed
# relatively, p_i (1 + eps d_i) with d along the gradient in log space (g_i p_i): their entries span five
# orders of magnitude (stretch springs ~50 N/m, bend triples ~1e-5 N m^2).
KINDS = {
    "initial_position": (lambda model, state0, control: state0.particle_q, 1e-4, False),
    "initial_velocity": (lambda model, state0, control: state0.particle_qd, 5e-2, False),
    "stiffness_field": (lambda model, state0, control: model.spring_stiffness, 0.1, True),
    "damping_field": (lambda model, state0, control: model.spring_damping, 0.1, True),
    "mass": (lambda model, state0, control: model.particle_mass, 0.1, True),
    "drag": (lambda model, state0, control: model.tri_drag, 0.1, True),
    "wind": (lambda model, state0, control: control.wind, 0.1, False),
    # membrane elements (membrane="element"): their Voigt constants and Kelvin-Voigt damping per triangle
    "membrane_stiffness": (lambda model, state0, control: model.membrane_stiffness, 0.1, True),
    "membrane_damping": (lambda model, state0, control: model.membrane_damping, 0.1, True),
    # plate-bending stencils (bending="stencil", meshes by default): A_v D per vertex
    "plate_stiffness": (lambda model, state0, control: model.plate_stiffness, 0.1, True),
}
# The kinds each membrane has: spring cloths carry stretch and shear in the springs' stiffness and damping; element
# cloths in the elements. An element cloth's structural and shear springs have zero stiffness and damping, so its
# spring fields hold only the (undamped) bend springs: here their directional derivative is ~1/300 of the membrane's,
# a loss change of ~1e-8 on 3e-3 at eps = 0.1, at the float32 noise floor of the difference (measured 2 % apart).
MEMBRANE_KINDS = {
    "springs": ("initial_position", "initial_velocity", "stiffness_field", "damping_field", "mass", "drag", "wind"),
    "element": ("initial_position", "initial_velocity", "membrane_stiffness", "membrane_damping", "mass", "drag", "wind"),
}


def hanging_mesh(device, kind, membrane, bending=None):
    """A 0.2 x 0.15 m strip of `kind` triangles (tests/meshes.py) pinned at one corner, bent by plate stencils (the
    mesh default) of a stiff material (bend 2e-3 N m: the loss feels the stencils well above float32 noise)."""
    v, tri = strip_mesh(kind, 0.2, 0.15, 0.05)
    b = cw.ModelBuilder()
    c = b.add_cloth_mesh(v, tri, material=SOFT.replace(bend_stiffness=2e-3), membrane=membrane, bending=bending)
    b.pin(c.indices([0]))
    return b.finalize(device, requires_grad=True)


class Setup:
    def __init__(self, device, solver_name, rng, model=None, make=None):
        self.model = hanging(device) if model is None else model
        listed, self.dt, steps = SOLVERS[solver_name]
        make = make or listed
        self.solver = make(self.model)
        n = self.model.particle_count
        self.v0 = rng.normal(scale=0.2, size=(n, 3)).astype(np.float32)
        # A crumpled start: in a flat sheet every bend triple is exactly straight, where Choi-Ko's immediate
        # buckling force jumps (the loss has a kink there and only one-sided derivatives).
        self.x0 = (self.model.particle_q.numpy() + rng.normal(scale=0.005, size=(n, 3))).astype(np.float32)
        target = self.model.particle_q.numpy() + rng.normal(scale=0.03, size=(n, 3))
        self.loss = cw.PositionLoss({steps: target}, device=device)
        self.rollout = cw.Rollout(self.model, self.solver, dt=self.dt, steps=steps)
        self.rollout.control.wind.assign(np.array([[1.0, 0.0, 2.0]], np.float32))

    def state0(self):
        s = self.model.state(requires_grad=True)
        s.particle_q.assign(self.x0)
        s.particle_qd.assign(self.v0)
        return s

    def check(self, kind, state0, value):
        get, eps_max, relative = KINDS[kind]
        arr = get(self.model, state0, self.rollout.control)
        base = arr.numpy().copy()
        g = arr.grad.numpy().astype(np.float64).reshape(-1)
        assert np.isfinite(g).all()
        scale = base.reshape(-1).astype(np.float64) if relative else np.ones_like(g)
        g = g * scale  # the gradient in the perturbation's coordinates
        norm = np.linalg.norm(g)
        assert norm > 0.0, f"{kind}: zero gradient"
        d = g / norm * scale

        def loss_at(delta):
            s0 = self.state0()
            target = get(self.model, s0, self.rollout.control)
            keep = target.numpy().copy()
            target.assign((base.reshape(-1) + delta * d).reshape(base.shape).astype(np.float32))
            value = self.rollout.forward(self.loss, s0)
            target.assign(keep)
            return value

        eps = min(eps_max, 1e-2 * value / norm)
        coarse = (loss_at(eps) - loss_at(-eps)) / (2.0 * eps)
        fine = (loss_at(eps / 2) - loss_at(-eps / 2)) / eps
        return norm, (4.0 * fine - coarse) / 3.0


# every solver with springs; elements with one explicit and one implicit solver (their adjoint is also checked on
# meshes below and in test_membrane)
ROLLOUT_CASES = [(name, "springs") for name in SOLVERS] + [("symplectic_euler", "element"), ("implicit_cg", "element")]


@pytest.mark.parametrize("solver_name, membrane", ROLLOUT_CASES)
def test_rollout_gradients_match_finite_differences(device, solver_name, membrane, rng):
    """Every parameter kind, one taped rollout: directional derivative along g within 1e-2, same sign. The cloth is
    built with membrane="springs" (the spring stiffness and damping fields carry stretch and shear) and with
    membrane="element" (the element constants and damping do; the spring stiffness field holds the bend springs)."""
    setup = Setup(device, solver_name, rng, model=hanging(device, membrane=membrane))
    state0 = setup.state0()
    value = setup.rollout.gradient(setup.loss, state0)
    report = {kind: setup.check(kind, state0, value) for kind in MEMBRANE_KINDS[membrane]}
    for kind, (ad, fd) in report.items():
        assert fd > 0.0, (solver_name, membrane, kind, report)
        assert abs(ad - fd) <= 1e-2 * abs(fd), (solver_name, membrane, kind, report)


@pytest.mark.parametrize("membrane", ["springs", "element"])
@pytest.mark.parametrize("kind", ["equilateral", "irregular"])
def test_implicit_gradients_on_triangle_meshes_match_finite_differences(device, kind, membrane, rng):
    """Garment-like cloth: the implicit adjoint on triangle meshes (springs or membrane elements, plate stencils)
    within 1e-2 of FD."""
    # no strain limiter: its active set makes differences of these small derivatives depend on the step
    setup = Setup(device, "implicit_cg", rng, model=hanging_mesh(device, kind, membrane),
                  make=lambda m: cw.SolverImplicitEuler(m, linear_solver="cg", tolerance=1e-6, strain_limit=None))
    state0 = setup.state0()
    value = setup.rollout.gradient(setup.loss, state0)
    membrane_field = "membrane_stiffness" if membrane == "element" else "stiffness_field"
    report = {k: setup.check(k, state0, value) for k in ("initial_position", "initial_velocity", membrane_field, "plate_stiffness", "mass")}
    for name, (ad, fd) in report.items():
        assert fd > 0.0, (kind, membrane, name, report)
        assert abs(ad - fd) <= 1e-2 * abs(fd), (kind, membrane, name, report)


def test_implicit_gradients_through_zero_stiffness_bend_triples_match_finite_differences(device, rng):
    """Bend triples the fit leaves at zero stiffness (irregular meshes, bending="springs") once took sqrt(0) in the
    implicit Jacobian weights, whose infinite derivative made the position adjoint NaN."""
    model = hanging_mesh(device, "irregular", "element", bending="springs")
    assert (model.spring_stiffness.numpy()[model.linear_spring_count:] == 0.0).any()
    setup = Setup(device, "implicit_cg", rng, model=model,
                  make=lambda m: cw.SolverImplicitEuler(m, linear_solver="cg", tolerance=1e-6, strain_limit=None))
    state0 = setup.state0()
    value = setup.rollout.gradient(setup.loss, state0)
    ad, fd = setup.check("initial_position", state0, value)
    assert abs(ad - fd) <= 1e-2 * abs(fd), (ad, fd)


def test_implicit_adjoint_matches_unrolled_solve(device, rng):
    """The adjoint (transposed solve) gradient equals the gradient of a taped, unrolled block-Jacobi solve."""
    grads = {}
    for mode in ("adjoint", "unrolled"):
        model = hanging(device)
        solver = cw.SolverImplicitEuler(model, linear_solver="cg", tolerance=1e-7, max_iterations=300, strain_limit=None,
                                        differentiation=mode)
        n = model.particle_count
        r = np.random.default_rng(7)
        rollout = cw.Rollout(model, solver, dt=1.0 / 120.0, steps=4)
        rollout.control.wind.assign(np.array([[1.0, 0.0, 2.0]], np.float32))
        state0 = model.state(requires_grad=True)
        state0.particle_qd.assign(r.normal(scale=0.2, size=(n, 3)).astype(np.float32))
        loss = cw.PositionLoss({4: model.particle_q.numpy() + r.normal(scale=0.03, size=(n, 3))}, device=device)
        rollout.gradient(loss, state0)
        grads[mode] = {"v0": state0.particle_qd.grad.numpy().copy(), "x0": state0.particle_q.grad.numpy().copy(),
                       "stiffness": model.spring_stiffness.grad.numpy().copy(), "mass": model.particle_mass.grad.numpy().copy(),
                       "drag": model.tri_drag.grad.numpy().copy(), "wind": rollout.control.wind.grad.numpy().copy()}
        if mode == "adjoint":
            assert solver.adjoint_solves == 4 and solver.adjoint_iterations > 0
    for key, ref in grads["unrolled"].items():
        err = np.abs(grads["adjoint"][key] - ref).max() / np.abs(ref).max()
        # 300 Jacobi iterations reach ~1e-6 relative on this system; float32 accumulation adds ~1e-5
        assert err < 1e-3, (key, err)


def assert_close_within_run_spread(actual, desired, repeat, atol, rtol=0.0):
    """`actual` equals `desired` (a run) to `atol` and `rtol`, or where two runs of the same thing differ (`repeat`: `desired` run
    again; CUDA's float atomics add in any order, and an iterative solve stopped at its tolerance carries the
    difference on), to 10 times their largest difference. On a CUDA H200 two taped 5-step rollouts' spring-stiffness
    gradients, sums of large cancelling terms, differed by up to 17 % of their largest."""
    spread = 0.0 if repeat is None else float(np.abs(repeat - desired).max())
    np.testing.assert_allclose(actual, desired, rtol=rtol, atol=max(atol, 10.0 * spread))


def test_checkpointed_gradient_equals_full_tape(device, rng):
    """Checkpointed segments (re-run under their own tapes) give the same loss and gradients as one tape (on CUDA, within
    the spread of two one-tape runs: :func:`assert_close_within_run_spread`)."""
    results = []
    repeat = (None,) if wp.get_device(device).is_cuda else ()
    for every in (None, 3, "auto", *repeat):
        setup = Setup(device, "implicit_cg", np.random.default_rng(3))
        setup.rollout = cw.Rollout(setup.model, setup.solver, dt=setup.dt, steps=STEPS, checkpoint_every=every)
        setup.rollout.control.wind.assign(np.array([[1.0, 0.0, 2.0]], np.float32))
        state0 = setup.state0()
        value = setup.rollout.gradient(setup.loss, state0)
        results.append((value, state0.particle_qd.grad.numpy().copy(), setup.model.spring_stiffness.grad.numpy().copy(),
                        setup.rollout.control.wind.grad.numpy().copy()))
    again = results[3] if repeat else (None,) * 4
    for other in results[1:3]:
        assert other[0] == pytest.approx(results[0][0], rel=1e-6)
        for a, b, r in zip(other[1:], results[0][1:], again[1:]):
            assert_close_within_run_spread(a, b, r, atol=1e-6 * np.abs(b).max(), rtol=1e-5)


@pytest.mark.parametrize("case", ["cg", "jacobi", "contacts_in_solve"])
def test_replayed_solve_loops_give_the_eager_gradients(device, case):
    """A taped rollout's solves (forward and adjoint) replay their loops as graphs (SolverImplicitEuler.replay_loops):
    the loss and every gradient equal those of the same rollout with each kernel launched one by one, bit for bit on the
    CPU. On CUDA the adjoint kernels' float atomics add in any order, so two runs of either kind differ (a 5-step
    rollout's velocity gradients by ~1e-5 of their largest on an H200, its spring-stiffness gradients by up to 17 %):
    there, the replayed gradients are within the spread of two eager runs (:func:`assert_close_within_run_spread`)."""
    results = []
    repeat = (False,) if wp.get_device(device).is_cuda else ()
    for replay in (False, True, *repeat):
        b = cw.ModelBuilder()
        b.add_cloth_grid(resolution=(5, 4), size=(0.2, 0.2), position=(0.0, 0.012, 0.0), rotation=cw.quat_from_axis_angle((1, 0, 0), -90.0),
                         material=SOFT)
        b.add_ground(thickness=0.01, friction=0.3)
        model = b.finalize(device, requires_grad=True)
        options = {"cg": {}, "jacobi": {"linear_solver": "jacobi"}, "contacts_in_solve": {"collider_contacts": "solve"}}[case]
        solver = cw.SolverImplicitEuler(model, tolerance=1e-5, **options)
        solver.replay_loops = replay
        state0 = model.state(requires_grad=True)
        state0.particle_qd.fill_(wp.vec3(0.3, -0.4, 0.0))
        target = model.particle_q.numpy() + np.array([0.01, -0.01, 0.0], np.float32)
        value = cw.Rollout(model, solver, dt=1.0 / 120.0, steps=5).gradient(cw.PositionLoss({5: target}, device=device), state0)
        assert solver.adjoint_iterations > 0
        if case == "contacts_in_solve":
            assert solver.read_report().contacts > 0
        results.append((value, state0.particle_qd.grad.numpy().copy(), model.spring_stiffness.grad.numpy().copy(),
                        model.particle_mass.grad.numpy().copy()))
    assert results[0][0] == results[1][0]
    again = results[2] if repeat else (None,) * 4
    for a, b, r in zip(results[0][1:], results[1][1:], again[1:]):
        assert np.abs(a).max() > 0.0
        if wp.get_device(device).is_cpu:
            assert np.array_equal(a, b)
        else:
            assert_close_within_run_spread(b, a, r, atol=1e-4 * np.abs(a).max())


HYGIENE_SCRIPT = """
import sys, numpy as np, warp as wp
wp.config.verify_autograd_array_access = True  # before any kernel is built: the access analysis runs at build time
sys.path.insert(0, {tests!r})
import cloth_warp as cw
from test_gradients import SOLVERS, Setup, hanging

# The check works here: a deliberate overwrite is reported.
model = hanging({device!r})
solver = cw.SolverSymplecticEuler(model, strain_limit=None)
control = model.control()
s0, s1 = model.state(requires_grad=True), model.state(requires_grad=True)
with wp.Tape():
    solver.step(s0, s1, control, 1e-3)
    solver.step(s1, s0, control, 1e-3)  # writes s0, which the first step read
sys.stderr.flush()
print("CONTROL-DONE", flush=True)
for name in SOLVERS:
    setup = Setup({device!r}, name, np.random.default_rng(0))
    setup.rollout.gradient(setup.loss, setup.state0())
    print("SOLVER-DONE", name, flush=True)
# collider contacts in the implicit solve (their constraints, filter and friction on the tape)
b = cw.ModelBuilder()
b.add_cloth_grid(resolution=(4, 4), size=(0.2, 0.2), position=(0.0, 0.01, 0.0), rotation=cw.quat_from_axis_angle((1, 0, 0), -90.0))
b.add_ground(thickness=0.01, friction=0.3)
model = b.finalize({device!r}, requires_grad=True)
solver = cw.SolverImplicitEuler(model, collider_contacts="solve")
state0 = model.state(requires_grad=True)
state0.particle_qd.fill_(wp.vec3(0.5, -0.1, 0.0))
cw.Rollout(model, solver, dt=1.0 / 120.0, steps=4).gradient(cw.PositionLoss({{4: model.particle_q.numpy()}}, device={device!r}), state0)
assert solver.read_report().contacts > 0
print("SOLVER-DONE contacts", flush=True)
"""


@pytest.mark.slow
def test_taped_steps_never_overwrite_what_the_tape_read(device):
    """Tape hygiene: with verify_autograd_array_access on, no solver writes an array a taped kernel read."""
    import pathlib
    import subprocess
    import sys

    script = HYGIENE_SCRIPT.format(tests=str(pathlib.Path(__file__).parent), device=device)
    proc = subprocess.run([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=600)
    out = proc.stdout
    assert proc.returncode == 0, out[-3000:]
    control, _, solvers = out.partition("CONTROL-DONE")
    assert "already been read from" in control, "the deliberate overwrite was not reported: the check is not active"
    found = [line for line in solvers.splitlines() if "already been read from" in line]
    assert not found, found[:2]
    assert solvers.count("SOLVER-DONE") == len(SOLVERS) + 1


def test_gradients_stay_finite_through_collisions(device):
    """A cloth dropped onto a sphere (collider and self-collision on) under the tape: finite, non-zero
    gradients. What does not differentiate: the contact set and the impact-zone grouping are held fixed
    (piecewise), so these gradients are those of the active contacts only."""
    b = cw.ModelBuilder()
    c = b.add_cloth_grid(resolution=(8, 8), size=(0.4, 0.4), position=(-0.2, 0.13, 0.2), rotation=(-0.7071068, 0.0, 0.0, 0.7071068),
                         material=SOFT)
    b.add_sphere((0.0, 0.0, 0.0), 0.12, friction=0.4)
    b.enable_self_collision(thickness=0.004)
    model = b.finalize(device, requires_grad=True)
    assert c.particle_count == 81
    n = model.particle_count
    for solver in (cw.SolverImplicitEuler(model, tolerance=1e-5), cw.SolverSymplecticEuler(model)):
        dt, steps = (1.0 / 120.0, 12) if solver.name == "implicit_euler" else (1.0 / 2400.0, 60)
        rollout = cw.Rollout(model, solver, dt=dt, steps=steps)
        target = model.particle_q.numpy() + np.array([0.0, -0.05, 0.0])
        state0 = model.state(requires_grad=True)
        value = rollout.gradient(cw.PositionLoss({steps: target}, device=device), state0)
        contacts = solver.pass_named("colliders").read_report()
        assert contacts.contacts > 0, contacts
        for arr in (state0.particle_q.grad, state0.particle_qd.grad, model.spring_stiffness.grad, model.particle_mass.grad,
                    model.collider_kinetic_friction.grad):
            g = arr.numpy()
            assert np.isfinite(g).all(), solver.name
        assert np.abs(state0.particle_qd.grad.numpy()).max() > 0.0 and np.isfinite(value)
        assert n == 81


def _richardson(loss_at, eps):
    coarse = (loss_at(eps) - loss_at(-eps)) / (2.0 * eps)
    fine = (loss_at(eps / 2) - loss_at(-eps / 2)) / eps
    return (4.0 * fine - coarse) / 3.0


@pytest.mark.parametrize("solver_name", ["symplectic_euler", "implicit_cg"])
def test_handle_keyframe_gradient_matches_finite_differences(device, solver_name):
    """d loss / d keyframe translation of an animated handle (per-step pin targets folded by the keyframe
    interpolation weights) against rebuilding the model with the keyframe moved."""
    make, dt, steps = SOLVERS[solver_name]
    t_end = dt * steps
    r = np.random.default_rng(5)

    def build(offset):
        b = cw.ModelBuilder()
        c = b.add_cloth_grid(resolution=(4, 4), size=(0.4, 0.4), material=SOFT)
        b.add_handle(c.select("edge:top"), [(0.0, (0.0, 0.0, 0.0)), (t_end, tuple(np.array([0.02, 0.0, 0.01]) + offset))], name="bar")
        return b.finalize(device, requires_grad=True)

    model = build(np.zeros(3))
    x0 = (model.particle_q.numpy() + r.normal(scale=0.005, size=(model.particle_count, 3))).astype(np.float32)
    target = model.particle_q.numpy() + r.normal(scale=0.03, size=x0.shape)

    def run(m, grad):
        rollout = cw.Rollout(m, make(m), dt=dt, steps=steps)
        s0 = m.state(requires_grad=True)
        s0.particle_q.assign(x0)
        loss = cw.PositionLoss({steps: target}, device=device)
        return (rollout.gradient(loss, s0), rollout) if grad else (rollout.forward(loss, s0), rollout)

    value, rollout = run(model, True)
    g = rollout.handle_gradients["bar"][1]  # the second keyframe's translation
    assert np.isfinite(g).all() and np.linalg.norm(g) > 0.0
    d = g / np.linalg.norm(g)
    eps = min(1e-3, 1e-2 * value / np.linalg.norm(g))
    fd = _richardson(lambda e: run(build(e * d), False)[0], eps)
    assert fd > 0.0 and abs(np.linalg.norm(g) - fd) <= 1e-2 * fd, (g, fd)


def test_chamfer_loss_gradient_matches_finite_differences(device):
    """The topology-free loss: gradient w.r.t. the initial velocities through an implicit rollout."""
    setup = Setup(device, "implicit_cg", np.random.default_rng(9))
    other = hanging(device, resolution=(6, 6))  # the target lives on a different mesh
    points = other.particle_q.numpy() + np.array([0.0, -0.02, 0.01])
    setup.loss = cw.ChamferLoss({setup.rollout.steps: points}, device=device)
    state0 = setup.state0()
    value = setup.rollout.gradient(setup.loss, state0)
    ad, fd = setup.check("initial_velocity", state0, value)
    assert fd > 0.0 and abs(ad - fd) <= 1e-2 * fd, (ad, fd)
