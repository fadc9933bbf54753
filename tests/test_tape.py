"""Explicit steps run under wp.Tape: a short taped rollout's gradient matches central finite differences."""

import numpy as np
import pytest
import warp as wp

import cloth_warp as cw

STEPS, DT = 20, 1.0 / 600.0


def hanging(device, membrane=None):
    b = cw.ModelBuilder()
    c = b.add_cloth_grid(resolution=(4, 4), size=(0.4, 0.4), material=cw.materials.COTTON.replace(stretch_stiffness=50.0),
                         membrane=membrane)
    b.pin(c.select("corner:top_left"))
    b.pin(c.select("corner:top_right"))
    return b.finalize(device, requires_grad=True)


def rollout(model, v0):
    # States are created before any recording: model.state() clones, and a clone recorded on the tape
    # would hand the initial-state gradient on to the model's arrays.
    states = [model.state() for _ in range(STEPS + 1)]
    states[0].particle_qd.assign(v0)
    return states


def advance(model, states):
    control = model.control()
    solver = cw.SolverSymplecticEuler(model, strain_limit=0.1, strain_limit_iterations=2)
    for k in range(STEPS):
        solver.step(states[k], states[k + 1], control, DT)


@pytest.mark.parametrize("membrane", ["springs", "element"])
def test_taped_rollout_gradient_matches_finite_differences(device, rng, membrane):
    """Check d(w . x_T)/d(v_0) through 20 symplectic steps with strain limiting against central differences, with the
    membrane on springs and on elements."""
    model = hanging(device, membrane)
    n = model.particle_count
    v0 = rng.normal(scale=0.3, size=(n, 3)).astype(np.float32)
    w = rng.normal(size=(n, 3)).astype(np.float32)
    states = rollout(model, v0)
    tape = wp.Tape()
    with tape:
        advance(model, states)
    tape.backward(grads={states[-1].particle_q: wp.array(w, dtype=wp.vec3, device=device)})
    grad = states[0].particle_qd.grad.numpy()
    assert np.isfinite(grad).all()

    def loss(v):
        s = rollout(model, v)
        advance(model, s)
        return float((s[-1].particle_q.numpy() * w).sum())

    # along the gradient: the directional derivative is |grad| (a random direction can be nearly orthogonal to it,
    # leaving a derivative at the difference's noise)
    d = (grad / np.linalg.norm(grad)).astype(np.float32)
    # float32: L ~ 0.56 carries a round-off of ~5e-7 after 20 steps, which at eps = 1e-3 puts a noise of ~2.5e-4 on
    # the difference (3 % of a derivative of 9e-3 the element cloth had along a random direction). eps = 1e-2 cuts it
    # to ~3e-5; Richardson extrapolation (4 D(eps/2) - D(eps)) / 3 removes the O(eps^2) truncation.
    eps = 1e-2

    def central(e):
        return (loss(v0 + e * d) - loss(v0 - e * d)) / (2 * e)

    fd = (4.0 * central(eps / 2) - central(eps)) / 3.0
    ad = float((grad * d).sum())
    assert np.sign(ad) == np.sign(fd)
    assert abs(ad - fd) <= 1e-2 * abs(fd), (ad, fd)
