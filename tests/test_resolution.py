"""The same material gives the same shape at every resolution (SI material, resolution-free weights)."""

import numpy as np
import pytest

import cloth_warp as cw
from conftest import run_steps


def drooping_plate(device, n, material, length=1.0):
    """A square sheet clamped along one edge (two pinned columns), n x n cells, drooping under gravity."""
    a = length / n
    b = cw.ModelBuilder(global_damping=2.0)
    c = b.add_cloth_grid(resolution=(n + 1, n), size=(length + a, length), position=(-a, 0.0, 0.0), material=material,
                         rotation=cw.quat_from_axis_angle((1, 0, 0), 90.0))
    idx = c.indices().reshape(n + 1, n + 2)
    b.pin(idx[:, :2].ravel())
    return b.finalize(device), idx[:, -1]


@pytest.mark.slow
def test_plate_shape_converges_under_refinement(device):
    """Check a clamped plate's free-edge deflection agrees at 16^2, 32^2, 64^2, with differences shrinking."""
    rho, g = 0.15, 9.81
    mat = cw.FabricMaterial(areal_density=rho, stretch_stiffness=300.0, shear_stiffness=30.0, bend_stiffness=rho * g / 4.0)
    tips = {}
    for n in (16, 32, 64):
        model, tip = drooping_plate(device, n, mat)
        s = run_steps(cw.SolverImplicitEuler(model, strain_limit=None, tolerance=1e-4, max_iterations=2000), model, 100, 0.05)
        x = s.particle_q.numpy()[tip]
        tips[n] = -x[:, 1]  # deflection along the free edge, n + 1 samples
    # Compare at the common samples (every 4th of 64, every 2nd of 32, all of 16).
    d16, d32, d64 = tips[16], tips[32][::2], tips[64][::4]
    err16 = np.abs(d16 - d64).max()
    err32 = np.abs(d32 - d64).max()
    print(f"free-edge deflection mid: {d16[8]:.5f} {d32[8]:.5f} {d64[8]:.5f} m; max |16-64| {err16:.2e}, |32-64| {err32:.2e}")
    assert err32 < err16  # discretisation error shrinks with refinement
    assert err16 < 1e-2 * d64.max()  # and is already below 1 % of the deflection at 16^2
