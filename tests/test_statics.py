"""Static shapes against exact references: hanging chains and strips (catenary)."""

import numpy as np
import pytest

import cloth_warp as cw
from analytic import discrete_chain, elastic_catenary_sag
from conftest import run_steps

SPAN, LENGTH, MASS, EA, G = 1.0, 1.2, 0.1, 10.0, 9.81


def chain_model(device, n, global_damping):
    """n springs of rest length LENGTH/n between two pins SPAN apart, started on a sagging parabola."""
    b = cw.ModelBuilder(gravity=(0.0, -G, 0.0), global_damping=global_damping)
    xs = np.linspace(-SPAN / 2, SPAN / 2, n + 1)
    ys = -0.3 * (1.0 - (2.0 * xs / SPAN) ** 2)
    for i, (x, y) in enumerate(zip(xs, ys)):
        b.add_particle((x, y, 0.0), mass=MASS / n, pinned=i in (0, n))
    for i in range(n):
        b.add_spring(i, i + 1, EA / (LENGTH / n), rest_length=LENGTH / n)
    return b.finalize(device)


def test_discrete_reference_matches_table():
    """Check our discrete-chain reference against physics.md 1(c) (N = 16, EA = 10 N: sag 0.333780 m)."""
    h, x, z = discrete_chain(16, SPAN, LENGTH, MASS, EA / (LENGTH / 16))
    assert -z.min() == pytest.approx(0.333780, abs=2e-6)
    assert h == pytest.approx(0.331661, abs=2e-6)


@pytest.mark.parametrize("name, dt, steps", [("implicit_euler", 0.02, 400), ("symplectic_euler", 2e-3, 4000)])
def test_chain_matches_discrete_equilibrium(device, name, dt, steps):
    """Check a damped chain settles onto the exact discrete equilibrium (1e-4 of the sag)."""
    n = 16
    model = chain_model(device, n, global_damping=5.0)
    opts = {"tolerance": 1e-6} if name == "implicit_euler" else {}
    s = run_steps(cw.make_solver(name, model, strain_limit=None, **opts), model, steps, dt)
    x = s.particle_q.numpy()
    _, xr, zr = discrete_chain(n, SPAN, LENGTH, MASS, EA / (LENGTH / n))
    sag = zr.min()
    # float32 positions and a residual velocity after settling: 1e-4 relative to the sag.
    np.testing.assert_allclose(x[:, 1], zr, atol=1e-4 * abs(sag))
    np.testing.assert_allclose(x[:, 0], xr - SPAN / 2, atol=1e-4 * abs(sag))


def test_chain_sag_converges_to_elastic_catenary(device):
    """Check the chain's sag is within 1 % of the elastic catenary at N = 16 and closer at N = 64."""
    ref = elastic_catenary_sag(SPAN, LENGTH, MASS * G / LENGTH, EA)  # 0.333138 m
    errors = {}
    for n in (16, 64):
        model = chain_model(device, n, global_damping=5.0)
        s = run_steps(cw.SolverImplicitEuler(model, strain_limit=None, tolerance=1e-6, max_iterations=500), model, 400, 0.02)
        errors[n] = abs(-s.particle_q.numpy()[:, 1].min() / ref - 1.0)
    assert errors[16] < 1e-2
    assert errors[64] < errors[16]  # discretisation error O(1/N^2): 0.19 % -> 0.013 %


def test_cloth_strip_sag_matches_catenary(device):
    """Check a cloth strip (grid 32 x 1, Choi-Ko springs) hung by its end columns sags like the catenary, 1 %."""
    width = 0.02
    mat = cw.FabricMaterial(areal_density=MASS / (LENGTH * width), stretch_stiffness=EA / width, shear_stiffness=1.0,
                            bend_stiffness=0.0)
    b = cw.ModelBuilder(global_damping=5.0)
    c = b.add_cloth_grid(resolution=(32, 1), size=(LENGTH, width), material=mat, position=(-LENGTH / 2, 0.0, 0.0))
    ends = np.concatenate([c.select("edge:left"), c.select("edge:right")])
    b.pin(ends)
    model = b.finalize(device)
    control = model.control()
    target = control.pin_target.numpy()
    target[c.select("edge:left"), 0] = -SPAN / 2
    target[c.select("edge:right"), 0] = SPAN / 2
    control.pin_target.assign(target)
    state = model.state()
    x = state.particle_q.numpy()
    u = x[:, 0] / (LENGTH / 2)  # start on a sagging parabola between the targets
    x[:, 0] = u * SPAN / 2
    x[:, 1] = -0.3 * (1.0 - u * u)
    state.particle_q.assign(x)
    s = run_steps(cw.SolverImplicitEuler(model, strain_limit=None, tolerance=1e-6, max_iterations=500), model, 400, 0.02,
                  state=state, control=control)
    sag = -s.particle_q.numpy()[:, 1].min()
    ref = elastic_catenary_sag(SPAN, LENGTH, MASS * G / LENGTH, EA)
    assert sag == pytest.approx(ref, rel=1e-2)
