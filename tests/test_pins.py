"""Pins and handles: hard pins follow keyframed rigid transforms exactly, soft pins hang at m g / k."""

import math

import numpy as np
import pytest

import cloth_warp as cw
from conftest import run_steps


@pytest.mark.parametrize("name", ["symplectic_euler", "rk4", "implicit_euler"])
def test_handle_follows_keyframes(device, name):
    """Check a handle's particles sit exactly on the keyframed rigid transform (translation + rotation) each frame."""
    b = cw.ModelBuilder()
    cloth = b.add_cloth_grid(resolution=(4, 4), size=(0.4, 0.4), material="cotton")
    top = cloth.select("edge:top")
    quarter = cw.quat_from_axis_angle((0, 0, 1), 90.0)
    handle = b.add_handle(top, [(0.0, (0, 0, 0)), (0.5, (0.2, 0.1, 0.0), quarter)])
    model = b.finalize(device)
    # h omega_max ~ 1.5 with 32 substeps for the explicit methods (cotton, 10 cm cells)
    sim = cw.Simulator(model, cw.make_solver(name, model), fps=60, substeps=1 if name == "implicit_euler" else 32)
    rest = model.rest_positions[top]
    for _ in range(45):  # past the last keyframe: the transform is held
        sim.step_frame()
        expected = handle.targets(rest, sim.time)
        np.testing.assert_allclose(sim.positions()[top], expected, atol=1e-5)
    # After the last keyframe the handle is rotated by 90 degrees about z around its centroid.
    x = sim.positions()[top]
    direction = (x[-1] - x[0]) / np.linalg.norm(x[-1] - x[0])
    np.testing.assert_allclose(direction, [0.0, 1.0, 0.0], atol=1e-5)


def test_handle_interpolates_linearly():
    """Check translation is linear and rotation is slerped between keyframes, and held outside them."""
    h = cw.Handle("h", np.array([0]), [cw.Keyframe(1.0, (0, 0, 0)), cw.Keyframe(3.0, (2, 0, 0), cw.quat_from_axis_angle((0, 0, 1), 90.0))])
    t, r = h.transform_at(2.0)
    np.testing.assert_allclose(t, [1, 0, 0])
    np.testing.assert_allclose(r @ [1, 0, 0], [math.cos(math.pi / 4), math.sin(math.pi / 4), 0], atol=1e-12)
    np.testing.assert_allclose(h.transform_at(0.0)[0], [0, 0, 0])
    np.testing.assert_allclose(h.transform_at(5.0)[0], [2, 0, 0])


def test_handle_keyframes_must_increase():
    """Check non-increasing keyframe times are rejected."""
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(2, 2))
    with pytest.raises(ValueError, match="increase"):
        b.add_handle([0], [(1.0, (0, 0, 0)), (1.0, (1, 0, 0))])


@pytest.mark.parametrize("name", ["symplectic_euler", "implicit_euler"])
def test_soft_pin_hangs_at_weight_over_stiffness(device, name):
    """Check a particle on a soft pin (stiffness k) settles m g / k below its target."""
    m, k, g = 0.01, 2.0, 9.81
    b = cw.ModelBuilder(gravity=(0.0, -g, 0.0), global_damping=10.0)
    p = b.add_particle((0.0, 0.0, 0.0), mass=m)
    b.pin([p], stiffness=k)
    model = b.finalize(device)
    s = run_steps(cw.make_solver(name, model, strain_limit=None), model, 600, 1e-2 if name == "implicit_euler" else 5e-3)
    assert s.particle_q.numpy()[0, 1] == pytest.approx(-m * g / k, rel=1e-4)  # 4.905 cm
