"""Integrators against closed forms: spring period and per-step energy factors, free fall offsets."""

import math

import numpy as np
import pytest

import cloth_warp as cw
from conftest import run_steps

MASS = 1.0  # kg
STIFFNESS = 100.0  # N/m -> omega = 10 rad/s, T = 0.6283 s
REST = 0.1  # m
AMPLITUDE = 0.01  # m


def oscillator(device, solver_cls, **opts):
    """Particle 1 on a spring to pinned particle 0, no gravity, displaced by AMPLITUDE along x."""
    b = cw.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_particle((0.0, 0.0, 0.0), mass=MASS, pinned=True)
    b.add_particle((REST + AMPLITUDE, 0.0, 0.0), mass=MASS)
    b.add_spring(0, 1, STIFFNESS, rest_length=REST)
    model = b.finalize(device)
    return model, solver_cls(model, strain_limit=None, **opts)


def energy(state):
    x = state.particle_q.numpy()[1, 0] - REST
    v = state.particle_qd.numpy()[1]
    return 0.5 * MASS * float(v @ v) + 0.5 * STIFFNESS * x * x


@pytest.mark.parametrize("solver_cls", [cw.SolverSymplecticEuler, cw.SolverRK4])
def test_spring_period(device, solver_cls):
    """Check that a particle on a spring oscillates with period 2 pi sqrt(m/k) to 0.5 %."""
    model, solver = oscillator(device, solver_cls)
    dt = 1.0e-3  # z = 0.01: numerical period error ~1e-5 (physics.md 1(d)), far below 0.5 %
    xs = []
    run_steps(solver, model, 6300, dt, record=lambda k, s: xs.append(s.particle_q.numpy()[1, 0] - REST))
    xs = np.asarray(xs)
    t = (np.arange(len(xs)) + 1) * dt
    # Downward zero crossings, linearly interpolated.
    idx = np.flatnonzero((xs[:-1] > 0) & (xs[1:] <= 0))
    crossings = t[idx] + dt * xs[idx] / (xs[idx] - xs[idx + 1])
    period = float(np.mean(np.diff(crossings)))
    expected = 2.0 * math.pi * math.sqrt(MASS / STIFFNESS)
    assert len(crossings) >= 9
    assert abs(period / expected - 1.0) < 5e-3, (period, expected)


@pytest.mark.parametrize(
    "solver_cls, factor",
    [
        (cw.SolverExplicitEuler, lambda z: 1.0 + z * z),  # |R(iz)|^2 of forward Euler
        (cw.SolverImplicitEuler, lambda z: 1.0 / (1.0 + z * z)),  # backward Euler
        (cw.SolverMidpoint, lambda z: 1.0 + z**4 / 4.0),
        (cw.SolverRK4, lambda z: 1.0 - z**6 / 72.0 + z**8 / 576.0),
    ],
)
def test_energy_factor_per_step(device, solver_cls, factor):
    """Check that each one-step method scales the oscillator energy by exactly |R(iz)|^2 per step."""
    opts = {"tolerance": 1e-7} if solver_cls is cw.SolverImplicitEuler else {}
    model, solver = oscillator(device, solver_cls, **opts)
    dt = 0.05  # z = 0.5: factors 1.25, 0.8, 1.0156, 0.99978
    z = math.sqrt(STIFFNESS / MASS) * dt
    s = model.state()
    e0 = energy(s)
    steps = 20
    s = run_steps(solver, model, steps, dt, state=s)
    # float32 positions: ~1e-6 relative per step on the energy, tolerance 1e-4 over 20 steps.
    assert energy(s) / e0 == pytest.approx(factor(z) ** steps, rel=1e-4)


def test_symplectic_euler_bounded_energy(device):
    """Check that symplectic Euler keeps the energy within [Q/(1+z/2), Q/(1-z/2)] and conserves Q."""
    model, solver = oscillator(device, cw.SolverSymplecticEuler)
    dt = 0.05
    z = 10.0 * dt
    w2 = STIFFNESS / MASS
    q_values, energies = [], []

    def record(k, s):
        x = s.particle_q.numpy()[1, 0] - REST
        v = s.particle_qd.numpy()[1, 0]
        energies.append(energy(s))
        # Q = v^2/2 + w^2 x^2/2 - h w^2 x v / 2 (per unit mass), evaluated at (x_n, v_n) after the step.
        q_values.append(0.5 * v * v + 0.5 * w2 * x * x - 0.5 * dt * w2 * x * v)

    run_steps(solver, model, 400, dt, record=record)
    q = np.asarray(q_values) * MASS
    e = np.asarray(energies)
    assert np.ptp(q) / q.mean() < 1e-4
    assert e.max() <= q.mean() / (1 - z / 2) * (1 + 1e-4)
    assert e.min() >= q.mean() / (1 + z / 2) * (1 - 1e-4)


