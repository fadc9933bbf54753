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
    relaxation: float,

    # outputs
    x_out: wp.array(dtype=wp.vec3),
):
    """Shorten the colour's over-stretched springs to (1 + max_strain) L, split by inverse mass (Provot 1995).

    With relaxation > 1 the excess is over-corrected (successive over-relaxation, never below the rest
    length), which speeds up the propagation of corrections along long chains of active constraints.
    """
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
    excess = wp.min(relaxation * (length - limit), length - spring_rest_length[s])
    x_out[i] = xi - (wi / (wi + wj)) * excess / length * d


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


@wp.kernel
def apply_attachment_limit(
    # Strain limiter data
    attachment_particle: wp.array2d(dtype=wp.int32),
    attachment_rest_distance: wp.array2d(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    # State in
    x_in: wp.array(dtype=wp.vec3),
    max_strain: float,
    # outputs
    x_out: wp.array(dtype=wp.vec3),
):
    """Long-range attachments (Kim et al. 2012): |x_i - x_p| <= (1 + max_strain) g_ip for pinned p.

    g_ip is the shortest rest length along limited springs from i to p, so any state whose springs all
    satisfy the strain limit satisfies these too; projecting onto them removes in one pass the global
    stretch that local passes would need O(n^2) sweeps for.
    """
    i = wp.tid()
    xi = x_in[i]
    if particle_pinned[i] == 0:
        for a in range(attachment_particle.shape[1]):
            p = attachment_particle[i, a]
            if p >= 0:
                d = xi - x_in[p]
                length = wp.length(d)
                limit = (1.0 + max_strain) * attachment_rest_distance[i, a]
                if length > limit:
                    xi = x_in[p] + (limit / length) * d
    x_out[i] = xi


@wp.kernel(enable_backward=False)
def apply_strain_limit_springs(
    # Model
    color_springs: wp.array(dtype=wp.int32),
    first: int,
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_rest_length: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    max_strain: float,
    relaxation: float,
    # updated in place (forward only: no two springs of a colour share a particle, so no races)
    x_out: wp.array(dtype=wp.vec3),
):
    """The same projection as apply_strain_limit_color, one thread per spring of the colour, in place."""
    s = color_springs[first + wp.tid()]
    a = spring_indices[s, 0]
    b = spring_indices[s, 1]
    wa = 0.0
    wb = 0.0
    if particle_pinned[a] == 0:
        wa = 1.0 / particle_mass[a]
    if particle_pinned[b] == 0:
        wb = 1.0 / particle_mass[b]
    if wa + wb == 0.0:
        return
    d = x_out[a] - x_out[b]
    length = wp.length(d)
    limit = (1.0 + max_strain) * spring_rest_length[s]
    if length <= limit or length < LENGTH_EPS:
        return
    excess = wp.min(relaxation * (length - limit), length - spring_rest_length[s])
    corr = (excess / ((wa + wb) * length)) * d
    x_out[a] = x_out[a] - wa * corr
    x_out[b] = x_out[b] + wb * corr
