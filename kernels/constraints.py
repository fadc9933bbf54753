"""Provot strain limiting (deformation constraints) as colour-wise Gauss-Seidel passes."""

import warp as wp

LENGTH_EPS = wp.constant(1.0e-9)


@wp.kernel
def apply_strain_limit_color(
    # Model
    strain_limit_colors: wp.array2d(dtype=wp.int32),
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_rest_length: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    # State in
    x_in: wp.array(dtype=wp.vec3),
    color: int,
    max_strain: float,
    # outputs
    x_out: wp.array(dtype=wp.vec3),
):
    """Shorten the colour's over-stretched springs to (1 + max_strain) L, split by inverse mass (Provot 1995)."""
    i = wp.tid()
    xi = x_in[i]
    s = strain_limit_colors[color, i]
    if s < 0 or particle_pinned[i] != 0:
        x_out[i] = xi
        return
    j = spring_indices[s, 0]
    if j == i:
        j = spring_indices[s, 1]
    d = xi - x_in[j]
    length = wp.length(d)
    limit = (1.0 + max_strain) * spring_rest_length[s]
    if length <= limit or length < LENGTH_EPS:
        x_out[i] = xi
        return
    wi = 1.0 / particle_mass[i]
    wj = 0.0
    if particle_pinned[j] == 0:
        wj = 1.0 / particle_mass[j]
    x_out[i] = xi - (wi / (wi + wj)) * (length - limit) / length * d


@wp.kernel
def correct_velocity(
    x_before: wp.array(dtype=wp.vec3),
    x_after: wp.array(dtype=wp.vec3),
    v_in: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs
    v_out: wp.array(dtype=wp.vec3),
):
    """v_out = v_in + (x_after - x_before) / h: keep velocities consistent with the corrected positions."""
    i = wp.tid()
    v_out[i] = v_in[i] + (x_after[i] - x_before[i]) / dt