@pytest.mark.parametrize(
    "name, sign",
    [("symplectic_euler", -1.0), ("explicit_euler", 1.0), ("implicit_euler", -1.0), ("midpoint", 0.0), ("rk4", 0.0)],
)
def test_free_fall_offsets(device, name, sign):
    """Check x_n = x0 - g t^2/2 + sign * g h t / 2 per integrator (physics.md 1(e)); pins stay put."""
    g = 9.81
    b = cw.ModelBuilder(gravity=(0.0, -g, 0.0))
    b.add_particle((0.0, 0.0, 0.0), mass=0.1)
    b.add_particle((1.0, 0.0, 0.0), mass=0.1, pinned=True)
    model = b.finalize(device)
    solver = cw.make_solver(name, model, strain_limit=None)
    h, steps = 0.01, 100
    s = run_steps(solver, model, steps, h)
    t = h * steps
    x = s.particle_q.numpy()
    expected = -0.5 * g * t * t + sign * 0.5 * g * h * t  # offset 0.04905 m: tolerance 1e-4 m (float32)
    assert x[0, 1] == pytest.approx(expected, abs=1e-4)
    assert s.particle_qd.numpy()[0, 1] == pytest.approx(-g * t, rel=1e-5)  # velocities exact for all
    np.testing.assert_array_equal(x[1], [1.0, 0.0, 0.0])


@pytest.mark.parametrize("name", ["symplectic_euler", "implicit_euler"])
def test_terminal_velocity_of_sheet(device, name):
    """Check a face-down sheet falls at v_t = rho_A g / c_A (physics.md 1(f)) within 1 %."""
    rho, c_a, g = 0.2, 1.0, 9.81
    mat = cw.FabricMaterial(areal_density=rho, stretch_stiffness=10.0, shear_stiffness=1.0, bend_stiffness=0.0, drag_coefficient=c_a)
    b = cw.ModelBuilder(gravity=(0.0, -g, 0.0))
    # Grid in the local xy-plane rotated to horizontal (normal along y): face down.
    b.add_cloth_grid(resolution=(4, 4), size=(0.5, 0.5), material=mat, rotation=cw.quat_from_axis_angle((1, 0, 0), -90.0))
    model = b.finalize(device)
    solver = cw.make_solver(name, model, strain_limit=None)
    s = run_steps(solver, model, 1500, 0.002)  # 3 s = 15 tau, tau = rho/c = 0.2 s; h omega_max ~ 0.6
    v = s.particle_qd.numpy()
    m = model.particle_mass.numpy()
    v_com = float((m[:, None] * v).sum(0)[1] / m.sum())
    assert v_com == pytest.approx(-rho * g / c_a, rel=1e-2)


def test_edge_on_sheet_falls_freely(device):
    """Check a sheet falling edge-on feels no drag (normal velocity is zero)."""
    mat = cw.FabricMaterial(areal_density=0.2, stretch_stiffness=10.0, shear_stiffness=1.0, bend_stiffness=0.0, drag_coefficient=1.0)
    b = cw.ModelBuilder(gravity=(0.0, -9.81, 0.0))
    b.add_cloth_grid(resolution=(3, 3), size=(0.3, 0.3), material=mat)  # in the xy-plane: vertical
    model = b.finalize(device)
    s = run_steps(cw.SolverSymplecticEuler(model, strain_limit=None), model, 500, 0.002)
    # float32 round-off in the (zero) spring forces: 1e-4 relative
    assert s.particle_qd.numpy()[:, 1] == pytest.approx(-9.81, rel=1e-4)


def test_wind_drives_a_sheet(device):
    """Check a free sheet in uniform wind approaches the wind velocity along its normal."""
    mat = cw.FabricMaterial(areal_density=0.2, stretch_stiffness=10.0, shear_stiffness=1.0, bend_stiffness=0.0, drag_coefficient=1.0)
    b = cw.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_cloth_grid(resolution=(3, 3), size=(0.3, 0.3), material=mat)  # normal along z
    model = b.finalize(device)
    control = model.control()
    control.set_wind((0.0, 0.0, 2.0))
    s = run_steps(cw.SolverSymplecticEuler(model, strain_limit=None), model, 1500, 0.002, control=control)
    v = s.particle_qd.numpy()
    # v(t) = w (1 - exp(-t/tau)), tau = 0.2 s, t = 3 s: 2 (1 - 3e-7) m/s
    assert v[:, 2] == pytest.approx(2.0, rel=1e-3)
    assert np.abs(v[:, :2]).max() < 1e-3  # in-plane: only float32 round-off of the spring forces
