"""Per-step statistics for divergence detection and reports (forward only)."""

import warp as wp

from .worlds import particle_world_of

wp.set_module_options({"enable_backward": False})

# The statistics block: the maxima first (atomic max), then the sums (atomic add); the kernel takes the two parts as
# two disjoint views, since Warp's deterministic mode takes one kind of atomic per array.
STAT_MAX_STRAIN = wp.constant(0)  # of the maxima
STAT_MAX_SPEED = wp.constant(1)
STAT_MAXIMA = wp.constant(2)
STAT_KINETIC_ENERGY = wp.constant(0)  # of the sums
STAT_NONFINITE = wp.constant(1)
STAT_GRAVITY_POTENTIAL = wp.constant(2)
STAT_SUMS = wp.constant(3)


@wp.kernel
def eval_step_statistics(
    # Model
    spring_offsets: wp.array(dtype=wp.int32),
    spring_ids: wp.array(dtype=wp.int32),
    spring_role: wp.array(dtype=wp.int32),
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_rest_length: wp.array(dtype=float),
    spring_limited: wp.array(dtype=wp.int32),
    particle_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    # State
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    gravity: wp.vec3,
    origin: wp.vec3,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs (zeroed by the caller)
    maxima_out: wp.array(dtype=float),
    sums_out: wp.array(dtype=float),
):
    """Maxima: structural/shear strain and speed of free particles; sums: kinetic energy of free particles,
    non-finite count, and over free particles m g . (x - origin) (the work gravity did on them is its change) [J].
    Per world (batched worlds: world w's maxima at w STAT_MAXIMA, its sums at w STAT_SUMS)."""
    i = wp.tid()
    w = particle_world_of(i, particle_world, worlds)
    mo = w * STAT_MAXIMA
    so = w * STAT_SUMS
    xi = x[i]
    vi = v[i]
    finite = wp.isfinite(xi) and wp.isfinite(vi)
    if not finite:
        wp.atomic_add(sums_out, so + STAT_NONFINITE, 1.0)
        return
    strain = float(0.0)
    for k in range(spring_offsets[i], spring_offsets[i + 1]):
        s = spring_ids[k]
        role = spring_role[k]
        if spring_limited[s] != 0 and role == 0:  # each spring once, from its first endpoint
            strain = wp.max(strain, wp.length(xi - x[spring_indices[s, 1]]) / spring_rest_length[s] - 1.0)
    wp.atomic_max(maxima_out, mo + STAT_MAX_STRAIN, strain)
    if particle_pinned[i] == 0:
        speed2 = wp.dot(vi, vi)
        wp.atomic_add(sums_out, so + STAT_KINETIC_ENERGY, 0.5 * particle_mass[i] * speed2)
        wp.atomic_max(maxima_out, mo + STAT_MAX_SPEED, wp.sqrt(speed2))
        wp.atomic_add(sums_out, so + STAT_GRAVITY_POTENTIAL, particle_mass[i] * wp.dot(gravity, xi - origin))
