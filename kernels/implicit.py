"""Baraff-Witkin implicit Euler: system blocks, matrix-free product, filtered PCG and block Jacobi.

One linearised backward-Euler step (physics.md 3(c)) solves for the velocity change dv

    A dv = b,   A = M' + h D + h^2 K,   b = h (f0 - h K v0),

with M' = M (1 + h gamma) + h^2 k_pin (global damping gamma, soft pins), K = -df/dx from
`spring_stiffness_block` (kept PSD), D = -df/dv from spring damping and air drag. Per spring the
system block is B_s = h D_s + h^2 K_s, so matrix-free

    (A p)_i = M'_i p_i + sum_s B_s (p_i - p_j) + h sum_t w_ti g_t (g_t . sum_c w_tc p_c),

with g_t = sqrt(c_A A_t) n_t and the corner weights w_tc of the drag (exact for linear drag), plus for
each Choi-Ko bend triple (a, m, b) the quadratic-bending term h^2 g_r (g . (p_a, p_m, p_b)) with
g = `bending_stiffness_weights` and g_r its entry for the particle's role; and for each triangle membrane
element the 9x9 block h D_e + h^2 K_e applied matrix-free (`membrane_product`: K_e = A B^T C B + A G(S+) (x) I,
Gauss-Newton plus the geometric stiffness of the positive part of the stress, so PSD; D_e = A B^T C_d B).
For each plate-bending stencil (forces.py: points j, weights c_j, stiffness S) the constant block h^2 (c_i . S c_j) I,
applied as h^2 U(p) S c_i with U(p) = sum_j p_j c_j^T (forces.py `scatter_plate_product`).
Hard pins are constraints through the filter S_i = 0 (Baraff & Witkin's modified PCG, solved in its
projected form): dv_i = z_i = (target_i - x0_i) / h - v0_i there.

Reductions (dot products) accumulate in float64 through atomics into a 3-slot array (`cg_sums`) that
one-thread kernels move into `cg_scalars`, one row per iteration, so no host round trip is needed inside an
iteration: column 0 holds r.s (s = P r), column 1 c.Ac, column 2 r.r. The same one-thread kernels compute
the iteration's alpha and beta once (`cg_step_size`, `end_cg_iteration`), which every thread read from there. (Chronopoulos & Gear's single-reduction CG, one pass over the particles fewer per
iteration, was tried: its recurrence for A c loses accuracy over the thousands of iterations a 1e-5 solve of
stiff membranes takes, 2500-3000+ iterations where this form needs 1300-2200, so it is not used.)
"""

import warp as wp

from .forces import (
    bending_stiffness_weights,
    corner_weight,
    membrane_product,
    membrane_system,
    membrane_voigt,
    add_plate_product,
    plate_curvature,
    spring_damping_block,
    spring_stiffness_block,
    total_force,
    triangle_drag_force,
)
from . import contracting_cpu_flags
from .worlds import (RANGE_BENDS, RANGE_MEMBRANES, RANGE_PARTICLES, RANGE_PLATES, RANGE_SPRINGS, RANGE_TRIANGLES, particle_world_of,
                     world_slot)

wp.set_module_options({"cpu_compiler_flags": contracting_cpu_flags()})

LENGTH_EPS = wp.constant(1.0e-9)
CG_RS = wp.constant(0)
CG_CAC = wp.constant(1)
CG_RR = wp.constant(2)
CG_COLUMNS = wp.constant(3)
CG_ALPHA = wp.constant(0)  # the iteration's step sizes (float32, computed once per iteration by one thread)
CG_BETA = wp.constant(1)
JACOBI_CHECK_ROW = wp.constant(1)  # block Jacobi's residual checks accumulate |r|^2 here (row 0 keeps |r_0|^2)
# The solve's loop control (int32, read by wp.capture_while and the guarded kernels) and status (float64).
LOOP_RUNNING = wp.constant(0)
LOOP_ITERATION = wp.constant(1)
LOOP_CHECK = wp.constant(2)  # block Jacobi: a residual check is due before the next iteration
LOOP_CARRIED = wp.constant(3)  # iterations of the step's earlier solves (a re-solve after contacts were released)
LOOP_BEST = wp.constant(4)  # CG: this iteration's dv has the smallest residual yet (`cg_direction` keeps it)
LOOP_SIZE = wp.constant(5)
# Collider contacts in the solve: the release loop's state (int32) and its cap of re-solves per step.
RELEASE_FLAG = wp.constant(0)  # a contact was released: solve again (batched: the batch's, set while any world's is)
RELEASE_ROUNDS = wp.constant(1)
RELEASE_RESOLVING = wp.constant(2)  # batched: this world takes part in the re-solve (set by begin_contact_resolve)
# A friction damper (eval_contact_friction_terms; self-contacts: kernels/contact.py) holds its contact, the slip then
# taken out, when the solved slip is within this factor of the stick speed (the solve's round-off stays below it).
SLIP_ALLOWANCE = wp.constant(1.01)
RELEASE_SIZE = wp.constant(3)  # per world, laid out as the loop state (kernels/worlds.py world_slot)
# `contact_released` of a contact admitted within its step (kernels/contact.py admit_collider_contacts): it may still be
# released (-1, a contact taken back, may not; collider + 1: released)
ADMITTED = wp.constant(-2)
# Indices into the contacts' counters (kernels/contact.py counts them, end_linear_solve records them), per world.
COUNT_CONTACTS = wp.constant(0)  # collider contacts
COUNT_SELF_CONTACTS = wp.constant(1)  # self-contact elements
COUNT_SIZE = wp.constant(2)  # per world, laid out as the loop state (kernels/worlds.py world_slot)
# Batched worlds (Model.world_count W > 1): every per-solve scalar is kept per world, world w's at w * <size> of its
# array (cg_sums, cg_step, solve status and record, the columns of cg_scalars); the loop state of world w sits at
# LOOP_SIZE * (1 + w) of `loop`, whose first LOOP_SIZE entries are then the batch's: LOOP_RUNNING while any world
# iterates, LOOP_ITERATION the most iterations of a world. With one world its loop state is the first entries.
STATUS_REFERENCE = wp.constant(0)  # |S (b - A z)|^2 of the zero guess: the tolerance is relative to it
STATUS_STOP = wp.constant(1)  # the relative residual at which this solve stops
STATUS_RELATIVE = wp.constant(2)  # the last relative residual measured (NaN: the system is not finite)
STATUS_BEST = wp.constant(3)  # CG: the smallest |r|^2 of this solve's iterations (its dv kept in `dv_best`)
STATUS_ERROR_TARGET = wp.constant(4)  # CG: the r.s at or below which the solve's velocity error is small enough (begin_linear_solve)
STATUS_SIZE = wp.constant(5)
# The smallest relative residual a solve is asked for (float32's floor): a warm start's reduction and the velocity-error
# target stop there.
SOLVE_FLOOR = wp.constant(1.0e-6)
# The record of solves since its reset (float64), read once per frame.
RECORD_SOLVES = wp.constant(0)
RECORD_ITERATIONS = wp.constant(1)
RECORD_MOST_ITERATIONS = wp.constant(2)
RECORD_FAILED = wp.constant(3)  # non-finite residual: the step's result is meaningless
RECORD_FIRST_FAILED = wp.constant(4)  # the 1-based solve (since the reset) that failed first, 0 if none
RECORD_UNCONVERGED = wp.constant(5)  # finite, above the tolerance at the cap of iterations
RECORD_WORST_RESIDUAL = wp.constant(6)  # the largest finite relative residual a solve ended with
RECORD_LAST_RESIDUAL = wp.constant(7)
RECORD_CONTACTS = wp.constant(8)  # collider contacts constrained in the solves (summed over them)
RECORD_RESOLVES = wp.constant(9)  # re-solves after contacts were released
RECORD_SELF_CONTACTS = wp.constant(10)  # self-contact elements in the systems (summed over the solves)
RECORD_SIZE = wp.constant(11)
# A membrane element's diagonal blocks enter the block-diagonal preconditioner P^-1 this many times over.
# Block Jacobi (dv <- dv + P (b - A dv)) converges when 2 P^-1 - A is positive definite: a spring's 6x6 block
# satisfies it with weight 1, a 3-corner element only with 3/2 (a PSD matrix of 3x3 blocks is <= 3x its block
# diagonal). With weight 1 Jacobi diverges on element cloth at any h^2 k / m above ~1; CG only needs P SPD.
MEMBRANE_DIAGONAL_WEIGHT = wp.constant(1.5)


@wp.func
def world_loop(w: int, worlds: int):
    """Where world w's loop state starts in `loop` (see above)."""
    return world_slot(w, worlds, LOOP_SIZE)


@wp.func
def world_iterates(w: int, worlds: int, loop: wp.array(dtype=wp.int32)):
    """Whether world w is still iterating (always with one world: the loop body only runs then). The CG's per-particle
    kernels skip batched worlds that stopped, which so keep their dv, residual and direction."""
    if worlds == 1:
        return True
    return loop[world_loop(w, worlds) + LOOP_RUNNING] != 0


@wp.kernel(enable_backward=False)
def eval_spring_system_blocks(
    # Model
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    spring_middle: wp.array(dtype=wp.int32),
    # State in
    x: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs
    stiffness_block_out: wp.array(dtype=wp.mat33),
    system_block_out: wp.array(dtype=wp.mat33),
    spring_compact_out: wp.array(dtype=wp.vec4),
    bend_vector_out: wp.array(dtype=wp.vec3),
):
    """K_s = -df_i/dx_i and B_s = h D_s + h^2 K_s for linear springs, and B_s's compact form (`spring_compact`);
    g for bend triples."""
    s = wp.tid()
    xi = x[spring_indices[s, 0]]
    xj = x[spring_indices[s, 1]]
    m = spring_middle[s]
    if m >= 0:
        stiffness_block_out[s] = wp.mat33(0.0)
        system_block_out[s] = wp.mat33(0.0)
        spring_compact_out[s] = wp.vec4(0.0)
        bend_vector_out[s] = bending_stiffness_weights(xi, x[m], xj, spring_stiffness[s])
        return
    k_block = spring_stiffness_block(xi, xj, spring_rest_length[s], spring_stiffness[s])
    d_block = spring_damping_block(xi, xj, spring_damping[s])
    stiffness_block_out[s] = k_block
    system_block_out[s] = dt * d_block + dt * dt * k_block
    spring_compact_out[s] = spring_compact(xi, xj, spring_rest_length[s], spring_stiffness[s], spring_damping[s], dt)
    bend_vector_out[s] = wp.vec3(0.0)


@wp.func
def spring_compact(xi: wp.vec3, xj: wp.vec3, rest_length: float, stiffness: float, damping: float, dt: float):
    """A linear spring's system block B_s = h D_s + h^2 K_s = a I + u u^T as (u_x, u_y, u_z, a): with n the unit
    direction and t = max(0, 1 - L/l) (`spring_stiffness_block`, `spring_damping_block`), a = h^2 k t and
    u = sqrt(h c + h^2 k (1 - t)) n (c, k >= 0); 16 bytes where the 3x3 block takes 36, for the CG's product."""
    d = xi - xj
    length2 = wp.dot(d, d)
    if length2 < LENGTH_EPS * LENGTH_EPS:  # (before the square root: its adjoint at a closed seam is 0 / 0)
        if rest_length <= LENGTH_EPS:  # a zero-length spring (a seam) closed: h^2 k I
            return wp.vec4(0.0, 0.0, 0.0, dt * dt * stiffness)
        return wp.vec4(0.0)
    length = wp.sqrt(length2)
    n = d / length
    t = wp.max(0.0, 1.0 - rest_length / length)
    a = dt * dt * stiffness * t
    u = wp.sqrt(wp.max(dt * damping + dt * dt * stiffness * (1.0 - t), 0.0)) * n
    return wp.vec4(u[0], u[1], u[2], a)


@wp.func
def compact_product(c: wp.vec4, d: wp.vec3):
    """B_s d for a spring's compact block (`spring_compact`)."""
    u = wp.vec3(c[0], c[1], c[2])
    return c[3] * d + wp.dot(u, d) * u


@wp.func
def role_weight(g: wp.vec3, role: int):
    """Entry of a triple's (a, m, b)-ordered vector for a particle of `role` (0: a, 1: b, 2: m)."""
    if role == 0:
        return g[0]
    if role == 1:
        return g[2]
    return g[1]


@wp.func
def triple_dot(g: wp.vec3, p: wp.array(dtype=wp.vec3), a: int, m: int, b: int):
    """sum over the triple's particles of g_r p_r."""
    return g[0] * p[a] + g[1] * p[m] + g[2] * p[b]


@wp.func
def drag_vector(xa: wp.vec3, xb: wp.vec3, xc: wp.vec3, drag_coefficient: float):
    """g_t = sqrt(c_A A_t) n_t of a triangle (0 when degenerate)."""
    cr = wp.cross(xb - xa, xc - xa)
    twice_area = wp.length(cr)
    if twice_area < LENGTH_EPS:
        return wp.vec3(0.0)
    return wp.sqrt(drag_coefficient * 0.5 * twice_area) * (cr / twice_area)


@wp.kernel(enable_backward=False)
def eval_triangle_drag_vectors(
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_drag: wp.array(dtype=float),
    x: wp.array(dtype=wp.vec3),
    # outputs
    drag_vector_out: wp.array(dtype=wp.vec3),
):
    """g_t = sqrt(c_A A_t) n_t, so that -df_a/dv_b = w_a w_b g_t g_t^T for corners a, b of t."""
    t = wp.tid()
    drag_vector_out[t] = drag_vector(x[tri_indices[t, 0]], x[tri_indices[t, 1]], x[tri_indices[t, 2]], tri_drag[t])


@wp.func
def effective_mass(i: int, particle_mass: wp.array(dtype=float), particle_pin_stiffness: wp.array(dtype=float), global_damping: float, dt: float):
    """M'_i = m_i (1 + h gamma) + h^2 k_pin."""
    return particle_mass[i] * (1.0 + dt * global_damping) + dt * dt * particle_pin_stiffness[i]


@wp.func
def is_pinched(height: float, thickness: float):
    """Whether a collider contact landing `height` [m] above its surface (kernels/contact.py eval_collider_contacts) is
    pinched between it and a surface facing it: landed below the collider's `thickness` [m], as far from both. Such a
    contact is two-sided and frictionless (`eval_contact_release`)."""
    return height < thickness


@wp.func
def contact_projector(n: wp.vec3, m: wp.vec3):
    """S_i = I - n n^T - m m^T for a particle whose velocity is prescribed along the unit contact normal n (a collider
    contact in the solve) and, pinched in a crease (`kernels/contact.py` eval_collider_contacts), along the unit m
    orthogonal to it (zero elsewhere): only the crease's line is left free. n = m = 0 (no contact): the identity."""
    return wp.identity(n=3, dtype=float) - wp.outer(n, n) - wp.outer(m, m)


@wp.func
def contact_filter(n: wp.vec3, m: wp.vec3, a: wp.vec3):
    """S_i a (`contact_projector`): a less its parts along the contact normal n and the crease direction m."""
    return a - wp.dot(a, n) * n - wp.dot(a, m) * m


@wp.func
def tangential_part(n: wp.vec3, a: wp.vec3):
    """a less its part along the unit contact normal n: a contact's velocity or slip in the surface's tangent plane,
    which friction acts on (n = 0: a)."""
    return a - wp.dot(a, n) * n


@wp.func
def filtered_block_inverse(block: wp.mat33, n: wp.vec3, m: wp.vec3):
    """(S B S)^+ with S = `contact_projector`(n, m): the inverse of the SPD block B [kg] within the directions S leaves
    free, zero along n and m. S B^-1 S is not it: where B is soft along a direction leaning out of the plane (a cloth
    edge's particle: little mass, stiff springs along the edge), B^-1's large entries leak into the plane (up to ~100x
    the in-plane inverse), and as a contact's preconditioner block that took a pile's preconditioned spectrum to ~200
    (condition number 3e5, against 4.7e3)."""
    s = contact_projector(n, m)
    # (n n^T + m m^T is I - S, written so that without a crease the block is bit for bit the single normal's: the
    # garments' end states held still are chaotic, and (I - S) moved every one of them)
    return s * wp.inverse(s * block * s + (wp.trace(block) / 3.0) * (wp.outer(n, n) + wp.outer(m, m))) * s


@wp.func
def pinned_velocity_change(i: int, particle_pinned: wp.array(dtype=wp.int32), pin_target: wp.array(dtype=wp.vec3), x0: wp.array(dtype=wp.vec3), v0: wp.array(dtype=wp.vec3), dt: float):
    """z_i: the velocity change that lands a hard-pinned particle on its target (0 for free ones)."""
    if particle_pinned[i] == 0:
        return wp.vec3(0.0)
    return (pin_target[i] - x0[i]) / dt - v0[i]


@wp.func
def corner_value(i: int, c: wp.vec3i, y0: wp.vec3, y1: wp.vec3, y2: wp.vec3):
    """The entry y_k of the corner k of element c that is particle i."""
    if i == c[0]:
        return y0
    if i == c[1]:
        return y1
    return y2


@wp.func
def membrane_block_product(membrane_vertices: wp.array(dtype=wp.vec3i), membrane_block: wp.array2d(dtype=wp.mat33), e: int,
                           p: wp.array(dtype=wp.vec3)):
    """(h D_e + h^2 K_e) p on the three corners of element e, from the blocks stored by `eval_membrane_system_blocks`."""
    c = membrane_vertices[e]
    return membrane_product(membrane_block[e, 0], membrane_block[e, 1], membrane_block[e, 2], membrane_block[e, 3],
                            membrane_block[e, 4], p[c[0]], p[c[1]], p[c[2]])


@wp.func
def membrane_diagonal(b: wp.mat33, voigt: wp.mat33, geometric: float):
    """The corner's diagonal 3x3 block B_k^T V B_k + G_kk I of an element's matrix."""
    return wp.transpose(b) * voigt * b + geometric * wp.identity(n=3, dtype=float)


@wp.kernel(enable_backward=False)
def eval_membrane_system_blocks(
    # Model
    membrane_vertices: wp.array(dtype=wp.vec3i),
    membrane_rest_inverse: wp.array(dtype=wp.mat22),
    membrane_rest_area: wp.array(dtype=float),
    membrane_stiffness: wp.array(dtype=wp.vec4),
    membrane_damping: wp.array(dtype=wp.vec4),
    particle_pinned: wp.array(dtype=wp.int32),
    # State in
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    # Control
    pin_target: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs (the three per-particle ones accumulated: zeroed by the caller)
    membrane_block_out: wp.array2d(dtype=wp.mat33),
    membrane_kv_out: wp.array(dtype=wp.vec3),
    membrane_diag_out: wp.array(dtype=wp.mat33),
    membrane_az_out: wp.array(dtype=wp.vec3),
):
    """Per element the pieces of h D_e + h^2 K_e (B_0, B_1, B_2, A (h^2 C + h C_d), h^2 A G(S+)); scattered
    per corner: K_e v0 (for b), the diagonal blocks x MEMBRANE_DIAGONAL_WEIGHT (preconditioner) and (h D_e + h^2 K_e) z (pinned corners)."""
    e = wp.tid()
    c = membrane_vertices[e]
    a = c[0]
    b = c[1]
    d = c[2]
    area = membrane_rest_area[e]
    b0, b1, b2, voigt, geometric = membrane_system(x0[a], x0[b], x0[d], membrane_rest_inverse[e], area, membrane_stiffness[e],
                                                   membrane_damping[e], dt * dt, dt)
    membrane_block_out[e, 0] = b0
    membrane_block_out[e, 1] = b1
    membrane_block_out[e, 2] = b2
    membrane_block_out[e, 3] = voigt
    membrane_block_out[e, 4] = geometric
    # K_e v0: the stiffness alone (A C and the geometric part without h^2)
    k0, k1, k2 = membrane_product(b0, b1, b2, area * membrane_voigt(membrane_stiffness[e]), geometric * (1.0 / (dt * dt)),
                                  v0[a], v0[b], v0[d])
    wp.atomic_add(membrane_kv_out, a, k0)
    wp.atomic_add(membrane_kv_out, b, k1)
    wp.atomic_add(membrane_kv_out, d, k2)
    wp.atomic_add(membrane_diag_out, a, MEMBRANE_DIAGONAL_WEIGHT * membrane_diagonal(b0, voigt, geometric[0, 0]))
    wp.atomic_add(membrane_diag_out, b, MEMBRANE_DIAGONAL_WEIGHT * membrane_diagonal(b1, voigt, geometric[1, 1]))
    wp.atomic_add(membrane_diag_out, d, MEMBRANE_DIAGONAL_WEIGHT * membrane_diagonal(b2, voigt, geometric[2, 2]))
    za = pinned_velocity_change(a, particle_pinned, pin_target, x0, v0, dt)
    zb = pinned_velocity_change(b, particle_pinned, pin_target, x0, v0, dt)
    zd = pinned_velocity_change(d, particle_pinned, pin_target, x0, v0, dt)
    y0, y1, y2 = membrane_product(b0, b1, b2, voigt, geometric, za, zb, zd)
    wp.atomic_add(membrane_az_out, a, y0)
    wp.atomic_add(membrane_az_out, b, y1)
    wp.atomic_add(membrane_az_out, d, y2)


@wp.kernel(enable_backward=False)
def eval_plate_system(
    # Model
    plate_offsets: wp.array(dtype=wp.int32),
    plate_points: wp.array(dtype=wp.int32),
    plate_weights: wp.array(dtype=wp.vec3),
    plate_stiffness: wp.array(dtype=wp.mat33),
    particle_pinned: wp.array(dtype=wp.int32),
    # State in
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    # Control
    pin_target: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs (accumulated: zeroed by the caller; the first three shared with the membrane elements)
    kv_out: wp.array(dtype=wp.vec3),
    diag_out: wp.array(dtype=wp.mat33),
    az_out: wp.array(dtype=wp.vec3),
    plate_diagonal_out: wp.array(dtype=float),
):
    """Per stencil, scattered to its points: K v0 = U(v0) S c_j (for b), the diagonal h^2 (c_j . S c_j) x m/2 (m points:
    a PSD matrix of m blocks is at most m times its block diagonal, so block Jacobi converges; the preconditioner
    and `jacobi_iterate` use the same weight) and h^2 K z (pinned points)."""
    s = wp.tid()
    start = plate_offsets[s]
    end = plate_offsets[s + 1]
    stiffness = plate_stiffness[s]
    kv = plate_curvature(plate_points, plate_weights, start, end, v0) * stiffness
    uz = wp.mat33(0.0)
    for k in range(start, end):
        uz += wp.outer(pinned_velocity_change(plate_points[k], particle_pinned, pin_target, x0, v0, dt), plate_weights[k])
    az = (dt * dt) * uz * stiffness
    weight = 0.5 * float(end - start) * dt * dt
    for k in range(start, end):
        j = plate_points[k]
        c = plate_weights[k]
        d = weight * wp.dot(c, stiffness * c)
        wp.atomic_add(kv_out, j, kv * c)
        wp.atomic_add(diag_out, j, d * wp.identity(n=3, dtype=float))
        wp.atomic_add(plate_diagonal_out, j, d)
        wp.atomic_add(az_out, j, az * c)


@wp.func
def system_product(
    i: int,
    spring_offsets: wp.array(dtype=wp.int32),
    spring_ids: wp.array(dtype=wp.int32),
    spring_role: wp.array(dtype=wp.int32),
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_middle: wp.array(dtype=wp.int32),
    tri_offsets: wp.array(dtype=wp.int32),
    tri_ids: wp.array(dtype=wp.int32),
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_corner_weights: wp.array(dtype=wp.vec3),
    membrane_offsets: wp.array(dtype=wp.int32),
    membrane_ids: wp.array(dtype=wp.int32),
    membrane_vertices: wp.array(dtype=wp.vec3i),
    system_block: wp.array(dtype=wp.mat33),
    bend_vector: wp.array(dtype=wp.vec3),
    drag_vector: wp.array(dtype=wp.vec3),
    membrane_block: wp.array2d(dtype=wp.mat33),
    plate_product: wp.array(dtype=wp.vec3),
    mass_eff: float,
    p: wp.array(dtype=wp.vec3),
    dt: float,
):
    """(A p)_i, matrix-free (the plate stencils' part scattered beforehand into `plate_product`)."""
    pi = p[i]
    q = mass_eff * pi + plate_product[i]
    for k in range(spring_offsets[i], spring_offsets[i + 1]):
        s = spring_ids[k]
        role = spring_role[k]
        m = spring_middle[s]
        if m < 0:
            q += system_block[s] * (pi - p[spring_indices[s, 1 - role]])
        else:
            g = bend_vector[s]
            q += dt * dt * role_weight(g, role) * triple_dot(g, p, spring_indices[s, 0], m, spring_indices[s, 1])
    for k in range(tri_offsets[i], tri_offsets[i + 1]):
        t = tri_ids[k]
        a = tri_indices[t, 0]
        b = tri_indices[t, 1]
        w = tri_corner_weights[t]
        g = drag_vector[t]
        p_mean = w[0] * p[a] + w[1] * p[b] + w[2] * p[tri_indices[t, 2]]
        q += dt * corner_weight(i, a, b, w) * wp.dot(g, p_mean) * g
    for k in range(membrane_offsets[i], membrane_offsets[i + 1]):
        e = membrane_ids[k]
        y0, y1, y2 = membrane_block_product(membrane_vertices, membrane_block, e, p)
        q += corner_value(i, membrane_vertices[e], y0, y1, y2)
    return q


@wp.kernel(enable_backward=False)
def eval_implicit_system(
    # Model
    spring_offsets: wp.array(dtype=wp.int32),
    spring_ids: wp.array(dtype=wp.int32),
    spring_role: wp.array(dtype=wp.int32),
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_middle: wp.array(dtype=wp.int32),
    tri_offsets: wp.array(dtype=wp.int32),
    tri_ids: wp.array(dtype=wp.int32),
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_corner_weights: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    particle_pin_stiffness: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    # per-step element forces and blocks
    element_force: wp.array(dtype=wp.vec3),
    stiffness_block: wp.array(dtype=wp.mat33),
    system_block: wp.array(dtype=wp.mat33),
    bend_vector: wp.array(dtype=wp.vec3),
    drag_vector: wp.array(dtype=wp.vec3),
    membrane_kv: wp.array(dtype=wp.vec3),
    membrane_diag: wp.array(dtype=wp.mat33),
    membrane_az: wp.array(dtype=wp.vec3),
    # State in
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    # Control
    pin_target: wp.array(dtype=wp.vec3),
    gravity: wp.vec3,
    global_damping: float,
    dt: float,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    rhs_out: wp.array(dtype=wp.vec3),
    precond_out: wp.array(dtype=wp.mat33),
    dv_out: wp.array(dtype=wp.vec3),
    residual_out: wp.array(dtype=wp.vec3),
    preconditioned_out: wp.array(dtype=wp.vec3),
    search_out: wp.array(dtype=wp.vec3),
    cg_scalars_out: wp.array2d(dtype=wp.float64),
    effective_mass_out: wp.array(dtype=float),
):
    """b = h (f0 - h K v0), P = A_ii^-1 (filtered), dv = z, r0 = S (b - A z), s0 = c0 = P r0; M' per particle (what each
    CG iteration's `cg_product` multiplies by)."""
    i = wp.tid()
    f0 = total_force(i, particle_mass, particle_pin_stiffness, element_force, x0, v0, pin_target, gravity, global_damping)
    vi = v0[i]
    m_eff = effective_mass(i, particle_mass, particle_pin_stiffness, global_damping, dt)
    effective_mass_out[i] = m_eff
    k_v = particle_pin_stiffness[i] * vi
    diag = m_eff * wp.identity(n=3, dtype=float)
    a_z = wp.vec3(0.0)
    for k in range(spring_offsets[i], spring_offsets[i + 1]):
        s = spring_ids[k]
        role = spring_role[k]
        m = spring_middle[s]
        if m < 0:
            j = spring_indices[s, 1 - role]
            k_v += stiffness_block[s] * (vi - v0[j])
            diag += system_block[s]
            a_z -= system_block[s] * pinned_velocity_change(j, particle_pinned, pin_target, x0, v0, dt)
        else:
            g = bend_vector[s]
            gi = role_weight(g, role)
            end_a = spring_indices[s, 0]
            end_b = spring_indices[s, 1]
            k_v += gi * triple_dot(g, v0, end_a, m, end_b)
            diag += dt * dt * gi * gi * wp.identity(n=3, dtype=float)
            z_sum = g[0] * pinned_velocity_change(end_a, particle_pinned, pin_target, x0, v0, dt)
            z_sum += g[1] * pinned_velocity_change(m, particle_pinned, pin_target, x0, v0, dt)
            z_sum += g[2] * pinned_velocity_change(end_b, particle_pinned, pin_target, x0, v0, dt)
            a_z += dt * dt * gi * z_sum
    for k in range(tri_offsets[i], tri_offsets[i + 1]):
        t = tri_ids[k]
        g = drag_vector[t]
        w = tri_corner_weights[t]
        wi = corner_weight(i, tri_indices[t, 0], tri_indices[t, 1], w)
        diag += dt * wi * wi * wp.outer(g, g)
        z_mean = wp.vec3(0.0)
        for c in range(3):
            z_mean += w[c] * pinned_velocity_change(tri_indices[t, c], particle_pinned, pin_target, x0, v0, dt)
        a_z += dt * wi * wp.dot(g, z_mean) * g
    # membrane elements: scattered per particle by eval_membrane_system_blocks (zero without elements)
    k_v += membrane_kv[i]
    diag += membrane_diag[i]
    a_z += membrane_az[i]
    b = dt * (f0 - dt * k_v)
    rhs_out[i] = b
    if particle_pinned[i] != 0:
        precond_out[i] = wp.mat33(0.0)
        dv_out[i] = pinned_velocity_change(i, particle_pinned, pin_target, x0, v0, dt)
        residual_out[i] = wp.vec3(0.0)
        preconditioned_out[i] = wp.vec3(0.0)
        search_out[i] = wp.vec3(0.0)
        return
    p_inv = wp.inverse(diag)
    r = b - a_z
    s0 = p_inv * r
    precond_out[i] = p_inv
    dv_out[i] = wp.vec3(0.0)
    residual_out[i] = r
    preconditioned_out[i] = s0
    search_out[i] = s0
    col = particle_world_of(i, particle_world, worlds) * CG_COLUMNS
    wp.atomic_add(cg_scalars_out, 0, col + CG_RS, wp.float64(wp.dot(r, s0)))
    wp.atomic_add(cg_scalars_out, 0, col + CG_RR, wp.float64(wp.dot(r, r)))


# The element part of A p, one element per thread and scattered (each element's work done once, where the per-particle
# gather of `system_product` repeats a triple's or triangle's dot for every member): one kernel per kind of element
# (on the CPU backend three branch-free kernels take ~0.25 ms where one kernel branching on the kind took ~0.34 ms
# for a 64^2 cloth). product_out holds their sum (zero on entry: `cg_update` clears it); `cg_product` adds the mass term.


@wp.func
def add_spring_product(e: int, spring_ends: wp.array(dtype=wp.vec2i), spring_compact: wp.array(dtype=wp.vec4),
                       p: wp.array(dtype=wp.vec3), product_out: wp.array(dtype=wp.vec3)):
    """Linear spring e's part of A p added to its ends (`scatter_spring_product`)."""
    ends = spring_ends[e]
    y = compact_product(spring_compact[e], p[ends[0]] - p[ends[1]])
    wp.atomic_add(product_out, ends[0], y)
    wp.atomic_sub(product_out, ends[1], y)


@wp.func
def add_bend_product(e: int, bend_triples: wp.array(dtype=wp.vec3i), linear_spring_count: int, bend_vector: wp.array(dtype=wp.vec3),
                     p: wp.array(dtype=wp.vec3), dt: float, product_out: wp.array(dtype=wp.vec3)):
    """Bend triple e's part of A p added to its members (`scatter_bend_product`)."""
    t = bend_triples[e]
    g = bend_vector[e + linear_spring_count]
    d = (dt * dt) * triple_dot(g, p, t[0], t[1], t[2])
    wp.atomic_add(product_out, t[0], g[0] * d)
    wp.atomic_add(product_out, t[1], g[1] * d)
    wp.atomic_add(product_out, t[2], g[2] * d)


@wp.func
def add_membrane_product(e: int, membrane_vertices: wp.array(dtype=wp.vec3i), membrane_block: wp.array2d(dtype=wp.mat33),
                         p: wp.array(dtype=wp.vec3), product_out: wp.array(dtype=wp.vec3)):
    """Membrane element e's part of A p added to its corners (`scatter_membrane_product`)."""
    corners = membrane_vertices[e]
    y0, y1, y2 = membrane_block_product(membrane_vertices, membrane_block, e, p)
    wp.atomic_add(product_out, corners[0], y0)
    wp.atomic_add(product_out, corners[1], y1)
    wp.atomic_add(product_out, corners[2], y2)


@wp.func
def add_drag_product(e: int, tri_vertices: wp.array(dtype=wp.vec3i), tri_corner_weights: wp.array(dtype=wp.vec3),
                     drag_vector: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3), dt: float,
                     product_out: wp.array(dtype=wp.vec3)):
    """Triangle e's air-drag part of A p added to its corners (`scatter_drag_product`)."""
    c = tri_vertices[e]
    w = tri_corner_weights[e]
    g = drag_vector[e]
    y = (dt * wp.dot(g, w[0] * p[c[0]] + w[1] * p[c[1]] + w[2] * p[c[2]])) * g
    wp.atomic_add(product_out, c[0], w[0] * y)
    wp.atomic_add(product_out, c[1], w[1] * y)
    wp.atomic_add(product_out, c[2], w[2] * y)


@wp.kernel(enable_backward=False)
def scatter_spring_product(
    spring_ends: wp.array(dtype=wp.vec2i),
    spring_compact: wp.array(dtype=wp.vec4),
    p: wp.array(dtype=wp.vec3),
    # outputs (accumulated)
    product_out: wp.array(dtype=wp.vec3),
):
    """Linear springs (the first linear_spring_count springs): B_s (p_a - p_b) to a, its negative to b, from the
    compact block (`spring_compact`)."""
    add_spring_product(wp.tid(), spring_ends, spring_compact, p, product_out)


@wp.kernel(enable_backward=False)
def scatter_bend_product(
    bend_triples: wp.array(dtype=wp.vec3i),
    linear_spring_count: int,
    bend_vector: wp.array(dtype=wp.vec3),
    p: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs (accumulated)
    product_out: wp.array(dtype=wp.vec3),
):
    """Bend triples (springs linear_spring_count + e): h^2 g_r (g . p_triple) to each member r."""
    add_bend_product(wp.tid(), bend_triples, linear_spring_count, bend_vector, p, dt, product_out)


@wp.kernel(enable_backward=False)
def scatter_membrane_product(
    membrane_vertices: wp.array(dtype=wp.vec3i),
    membrane_block: wp.array2d(dtype=wp.mat33),
    p: wp.array(dtype=wp.vec3),
    # outputs (accumulated)
    product_out: wp.array(dtype=wp.vec3),
):
    """Membrane elements: (h D_e + h^2 K_e) p to their corners."""
    add_membrane_product(wp.tid(), membrane_vertices, membrane_block, p, product_out)


@wp.kernel(enable_backward=False)
def scatter_drag_product(
    tri_vertices: wp.array(dtype=wp.vec3i),
    tri_corner_weights: wp.array(dtype=wp.vec3),
    drag_vector: wp.array(dtype=wp.vec3),
    p: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs (accumulated)
    product_out: wp.array(dtype=wp.vec3),
):
    """Triangles' air drag: h w_r (g . p_mean) g to each corner r."""
    add_drag_product(wp.tid(), tri_vertices, tri_corner_weights, drag_vector, p, dt, product_out)


@wp.func
def cg_product_row(
    i: int,
    effective_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    search: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_crease: wp.array(dtype=wp.vec3),
    filtered: int,
    product_out: wp.array(dtype=wp.vec3),
):
    """Row i of q = S A c (the mass term added to the scattered element part, pinned rows filtered) into
    product_out; returns c_i . q_i."""
    if particle_pinned[i] != 0:
        product_out[i] = wp.vec3(0.0)
        return wp.float64(0.0)
    c = search[i]
    q = effective_mass[i] * c + product_out[i]
    if filtered != 0:  # collider contacts in the solve (`contact_normal`, `contact_crease`; the per-particle reads only then)
        q = contact_filter(contact_normal[i], contact_crease[i], q)
    product_out[i] = q
    return wp.float64(wp.dot(c, q))


@wp.kernel(enable_backward=False)
def cg_product(
    # Model
    particle_count: int,
    effective_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    search: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_crease: wp.array(dtype=wp.vec3),
    filtered: int,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    # outputs: holds the element part (the scatter_*_product kernels) on entry, q on exit
    product_out: wp.array(dtype=wp.vec3),
    cg_sums_out: wp.array(dtype=wp.float64),
):
    """q = S A c, and c . q summed into cg_sums_out[CG_CAC] of the particle's world (`cg_step_size` moves it into the
    iteration's row), one thread per particle (the CPU's form, and batched worlds'; see cloth_warp.reductions)."""
    i = wp.tid()
    w = particle_world_of(i, particle_world, worlds)
    if not world_iterates(w, worlds, loop):
        return
    cq = cg_product_row(i, effective_mass, particle_pinned, search, contact_normal, contact_crease, filtered, product_out)
    wp.atomic_add(cg_sums_out, w * CG_COLUMNS + CG_CAC, cq)


@wp.kernel(enable_backward=False)
def cg_product_blocks(
    # Model
    particle_count: int,
    effective_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    search: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_crease: wp.array(dtype=wp.vec3),
    filtered: int,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    # outputs: holds the element part (the scatter_*_product kernels) on entry, q on exit
    product_out: wp.array(dtype=wp.vec3),
    cg_sums_out: wp.array(dtype=wp.float64),
):
    """:func:`cg_product` with c . q summed per block and added once per block (the GPU's form, one world only)."""
    block, lane = wp.tid()
    i = block * wp.block_dim() + lane
    cq = wp.float64(0.0)
    if i < particle_count:
        cq = cg_product_row(i, effective_mass, particle_pinned, search, contact_normal, contact_crease, filtered, product_out)
    total = wp.tile_extract(wp.tile_sum(wp.tile(cq)), 0)
    if lane == 0:
        wp.atomic_add(cg_sums_out, CG_CAC, total)


@wp.kernel(enable_backward=False)
def cg_step_size(worlds: int, loop_out: wp.array(dtype=wp.int32), cg_sums_out: wp.array(dtype=wp.float64),
                 cg_scalars_out: wp.array2d(dtype=wp.float64), step_out: wp.array(dtype=float)):
    """One thread per world: c.Ac (summed by `cg_product` into cg_sums_out, cleared here) into row loop[LOOP_ITERATION],
    and that iteration's alpha = r.s / c.Ac (0 when c.Ac <= 0) once for `cg_update`'s threads (0 for a world that
    stopped: its dv and residual stay as they are). (Each thread dividing in float64, and the reductions indexing the
    row through the loop state per thread, cost the CPU a fifth of an iteration.)"""
    w = wp.tid()
    base = world_loop(w, worlds)
    col = w * CG_COLUMNS
    cac = cg_sums_out[col + CG_CAC]
    cg_sums_out[col + CG_CAC] = wp.float64(0.0)
    alpha = float(0.0)
    if worlds > 1 and w == 0:
        loop_out[LOOP_RUNNING] = 0  # the batch's flag: set again by `end_cg_iteration`'s worlds that go on
    if loop_out[base + LOOP_RUNNING] != 0:
        iteration = loop_out[base + LOOP_ITERATION]
        cg_scalars_out[iteration, col + CG_CAC] = cac
        if cac > wp.float64(0.0):
            alpha = float(cg_scalars_out[iteration, col + CG_RS] / cac)
    step_out[w * 2 + CG_ALPHA] = alpha


@wp.func
def cg_update_row(i: int, q: wp.vec3, alpha: float, precond: wp.array(dtype=wp.mat33), search: wp.array(dtype=wp.vec3),
                  dv_out: wp.array(dtype=wp.vec3), residual_out: wp.array(dtype=wp.vec3),
                  preconditioned_out: wp.array(dtype=wp.vec3)):
    """Row i of `cg_update` (q_i its product, read and cleared by the caller)."""
    dv_out[i] = dv_out[i] + alpha * search[i]
    r = residual_out[i] - alpha * q
    residual_out[i] = r
    preconditioned_out[i] = precond[i] * r  # (filtered on a contact: `filter_contact_preconditioner`)


@wp.kernel(enable_backward=False)
def cg_update(
    precond: wp.array(dtype=wp.mat33),
    search: wp.array(dtype=wp.vec3),
    step: wp.array(dtype=float),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    # outputs (updated in place: forward-only solve, its gradient comes from an adjoint solve)
    product_out: wp.array(dtype=wp.vec3),
    dv_out: wp.array(dtype=wp.vec3),
    residual_out: wp.array(dtype=wp.vec3),
    preconditioned_out: wp.array(dtype=wp.vec3),
):
    """dv += alpha c; r -= alpha q; s = P r with alpha = step[CG_ALPHA] (`cg_step_size`); `cg_residual_dots` then accumulates
    r.s and r.r (a kernel of its own: Warp's deterministic mode refuses an array both read and atomically updated in one
    kernel). q (`cg_product`) is read and cleared: the next iteration's scatter starts from zero."""
    i = wp.tid()
    q = product_out[i]
    product_out[i] = wp.vec3(0.0)
    w = particle_world_of(i, particle_world, worlds)
    if not world_iterates(w, worlds, loop):
        return
    cg_update_row(i, q, step[w * 2 + CG_ALPHA], precond, search, dv_out, residual_out, preconditioned_out)


@wp.kernel(enable_backward=False)
def cg_residual_dots(
    particle_count: int,
    residual: wp.array(dtype=wp.vec3),
    preconditioned: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    cg_sums_out: wp.array(dtype=wp.float64),
):
    """r.s and r.r of the updated residual summed into cg_sums_out of the particle's world (`end_cg_iteration` moves
    them into the next iteration's row), one thread per particle (the CPU's form, and batched worlds'; see
    cloth_warp.reductions)."""
    i = wp.tid()
    w = particle_world_of(i, particle_world, worlds)
    if not world_iterates(w, worlds, loop):
        return
    r = residual[i]
    col = w * CG_COLUMNS
    wp.atomic_add(cg_sums_out, col + CG_RS, wp.float64(wp.dot(r, preconditioned[i])))
    wp.atomic_add(cg_sums_out, col + CG_RR, wp.float64(wp.dot(r, r)))


@wp.kernel(enable_backward=False)
def cg_residual_dots_blocks(
    particle_count: int,
    residual: wp.array(dtype=wp.vec3),
    preconditioned: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    cg_sums_out: wp.array(dtype=wp.float64),
):
    """:func:`cg_residual_dots` summed per block and added once per block (the GPU's form, one world only)."""
    block, lane = wp.tid()
    i = block * wp.block_dim() + lane
    rs = wp.float64(0.0)
    rr = wp.float64(0.0)
    if i < particle_count:
        r = residual[i]
        rs = wp.float64(wp.dot(r, preconditioned[i]))
        rr = wp.float64(wp.dot(r, r))
    rs_total = wp.tile_extract(wp.tile_sum(wp.tile(rs)), 0)
    rr_total = wp.tile_extract(wp.tile_sum(wp.tile(rr)), 0)
    if lane == 0:
        wp.atomic_add(cg_sums_out, CG_RS, rs_total)
        wp.atomic_add(cg_sums_out, CG_RR, rr_total)


@wp.kernel(enable_backward=False)
def cg_direction(
    preconditioned: wp.array(dtype=wp.vec3),
    step: wp.array(dtype=float),
    loop: wp.array(dtype=wp.int32),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    dv: wp.array(dtype=wp.vec3),
    # outputs
    search_out: wp.array(dtype=wp.vec3),
    dv_best_out: wp.array(dtype=wp.vec3),
):
    """c = s + beta c with beta = step[CG_BETA] (`end_cg_iteration`), after the iteration it counted (none once the
    particle's world stopped); dv kept in `dv_best_out` when its residual is the smallest yet (LOOP_BEST)."""
    i = wp.tid()
    w = particle_world_of(i, particle_world, worlds)
    base = world_loop(w, worlds)
    if loop[base + LOOP_RUNNING] == 0:  # (with one world too: none after the last iteration)
        return
    cg_direction_row(i, loop[base + LOOP_BEST], step[w * 2 + CG_BETA], preconditioned, dv, search_out, dv_best_out)


@wp.func
def cg_direction_row(i: int, best: int, beta: float, preconditioned: wp.array(dtype=wp.vec3), dv: wp.array(dtype=wp.vec3),
                     search_out: wp.array(dtype=wp.vec3), dv_best_out: wp.array(dtype=wp.vec3)):
    """Row i of `cg_direction` (best: the world's LOOP_BEST)."""
    if best != 0:
        dv_best_out[i] = dv[i]
    search_out[i] = preconditioned[i] + beta * search_out[i]


# -- batched worlds on the CPU: one thread per world ---------------------------------------------------------------
# The CG's per-element and per-particle kernels launched with one thread per item run every world's items each
# iteration, the stopped worlds' too (the batch iterates until its slowest world stops): at 2-8 ns an item that is
# most of the work, and a mixed batch's worlds stop far apart. On the CPU a batch runs these forms instead: one
# thread per world walks its own items (contiguous, `ranges`), in the order the one-item kernels take them, so every
# world's products and sums are its single run's bit for bit, and a world that stopped costs one test. (A while loop:
# Warp's range loop costs a CPU about a fifth more per item.) Built with -ffp-contract=fast, the compiler fuses a
# float32 dot product's multiply-adds as the code round it lets it: r.r taken in the update's loop from the row just
# computed came out in other last bits than `cg_residual_dots`'s; taken from the stored rows in a loop of their own,
# as that kernel takes them, it is the same. tests/test_worlds.py runs both forms against single runs.

@wp.kernel(enable_backward=False)
def cg_product_worlds(
    ranges: wp.array2d(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    # the elements (as the scatter_*_product kernels take them)
    spring_ends: wp.array(dtype=wp.vec2i),
    spring_compact: wp.array(dtype=wp.vec4),
    bend_triples: wp.array(dtype=wp.vec3i),
    linear_spring_count: int,
    bend_vector: wp.array(dtype=wp.vec3),
    dt: float,
    membrane_vertices: wp.array(dtype=wp.vec3i),
    membrane_block: wp.array2d(dtype=wp.mat33),
    tri_vertices: wp.array(dtype=wp.vec3i),
    tri_corner_weights: wp.array(dtype=wp.vec3),
    drag_vector: wp.array(dtype=wp.vec3),
    plate_offsets: wp.array(dtype=wp.int32),
    plate_points: wp.array(dtype=wp.int32),
    plate_weights: wp.array(dtype=wp.vec3),
    plate_stiffness: wp.array(dtype=wp.mat33),
    plate_scale: float,
    # the rows (as `cg_product` takes them)
    effective_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    search: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_crease: wp.array(dtype=wp.vec3),
    filtered: int,
    scatter: int,
    rows: int,
    # outputs
    product_out: wp.array(dtype=wp.vec3),
    cg_sums_out: wp.array(dtype=wp.float64),
):
    """q = S A c of world w (with `scatter`, its springs', bends', membranes', triangles' and plate stencils' parts
    scattered; with `rows`, then its rows) and c . q into its cg_sums_out[CG_CAC]: the scatter kernels and `cg_product`
    of one world (launched twice, scatter then rows, where another kernel scatters between: the self-contacts)."""
    w = wp.tid()
    if not world_iterates(w, worlds, loop):
        return
    if scatter != 0:  # its elements' part, in the order the scatter kernels add it
        e = ranges[RANGE_SPRINGS, w]
        end = ranges[RANGE_SPRINGS, w + 1]
        while e < end:
            add_spring_product(e, spring_ends, spring_compact, search, product_out)
            e += 1
        e = ranges[RANGE_BENDS, w]
        end = ranges[RANGE_BENDS, w + 1]
        while e < end:
            add_bend_product(e, bend_triples, linear_spring_count, bend_vector, search, dt, product_out)
            e += 1
        e = ranges[RANGE_MEMBRANES, w]
        end = ranges[RANGE_MEMBRANES, w + 1]
        while e < end:
            add_membrane_product(e, membrane_vertices, membrane_block, search, product_out)
            e += 1
        e = ranges[RANGE_TRIANGLES, w]
        end = ranges[RANGE_TRIANGLES, w + 1]
        while e < end:
            add_drag_product(e, tri_vertices, tri_corner_weights, drag_vector, search, dt, product_out)
            e += 1
        e = ranges[RANGE_PLATES, w]
        end = ranges[RANGE_PLATES, w + 1]
        while e < end:
            add_plate_product(e, plate_offsets, plate_points, plate_weights, plate_stiffness, search, plate_scale, product_out)
            e += 1
    if rows == 0:
        return
    cac = wp.float64(0.0)
    i = ranges[RANGE_PARTICLES, w]
    end = ranges[RANGE_PARTICLES, w + 1]
    while i < end:
        cac += cg_product_row(i, effective_mass, particle_pinned, search, contact_normal, contact_crease, filtered, product_out)
        i += 1
    wp.atomic_add(cg_sums_out, w * CG_COLUMNS + CG_CAC, cac)


@wp.kernel(enable_backward=False)
def cg_update_worlds(
    ranges: wp.array2d(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    precond: wp.array(dtype=wp.mat33),
    search: wp.array(dtype=wp.vec3),
    step: wp.array(dtype=float),
    # outputs
    product_out: wp.array(dtype=wp.vec3),
    dv_out: wp.array(dtype=wp.vec3),
    residual_out: wp.array(dtype=wp.vec3),
    preconditioned_out: wp.array(dtype=wp.vec3),
    cg_sums_out: wp.array(dtype=wp.float64),
):
    """`cg_update` and `cg_residual_dots` of world w (q read and cleared, its last iteration leaving it zero)."""
    w = wp.tid()
    if not world_iterates(w, worlds, loop):
        return
    alpha = step[w * 2 + CG_ALPHA]
    i = ranges[RANGE_PARTICLES, w]
    end = ranges[RANGE_PARTICLES, w + 1]
    while i < end:
        q = product_out[i]
        product_out[i] = wp.vec3(0.0)
        cg_update_row(i, q, alpha, precond, search, dv_out, residual_out, preconditioned_out)
        i += 1
    # r.s and r.r summed as `cg_residual_dots` sums them: from the stored rows, in a loop of their own
    rs = wp.float64(0.0)
    rr = wp.float64(0.0)
    i = ranges[RANGE_PARTICLES, w]
    while i < end:
        r = residual_out[i]
        rs += wp.float64(wp.dot(r, preconditioned_out[i]))
        rr += wp.float64(wp.dot(r, r))
        i += 1
    col = w * CG_COLUMNS
    wp.atomic_add(cg_sums_out, col + CG_RS, rs)
    wp.atomic_add(cg_sums_out, col + CG_RR, rr)


@wp.kernel(enable_backward=False)
def cg_direction_worlds(
    ranges: wp.array2d(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    preconditioned: wp.array(dtype=wp.vec3),
    step: wp.array(dtype=float),
    dv: wp.array(dtype=wp.vec3),
    # outputs
    search_out: wp.array(dtype=wp.vec3),
    dv_best_out: wp.array(dtype=wp.vec3),
):
    """`cg_direction` of world w."""
    w = wp.tid()
    base = world_loop(w, worlds)
    if loop[base + LOOP_RUNNING] == 0:
        return
    best = loop[base + LOOP_BEST]
    beta = step[w * 2 + CG_BETA]
    i = ranges[RANGE_PARTICLES, w]
    end = ranges[RANGE_PARTICLES, w + 1]
    while i < end:
        cg_direction_row(i, best, beta, preconditioned, dv, search_out, dv_best_out)
        i += 1


@wp.kernel(enable_backward=False)
def restore_best_iterate(
    loop: wp.array(dtype=wp.int32),
    dv_best: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    dv_out: wp.array(dtype=wp.vec3),
):
    """After a CG solve: where the last iteration's residual is not the smallest of the solve (it stopped at the cap
    after its residual grew again), dv is the iterate that had the smallest (`cg_direction` kept it; the report's
    relative residual is that one's, `best_iterate_status`). On a cloth-on-cloth incline with both contacts and their
    friction in the solve, a float32 solve fell to 4.4e-6 of its reference by iteration 101 (the stop 1e-6) and grew
    to 6.5e-4 by the 1000-iteration cap, on a system whose preconditioned spectrum is [0.004, 2.0]."""
    i = wp.tid()
    w = particle_world_of(i, particle_world, worlds)
    if loop[world_loop(w, worlds) + LOOP_BEST] == 2:
        dv_out[i] = dv_best[i]


@wp.kernel(enable_backward=False)
def best_iterate_status(
    worlds: int,
    # outputs
    status_out: wp.array(dtype=wp.float64),
    loop_out: wp.array(dtype=wp.int32),
):
    """After a CG solve (1 thread per world): LOOP_BEST = 2 (`restore_best_iterate`) where the last iteration's
    residual is above the smallest the solve reached, and the status's relative residual that one's."""
    w = wp.tid()
    base = world_loop(w, worlds)
    st = w * STATUS_SIZE
    loop_out[base + LOOP_BEST] = 0
    best = status_out[st + STATUS_BEST]
    if best >= wp.float64(1.0e300):  # no iteration
        return
    relative = relative_residual(best, status_out[st + STATUS_REFERENCE])
    if relative < status_out[st + STATUS_RELATIVE]:
        status_out[st + STATUS_RELATIVE] = relative
        loop_out[base + LOOP_BEST] = 2


@wp.kernel(enable_backward=False)
def jacobi_iterate(
    # Model
    spring_offsets: wp.array(dtype=wp.int32),
    spring_ids: wp.array(dtype=wp.int32),
    spring_role: wp.array(dtype=wp.int32),
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_middle: wp.array(dtype=wp.int32),
    tri_offsets: wp.array(dtype=wp.int32),
    tri_ids: wp.array(dtype=wp.int32),
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_corner_weights: wp.array(dtype=wp.vec3),
    membrane_offsets: wp.array(dtype=wp.int32),
    membrane_ids: wp.array(dtype=wp.int32),
    membrane_vertices: wp.array(dtype=wp.vec3i),
    particle_pinned: wp.array(dtype=wp.int32),
    system_block: wp.array(dtype=wp.mat33),
    bend_vector: wp.array(dtype=wp.vec3),
    drag_vector: wp.array(dtype=wp.vec3),
    membrane_block: wp.array2d(dtype=wp.mat33),
    plate_product: wp.array(dtype=wp.vec3),
    plate_diagonal: wp.array(dtype=float),
    precond: wp.array(dtype=wp.mat33),
    rhs: wp.array(dtype=wp.vec3),
    dv_in: wp.array(dtype=wp.vec3),
    dt: float,
    loop: wp.array(dtype=wp.int32),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    dv_out: wp.array(dtype=wp.vec3),
):
    """Block Jacobi: dv_i <- P_i (b_i - sum_{j != i} A_ij dv_j + E_i dv_i), P_i^-1 = A_ii + E_i (E_i: the membrane
    elements' and plate stencils' extra diagonal weight); pinned rows keep z_i. Nothing once the particle's world's
    loop stopped."""
    i = wp.tid()
    if loop[world_loop(particle_world_of(i, particle_world, worlds), worlds) + LOOP_RUNNING] == 0:
        return
    if particle_pinned[i] != 0:
        dv_out[i] = dv_in[i]
        return
    acc = rhs[i]
    di = dv_in[i]
    for k in range(spring_offsets[i], spring_offsets[i + 1]):
        s = spring_ids[k]
        role = spring_role[k]
        m = spring_middle[s]
        if m < 0:
            acc += system_block[s] * dv_in[spring_indices[s, 1 - role]]
        else:
            g = bend_vector[s]
            gi = role_weight(g, role)
            acc -= dt * dt * gi * (triple_dot(g, dv_in, spring_indices[s, 0], m, spring_indices[s, 1]) - gi * di)
    for k in range(tri_offsets[i], tri_offsets[i + 1]):
        t = tri_ids[k]
        a = tri_indices[t, 0]
        b = tri_indices[t, 1]
        w = tri_corner_weights[t]
        g = drag_vector[t]
        wi = corner_weight(i, a, b, w)
        others = w[0] * dv_in[a] + w[1] * dv_in[b] + w[2] * dv_in[tri_indices[t, 2]] - wi * di
        acc -= dt * wi * wp.dot(g, others) * g
    for k in range(membrane_offsets[i], membrane_offsets[i + 1]):
        e = membrane_ids[k]
        c = membrane_vertices[e]
        y0, y1, y2 = membrane_block_product(membrane_vertices, membrane_block, e, dv_in)
        # dv + P (b - A dv) with P^-1 holding the element's diagonal block x MEMBRANE_DIAGONAL_WEIGHT:
        # subtract y_k - weight A_kk dv_i
        if i == c[0]:
            acc -= y0 - MEMBRANE_DIAGONAL_WEIGHT * (membrane_diagonal(membrane_block[e, 0], membrane_block[e, 3], membrane_block[e, 4][0, 0]) * di)
        elif i == c[1]:
            acc -= y1 - MEMBRANE_DIAGONAL_WEIGHT * (membrane_diagonal(membrane_block[e, 1], membrane_block[e, 3], membrane_block[e, 4][1, 1]) * di)
        else:
            acc -= y2 - MEMBRANE_DIAGONAL_WEIGHT * (membrane_diagonal(membrane_block[e, 2], membrane_block[e, 3], membrane_block[e, 4][2, 2]) * di)
    # plate stencils: their product scattered beforehand, their diagonal weighted as in the preconditioner
    acc -= plate_product[i] - plate_diagonal[i] * di
    dv_out[i] = precond[i] * acc


@wp.kernel(enable_backward=False)
def eval_system_residual(
    # Model
    spring_offsets: wp.array(dtype=wp.int32),
    spring_ids: wp.array(dtype=wp.int32),
    spring_role: wp.array(dtype=wp.int32),
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_middle: wp.array(dtype=wp.int32),
    tri_offsets: wp.array(dtype=wp.int32),
    tri_ids: wp.array(dtype=wp.int32),
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_corner_weights: wp.array(dtype=wp.vec3),
    membrane_offsets: wp.array(dtype=wp.int32),
    membrane_ids: wp.array(dtype=wp.int32),
    membrane_vertices: wp.array(dtype=wp.vec3i),
    particle_mass: wp.array(dtype=float),
    particle_pin_stiffness: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    system_block: wp.array(dtype=wp.mat33),
    bend_vector: wp.array(dtype=wp.vec3),
    drag_vector: wp.array(dtype=wp.vec3),
    membrane_block: wp.array2d(dtype=wp.mat33),
    plate_product: wp.array(dtype=wp.vec3),
    rhs: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    global_damping: float,
    dt: float,
    loop: wp.array(dtype=wp.int32),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    cg_scalars_out: wp.array2d(dtype=wp.float64),
):
    """|S (b - A dv)|^2 of each world into cg_scalars_out[JACOBI_CHECK_ROW, its CG_RR] when its check is due
    (its loop's LOOP_CHECK)."""
    i = wp.tid()
    w = particle_world_of(i, particle_world, worlds)
    if loop[world_loop(w, worlds) + LOOP_CHECK] == 0:
        return
    if particle_pinned[i] != 0:
        return
    m_eff = effective_mass(i, particle_mass, particle_pin_stiffness, global_damping, dt)
    r = rhs[i] - system_product(i, spring_offsets, spring_ids, spring_role, spring_indices, spring_middle, tri_offsets, tri_ids, tri_indices, tri_corner_weights, membrane_offsets, membrane_ids, membrane_vertices, system_block, bend_vector, drag_vector, membrane_block, plate_product, m_eff, dv, dt)
    wp.atomic_add(cg_scalars_out, JACOBI_CHECK_ROW, w * CG_COLUMNS + CG_RR, wp.float64(wp.dot(r, r)))


@wp.kernel
def integrate_implicit(
    particle_pinned: wp.array(dtype=wp.int32),
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    pin_target: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    """v1 = v0 + dv, x1 = x0 + h v1 (pinned particles land exactly on their targets)."""
    i = wp.tid()
    if particle_pinned[i] != 0:
        target = pin_target[i]
        x_out[i] = target
        v_out[i] = (target - x0[i]) / dt
        return
    v1 = v0[i] + dv[i]
    v_out[i] = v1
    x_out[i] = x0[i] + dt * v1


@wp.kernel(enable_backward=False)
def cg_warm_start(
    # Model
    spring_offsets: wp.array(dtype=wp.int32),
    spring_ids: wp.array(dtype=wp.int32),
    spring_role: wp.array(dtype=wp.int32),
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_middle: wp.array(dtype=wp.int32),
    tri_offsets: wp.array(dtype=wp.int32),
    tri_ids: wp.array(dtype=wp.int32),
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_corner_weights: wp.array(dtype=wp.vec3),
    membrane_offsets: wp.array(dtype=wp.int32),
    membrane_ids: wp.array(dtype=wp.int32),
    membrane_vertices: wp.array(dtype=wp.vec3i),
    particle_mass: wp.array(dtype=float),
    particle_pin_stiffness: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    system_block: wp.array(dtype=wp.mat33),
    bend_vector: wp.array(dtype=wp.vec3),
    drag_vector: wp.array(dtype=wp.vec3),
    membrane_block: wp.array2d(dtype=wp.mat33),
    plate_product: wp.array(dtype=wp.vec3),
    precond: wp.array(dtype=wp.mat33),
    rhs: wp.array(dtype=wp.vec3),
    guess: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_crease: wp.array(dtype=wp.vec3),
    friction_mass: wp.array(dtype=float),
    global_damping: float,
    dt: float,
    enabled: wp.array(dtype=wp.int32),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    dv_out: wp.array(dtype=wp.vec3),
    residual_out: wp.array(dtype=wp.vec3),
    preconditioned_out: wp.array(dtype=wp.vec3),
    search_out: wp.array(dtype=wp.vec3),
    cg_scalars_out: wp.array2d(dtype=wp.float64),
):
    """Restart CG from `guess` (last step's dv on free particles, z on pinned): r0 = S (b - A guess), r.s and r.r
    into row 0 of `cg_scalars_out` (A with a sticking contact's friction damper, `eval_contact_friction_terms`); nothing
    where enabled[world] is 0 (no previous step: the assembled cold start stays)."""
    i = wp.tid()
    w = particle_world_of(i, particle_world, worlds)
    if enabled[w] == 0:
        return
    g = guess[i]
    dv_out[i] = g
    if particle_pinned[i] != 0:
        residual_out[i] = wp.vec3(0.0)
        preconditioned_out[i] = wp.vec3(0.0)
        search_out[i] = wp.vec3(0.0)
        return
    m_eff = effective_mass(i, particle_mass, particle_pin_stiffness, global_damping, dt) + friction_mass[i]
    r = contact_filter(contact_normal[i], contact_crease[i], rhs[i] - system_product(i, spring_offsets, spring_ids, spring_role, spring_indices, spring_middle, tri_offsets, tri_ids, tri_indices, tri_corner_weights, membrane_offsets, membrane_ids, membrane_vertices, system_block, bend_vector, drag_vector, membrane_block, plate_product, m_eff, guess, dt))
    s = precond[i] * r
    residual_out[i] = r
    preconditioned_out[i] = s
    search_out[i] = s
    wp.atomic_add(cg_scalars_out, 0, w * CG_COLUMNS + CG_RS, wp.float64(wp.dot(r, s)))
    wp.atomic_add(cg_scalars_out, 0, w * CG_COLUMNS + CG_RR, wp.float64(wp.dot(r, r)))


@wp.kernel(enable_backward=False)
def compose_warm_start(
    particle_pinned: wp.array(dtype=wp.int32),
    dv_previous: wp.array(dtype=wp.vec3),
    dv_pinned: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_crease: wp.array(dtype=wp.vec3),
    contact_dv: wp.array(dtype=wp.vec3),
    use_previous: wp.array(dtype=wp.int32),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    guess_out: wp.array(dtype=wp.vec3),
):
    """guess = this step's prescribed z on pinned particles; elsewhere the previous step's dv (when use_previous[0],
    else 0) with, on a collider contact, its constrained part (the normal's, a crease's) replaced by the contact's prescribed z."""
    i = wp.tid()
    if particle_pinned[i] != 0:
        guess_out[i] = dv_pinned[i]
        return
    free = wp.vec3(0.0)
    if use_previous[particle_world_of(i, particle_world, worlds)] != 0:
        free = dv_previous[i]
    guess_out[i] = contact_filter(contact_normal[i], contact_crease[i], free) + contact_dv[i]


@wp.kernel(enable_backward=False)
def compose_restart(
    contact_released: wp.array(dtype=wp.int32),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_crease: wp.array(dtype=wp.vec3),
    contact_dv: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    release: wp.array(dtype=wp.int32),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    guess_out: wp.array(dtype=wp.vec3),
):
    """A re-solve's start: the last dv, where a contact was taken back or admitted in this step (`contact_released` < 0)
    in a world taking part in the re-solve (RELEASE_RESOLVING, `begin_contact_resolve`) with its constrained part
    replaced by its prescribed z. The filtered CG keeps a guess's constrained part: from the last dv such a contact kept
    the free solve's velocity into the collider. Elsewhere dv bit for bit: a batch's worlds that sit the re-solve out
    keep theirs, as their single runs do (every other contact's constrained part is z already)."""
    i = wp.tid()
    g = dv[i]
    rb = world_slot(particle_world_of(i, particle_world, worlds), worlds, RELEASE_SIZE)
    if contact_released[i] < 0 and release[rb + RELEASE_RESOLVING] != 0:
        g = contact_filter(contact_normal[i], contact_crease[i], g) + contact_dv[i]
    guess_out[i] = g


@wp.kernel(enable_backward=False)
def filter_contact_preconditioner(
    contact_normal: wp.array(dtype=wp.vec3),
    contact_crease: wp.array(dtype=wp.vec3),
    filtered_inverse: int,
    # outputs
    precond_out: wp.array(dtype=wp.mat33),
    precond_free_out: wp.array(dtype=wp.mat33),
):
    """On a collider contact: the preconditioner block P_i = A_ii^-1 kept (`precond_free_out`, for a release) and
    replaced by one that keeps the CG's s = P r in the filtered space (symmetric, as the CG needs): the filtered
    block's inverse (S_i A_ii S_i)^+ (`filtered_block_inverse`) with `filtered_inverse`, else S_i P_i S_i. With the
    contacts' friction in the solve a contact starts with S P S, and its damper (`eval_contact_friction_terms`) or its
    slide (`eval_contact_release`) gives it the filtered inverse: measured over 11 piles and drapes, that rested 10
    (7 with S P S throughout) in 17 % fewer iterations, while the filtered inverse here too left the 24^2 drape
    creeping at 2.7 mm/s (docs/contacts-in-the-solve.md)."""
    i = wp.tid()
    n = contact_normal[i]
    if wp.dot(n, n) == 0.0:
        return
    p = precond_out[i]
    precond_free_out[i] = p
    m = contact_crease[i]
    if filtered_inverse != 0:
        precond_out[i] = filtered_block_inverse(wp.inverse(p), n, m)
    else:
        s = contact_projector(n, m)
        precond_out[i] = s * p * s


@wp.func
def stick_damper(bound: float, speed: float, stick_speed: float):
    """A held contact's tangential damper mass d = `bound` / max(eps, |v_T|) [kg] (`bound` = mu lambda [kg m/s], `speed`
    = |v_T| its tangential speed at the step's start [m/s], eps = `stick_speed`): the collider contacts' and the
    self-contact elements' static friction in the solve."""
    return bound / wp.max(stick_speed, speed)


@wp.func
def contact_block_inverse(free_block_inverse: wp.mat33, friction_mass: float, n: wp.vec3, m: wp.vec3):
    """A collider contact's preconditioner block [1/kg]: the inverse of its free block (`free_block_inverse`, A_ii^-1)
    plus its friction damper d T (`friction_mass` d [kg], T = I - n n^T; 0 without one), filtered along its normal n
    and crease direction m (zero for most): `filtered_block_inverse`."""
    return filtered_block_inverse(wp.inverse(free_block_inverse) + friction_mass * (wp.identity(n=3, dtype=float) - wp.outer(n, n)), n, m)


@wp.func
def take_back_contact(i: int, c: int, n: wp.vec3, m: wp.vec3, z: wp.vec3, free_block_inverse: wp.mat33, rb: int,
                      contact_collider_out: wp.array(dtype=wp.int32), contact_normal_out: wp.array(dtype=wp.vec3),
                      contact_crease_out: wp.array(dtype=wp.vec3), contact_dv_out: wp.array(dtype=wp.vec3),
                      precond_out: wp.array(dtype=wp.mat33), released_out: wp.array(dtype=wp.int32),
                      release_out: wp.array(dtype=wp.int32)):
    """A contact released in the step made a contact of collider c again (normal n, crease direction m, prescribed
    change z; frictionless in the solve), not to be released again in the step (`released_out` -1), and the step flagged
    to be solved again (world slot `rb`): `eval_contact_release`, kernels/contact.py `admit_collider_contacts`."""
    contact_collider_out[i] = c
    contact_normal_out[i] = n
    contact_crease_out[i] = m
    contact_dv_out[i] = z
    precond_out[i] = filtered_block_inverse(wp.inverse(free_block_inverse), n, m)
    released_out[i] = -1
    release_out[rb + RELEASE_FLAG] = 1
    release_out[RELEASE_FLAG] = 1


@wp.func
def hold_contact(i: int, n: wp.vec3, m: wp.vec3, tangential: wp.vec3, bound: float, stick_speed: float,
                 precond_free: wp.array(dtype=wp.mat33), rhs_out: wp.array(dtype=wp.vec3), effective_mass_out: wp.array(dtype=float),
                 friction_mass_out: wp.array(dtype=float), friction_impulse_out: wp.array(dtype=wp.vec3),
                 precond_out: wp.array(dtype=wp.mat33)):
    """Contact i held by a tangential damper of mass d = `bound` / max(eps, |v_T|) [kg] (`bound` = mu_s lambda [kg m/s],
    v_T = `tangential` its tangential velocity relative to the surface at the step's start, eps = `stick_speed`): A += d T,
    b -= d v_T, its preconditioner block the filtered damped block's inverse (`eval_contact_friction_terms`; filtered
    along its crease direction m too, zero for most); nothing added when d is 0."""
    d = stick_damper(bound, wp.length(tangential), stick_speed)
    if d <= 0.0:
        return
    stick = -d * tangential
    friction_mass_out[i] = d
    friction_impulse_out[i] = stick
    rhs_out[i] = rhs_out[i] + stick
    effective_mass_out[i] = effective_mass_out[i] + d
    precond_out[i] = contact_block_inverse(precond_free[i], d, n, m)


@wp.kernel(enable_backward=False)
def eval_contact_release(
    # Model
    spring_offsets: wp.array(dtype=wp.int32),
    spring_ids: wp.array(dtype=wp.int32),
    spring_role: wp.array(dtype=wp.int32),
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_middle: wp.array(dtype=wp.int32),
    tri_offsets: wp.array(dtype=wp.int32),
    tri_ids: wp.array(dtype=wp.int32),
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_corner_weights: wp.array(dtype=wp.vec3),
    membrane_offsets: wp.array(dtype=wp.int32),
    membrane_ids: wp.array(dtype=wp.int32),
    membrane_vertices: wp.array(dtype=wp.vec3i),
    particle_mass: wp.array(dtype=float),
    particle_pin_stiffness: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    system_block: wp.array(dtype=wp.mat33),
    bend_vector: wp.array(dtype=wp.vec3),
    drag_vector: wp.array(dtype=wp.vec3),
    membrane_block: wp.array2d(dtype=wp.mat33),
    plate_product: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    precond_free: wp.array(dtype=wp.mat33),
    global_damping: float,
    dt: float,
    release_impulse: float,
    max_rounds: int,
    v0: wp.array(dtype=wp.vec3),
    contact_velocity: wp.array(dtype=wp.vec3),
    contact_height: wp.array(dtype=float),
    collider_thickness: wp.array(dtype=float),
    collider_static_friction: wp.array(dtype=float),
    collider_kinetic_friction: wp.array(dtype=float),
    stick_speed: float,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    rhs_out: wp.array(dtype=wp.vec3),
    effective_mass_out: wp.array(dtype=float),
    friction_mass_out: wp.array(dtype=float),
    friction_impulse_out: wp.array(dtype=wp.vec3),
    precond_out: wp.array(dtype=wp.mat33),
    contact_collider_out: wp.array(dtype=wp.int32),
    contact_normal_out: wp.array(dtype=wp.vec3),
    contact_crease_out: wp.array(dtype=wp.vec3),
    contact_dv_out: wp.array(dtype=wp.vec3),
    contact_impulse_out: wp.array(dtype=float),
    release_out: wp.array(dtype=wp.int32),
    released_out: wp.array(dtype=wp.int32),
    released_normal_out: wp.array(dtype=wp.vec3),
    released_dv_out: wp.array(dtype=wp.vec3),
    pulled_out: wp.array(dtype=wp.int32),
    pulled_friction: int,
):
    """The impulse [kg m/s] each collider contact exerts along its normal in the solved step, lambda = n . (A dv - b)_i
    (the part of the momentum balance the filter took out); a contact that pulls (lambda < -release_impulse m_i
    [m/s x kg]: the cloth wants to leave the surface faster than prescribed; the threshold keeps the solve's
    round-off in lambda from releasing a contact that barely bears any load) is released (collider -1, n = 0, z = 0,
    its unfiltered preconditioner block back, its friction terms (`eval_contact_friction_terms`) out of the system) and
    release_out[RELEASE_FLAG] set, while fewer than `max_rounds` re-solves were run this step. A contact held by a
    friction damper is first let slide instead (the kinetic impulse -mu_k lambda+ s / |s| along its solved slip s
    relative to the surface, `v0` + dv - `contact_velocity`, in place of the damper; the flag set) where static friction
    cannot hold it: lambda pulls, or the damper's impulse d |s| passed the bound mu_s lambda with |s| above the stick
    speed [m/s]. A damper held past the bound made the stuck cloth pull off the surface where it would fall back
    sliding, and the contact chattered between the two. A sliding contact whose kinetic impulse reversed its solved
    slip (friction stronger than what moves it: the normal impulse it was taken from fell in the re-solve) sticks again,
    with a damper from this solve's lambda, and the step is solved again: left sliding, the cloth round it took the
    kinetic impulse the contact did not need (`apply_contact_friction` then stops the contact alone), and the contact
    went from stick to slide and back every step, its neighbours thrown back and forth (a dress held still: 60
    particles at 5-7 mm/s in a period-two cycle that did not move them). This check has one round more than the
    others (`max_rounds` + 1, when `max_rounds` > 0): the re-solve after the last round that let a contact slide is
    checked for it too, so that no step ends with a slide its kinetic impulse reversed (the T-shirt held still at 3.4 cm
    edges: a shoulder contact let slide in the last round every other step, stopped after the solve, its neighbours
    at +-1.7 mm/s in a period-two cycle; 0.3-0.5 mm/s with the round). A damped contact let slide because it pulled
    (no kinetic impulse: `pulled_out` 1) that presses in the check of that extra round sticks again the same way, with
    `pulled_friction` (SolverImplicitEuler's option; in every round, the rest set's piles went on folding: 38 of 60 at
    rest against 54; in that round only, 52, the shipped drape at rest at 5.4 s instead of 5 s): left without
    friction in the solve, friction after it stopped it alone (the T-shirt held still at 2.6 cm edges: a shoulder
    contact bearing 0.1 N, its neighbours at 7 mm/s in a period-two cycle). A pinched contact (its `contact_height` below
    the collider's thickness, `kernels/contact.py` eval_collider_contacts) is two-sided: its impulse either way presses
    one of its surfaces, so it is never released; and frictionless, its impulse 0 (what holds it between two surfaces
    is no squeeze on one: with friction from |lambda| the shipped T-shirt's settling held an armpit seam 7 mm open, which
    closed without). In a crease (`contact_crease_out` m: the facing side's normal, orthogonal to n) it is held along m
    too, one-sided: where that part of its impulse pulls it towards the facing side (the cloth draws it out of the
    crease, along its own side), m is let go and the step solved again; it is still held along n. A released contact
    is kept (`released_out`: collider + 1, its normal and prescribed change): where a later check finds that the
    re-solve ends it below the collider's thickness, the contact is taken back (`released_out` -1: not released again
    in the step) and the step solved again, from its prescribed z (`SolverImplicitEuler._restart`; the filtered CG
    keeps a guess's normal part): from the last dv it held the free solve's normal velocity into the collider, which
    the colliders pass put out after the step, and the shipped T-shirt held still went through a neck contact's
    take-back every other step at 6.5 mm/s (0.46 from z). A contact found pulling in a check that also let many dampers around it
    slide was released, and the cloth round it, sliding, carried it into the surface; the colliders pass pushed it out
    after the step and it was a contact again in the next, which pulled again: a dress held still (4 cm edges) went
    back and forth at 12 mm/s (0.8 with this). (Batched worlds: the flag and the rounds are the particle's world's, and
    the batch's flag is set with a world's.)"""
    i = wp.tid()
    rb = world_slot(particle_world_of(i, particle_world, worlds), worlds, RELEASE_SIZE)
    n = contact_normal_out[i]
    if particle_pinned[i] != 0 or wp.dot(n, n) == 0.0:
        contact_impulse_out[i] = 0.0
        r = released_out[i]
        if r > 0 and release_out[rb + RELEASE_ROUNDS] < max_rounds:
            c = r - 1
            nr = released_normal_out[i]
            z = released_dv_out[i]
            # released, the free solve ends it below the thickness (the height its contact ended it at, less what the
            # solve moved it beyond that): it presses after all (the cloth around it changed in the same check), so its
            # contact is back (frictionless in the solve: friction after it, from the measured impulse), solved again
            end_height = contact_height[i] - dt * wp.dot(z - dv[i], nr)
            if end_height < collider_thickness[c]:
                take_back_contact(i, c, nr, wp.vec3(0.0), z, precond_free[i], rb, contact_collider_out, contact_normal_out,
                                  contact_crease_out, contact_dv_out, precond_out, released_out, release_out)
        return
    m_eff = effective_mass(i, particle_mass, particle_pin_stiffness, global_damping, dt)
    a_dv = system_product(i, spring_offsets, spring_ids, spring_role, spring_indices, spring_middle, tri_offsets, tri_ids, tri_indices,
                          tri_corner_weights, membrane_offsets, membrane_ids, membrane_vertices, system_block, bend_vector, drag_vector,
                          membrane_block, plate_product, m_eff, dv, dt)
    impulse = wp.dot(n, a_dv - rhs_out[i])  # (the friction terms are tangential: no part of it)
    pinched = is_pinched(contact_height[i], collider_thickness[contact_collider_out[i]])
    contact_impulse_out[i] = impulse
    if pinched:
        contact_impulse_out[i] = 0.0  # pinched: held, frictionless
    m = contact_crease_out[i]
    if (wp.dot(m, a_dv - rhs_out[i]) < -release_impulse * particle_mass[i] and wp.dot(m, m) > 0.0
            and release_out[rb + RELEASE_ROUNDS] < max_rounds):
        # in a crease (pinched, or held on one face and found inside the collider by another: admit_collider_contacts),
        # held off the facing side by pulling towards it: the cloth leaves the crease (along m, away from that side),
        # so the crease direction is let go and the step solved again
        contact_dv_out[i] = contact_dv_out[i] - wp.dot(contact_dv_out[i], m) * m
        contact_crease_out[i] = wp.vec3(0.0)
        precond_out[i] = contact_block_inverse(precond_free[i], friction_mass_out[i], n, wp.vec3(0.0))
        release_out[rb + RELEASE_FLAG] = 1
        release_out[RELEASE_FLAG] = 1
        return
    if pinched:
        return
    d = friction_mass_out[i]
    if d > 0.0 and release_out[rb + RELEASE_ROUNDS] < max_rounds:
        # a sticking contact that static friction cannot hold (its damper past the bound, or no push left to hold
        # it): it slides in this step, solved again (its release, if it still pulls, is the next round's)
        c = contact_collider_out[i]
        slip = tangential_part(n, v0[i] + dv[i] - contact_velocity[i])
        speed = wp.length(slip)
        push = wp.max(impulse, 0.0)
        if (impulse < -release_impulse * particle_mass[i]
                or (speed > SLIP_ALLOWANCE * stick_speed and d * speed > SLIP_ALLOWANCE * collider_static_friction[c] * push)):
            slide = wp.vec3(0.0)
            if speed > 0.0:
                slide = (-collider_kinetic_friction[c] * push / speed) * slip
            if push == 0.0:
                pulled_out[i] = 1  # (no kinetic impulse: its friction back if it presses again, below)
            rhs_out[i] = rhs_out[i] - friction_impulse_out[i] + slide
            effective_mass_out[i] = effective_mass_out[i] - d
            friction_mass_out[i] = 0.0
            friction_impulse_out[i] = slide
            precond_out[i] = filtered_block_inverse(wp.inverse(precond_free[i]), n, contact_crease_out[i])
            release_out[rb + RELEASE_FLAG] = 1
            release_out[RELEASE_FLAG] = 1
        return
    fi = friction_impulse_out[i]
    # (one round more than the other changes: a contact the last round let slide is checked for it too)
    reversal_rounds = max_rounds + wp.min(max_rounds, 1)
    rounds = release_out[rb + RELEASE_ROUNDS]
    regain = pulled_friction != 0 and pulled_out[i] != 0 and rounds >= max_rounds  # (the extra round only)
    if d == 0.0 and impulse > 0.0 and rounds < reversal_rounds and (wp.dot(fi, fi) > 0.0 or regain):
        c = contact_collider_out[i]
        rel = v0[i] - contact_velocity[i]
        slip = tangential_part(n, rel + dv[i])
        if wp.dot(slip, fi) > 0.0 or regain:
            # the kinetic impulse reversed the contact's slip (or the contact's friction left as it pulled, and it
            # presses again): friction held it, so it sticks (a damper from this solve's normal impulse, as
            # eval_contact_friction_terms makes one), solved again (a kinetic impulse means mu_s >= mu_k > 0 and
            # lambda > 0, as does a damper it had: the damper's mass is positive)
            rhs_out[i] = rhs_out[i] - fi
            hold_contact(i, n, contact_crease_out[i], tangential_part(n, rel), collider_static_friction[c] * impulse, stick_speed, precond_free, rhs_out,
                         effective_mass_out, friction_mass_out, friction_impulse_out, precond_out)
            pulled_out[i] = 0
            release_out[rb + RELEASE_FLAG] = 1
            release_out[RELEASE_FLAG] = 1
            return
    if (impulse < -release_impulse * particle_mass[i] and release_out[rb + RELEASE_ROUNDS] < max_rounds
            and (released_out[i] == 0 or released_out[i] == ADMITTED)):
        released_out[i] = contact_collider_out[i] + 1
        released_normal_out[i] = n
        released_dv_out[i] = contact_dv_out[i]
        rhs_out[i] = rhs_out[i] - friction_impulse_out[i]
        effective_mass_out[i] = effective_mass_out[i] - friction_mass_out[i]
        friction_impulse_out[i] = wp.vec3(0.0)
        friction_mass_out[i] = 0.0
        contact_collider_out[i] = -1
        contact_normal_out[i] = wp.vec3(0.0)
        contact_crease_out[i] = wp.vec3(0.0)
        contact_dv_out[i] = wp.vec3(0.0)
        contact_impulse_out[i] = 0.0
        precond_out[i] = precond_free[i]
        release_out[rb + RELEASE_FLAG] = 1
        release_out[RELEASE_FLAG] = 1


@wp.kernel(enable_backward=False)
def begin_contact_resolve(
    worlds: int,
    polish: int,
    motion: wp.array(dtype=wp.float64),
    tolerance: wp.float64,
    velocity_tolerance: wp.float64,
    # outputs
    release_out: wp.array(dtype=wp.int32),
    loop_out: wp.array(dtype=wp.int32),
):
    """A re-solve starts (1 thread per world): a world with a contact released takes part (RELEASE_RESOLVING): one
    more round, its flag cleared, its last solve's iterations carried; batched, a world without sits it out, its
    solve as it was (and the batch's flag is cleared). With `polish` (the step's last solve, after the contacts settled
    on solves short of the tolerance: to it) every world takes part, without spending a round; with `polish` 2 (short
    of the velocity tolerance only: begin_linear_solve), the worlds near rest (`near_rest`) only."""
    w = wp.tid()
    rb = world_slot(w, worlds, RELEASE_SIZE)
    base = world_loop(w, worlds)
    if worlds > 1 and w == 0:
        release_out[RELEASE_FLAG] = 0
    release_out[rb + RELEASE_RESOLVING] = 0
    if release_out[rb + RELEASE_FLAG] == 0 and polish == 0:
        return
    if polish == 2 and not near_rest(motion, w, tolerance, velocity_tolerance):
        return
    release_out[rb + RELEASE_RESOLVING] = 1
    release_out[rb + RELEASE_FLAG] = 0
    if polish == 0:
        release_out[rb + RELEASE_ROUNDS] = release_out[rb + RELEASE_ROUNDS] + 1
    loop_out[base + LOOP_CARRIED] = loop_out[base + LOOP_CARRIED] + loop_out[base + LOOP_ITERATION]


@wp.kernel(enable_backward=False)
def eval_contact_friction_terms(
    particle_mass: wp.array(dtype=float),
    particle_seam_root: wp.array(dtype=wp.int32),
    contact_collider: wp.array(dtype=wp.int32),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_velocity: wp.array(dtype=wp.vec3),
    previous_impulse: wp.array(dtype=float),
    collider_static_friction: wp.array(dtype=float),
    collider_kinetic_friction: wp.array(dtype=float),
    v0: wp.array(dtype=wp.vec3),
    precond_free: wp.array(dtype=wp.mat33),
    stick_speed: float,
    contact_height: wp.array(dtype=float),
    collider_thickness: wp.array(dtype=float),
    # outputs
    rhs_out: wp.array(dtype=wp.vec3),
    effective_mass_out: wp.array(dtype=float),
    precond_out: wp.array(dtype=wp.mat33),
    friction_mass_out: wp.array(dtype=float),
    friction_impulse_out: wp.array(dtype=wp.vec3),
):
    """Coulomb friction of a collider contact as terms of the step's system (forward steps), from the normal impulse
    lambda [kg m/s] of the contact's last step (lagged, as in IPC's friction) and its tangential velocity relative to
    the surface at the step's start, v_T. A contact faster than static friction could stop in a step
    (m |v_T| > mu_s lambda) slides: the kinetic impulse -mu_k lambda v_T / |v_T| in b (`apply_contact_friction` stops
    it where the solve reverses it). Any other gets a tangential damper of mass d = mu_s lambda / max(eps, |v_T|) [kg]
    (eps = `stick_speed` [m/s]; A += d T, b -= d T (v0 - u), T = I - n n^T): at rest its impulse reaches the static
    bound where the solved slip reaches eps, so the solve holds the contact instead of moving the cloth around a
    slide that friction undoes after it; creeping at |v_T| it is Coulomb's force linearised there (its impulse is
    mu_s lambda at the same speed), which takes a contact from stick to slide and back without the switch kicking
    the cloth around it. `eval_contact_release` switches a damper the solve pushed past the bound to the kinetic
    impulse and solves again. Neither without a last impulse (a new contact) or on a sewn point that takes friction
    as one point (`particle_seam_root` >= 0: its seam still open): `apply_contact_friction` after the solve. Nor on a
    pinched contact (`contact_height` below the collider's thickness [m]): frictionless (`eval_contact_release`) from
    the step it is pinched in, after pressing one side. A damped contact's preconditioner block becomes the filtered
    block's inverse (S (P_free^-1 + d T) S)^+ (`filtered_block_inverse`; S (P_free^-1 + d T)^-1 S took 2.3x the
    iterations on the layered outfit held still); the CG's product takes d on the effective mass (S d c = S d T c)."""
    i = wp.tid()
    friction_mass_out[i] = 0.0
    friction_impulse_out[i] = wp.vec3(0.0)
    c = contact_collider[i]
    impulse = previous_impulse[i]
    if c < 0 or particle_seam_root[i] >= 0 or impulse <= 0.0 or is_pinched(contact_height[i], collider_thickness[c]):
        return
    n = contact_normal[i]
    rel = v0[i] - contact_velocity[i]
    tangential = tangential_part(n, rel)
    speed = wp.length(tangential)
    if particle_mass[i] * speed > collider_static_friction[c] * impulse:
        slide = (-collider_kinetic_friction[c] * impulse / speed) * tangential
        friction_impulse_out[i] = slide
        rhs_out[i] = rhs_out[i] + slide
        return
    hold_contact(i, n, wp.vec3(0.0), tangential, collider_static_friction[c] * impulse, stick_speed, precond_free, rhs_out, effective_mass_out,
                 friction_mass_out, friction_impulse_out, precond_out)


@wp.func
def coulomb_friction(dv: wp.vec3, v0: wp.vec3, surface_velocity: wp.vec3, n: wp.vec3, impulse: float, mass: float,
                     static_friction: float, kinetic_friction: float):
    """A contact's velocity change after Coulomb friction from its normal impulse lambda [kg m/s] (velocity level,
    Bridson et al. 2002): with dv_N = lambda / m, the end velocity's tangential part relative to the surface, v_T, is
    stopped when |v_T| <= mu_s dv_N, else shortened by mu_k dv_N. No friction without a pushing impulse."""
    if impulse <= 0.0 or mass <= 0.0:
        return dv
    normal_change = impulse / mass
    rel = v0 + dv - surface_velocity
    tangential = tangential_part(n, rel)
    speed = wp.length(tangential)
    if speed <= static_friction * normal_change:
        return dv - tangential
    return dv - (kinetic_friction * normal_change / speed) * tangential


@wp.kernel(enable_backward=False)
def gather_seam_friction(
    particle_mass: wp.array(dtype=float),
    particle_seam_root: wp.array(dtype=wp.int32),
    contact_collider: wp.array(dtype=wp.int32),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_velocity: wp.array(dtype=wp.vec3),
    contact_impulse: wp.array(dtype=float),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    # outputs: sums, zeroed before the launch
    group_momentum_out: wp.array(dtype=wp.vec3),
    group_mass_out: wp.array(dtype=float),
    group_impulse_out: wp.array(dtype=float),
):
    """Per sewn point (the particles a seam joins, `particle_seam_root` >= 0), the sums over its pushing contacts of
    tangential momentum relative to the surface m v_T [kg m/s], mass [kg] and normal impulse [kg m/s]."""
    i = wp.tid()
    r = particle_seam_root[i]
    if r < 0 or contact_collider[i] < 0 or contact_impulse[i] <= 0.0:
        return
    n = contact_normal[i]
    rel = v0[i] + dv[i] - contact_velocity[i]
    m = particle_mass[i]
    wp.atomic_add(group_momentum_out, r, m * (rel - wp.dot(rel, n) * n))
    wp.atomic_add(group_mass_out, r, m)
    wp.atomic_add(group_impulse_out, r, contact_impulse[i])


@wp.kernel(enable_backward=False)
def apply_contact_friction(
    particle_mass: wp.array(dtype=float),
    contact_collider: wp.array(dtype=wp.int32),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_velocity: wp.array(dtype=wp.vec3),
    contact_impulse: wp.array(dtype=float),
    collider_static_friction: wp.array(dtype=float),
    collider_kinetic_friction: wp.array(dtype=float),
    v0: wp.array(dtype=wp.vec3),
    particle_seam_root: wp.array(dtype=wp.int32),
    group_momentum: wp.array(dtype=wp.vec3),
    group_mass: wp.array(dtype=float),
    group_impulse: wp.array(dtype=float),
    friction_mass: wp.array(dtype=float),
    friction_impulse: wp.array(dtype=wp.vec3),
    stick_speed: float,
    # outputs
    dv_out: wp.array(dtype=wp.vec3),
    slipping_out: wp.array(dtype=wp.int32),
):
    """Friction on each contact's solved dv. A contact whose friction was in the solve (`eval_contact_friction_terms`):
    one its damper held within the stick speed (`stick_speed` [m/s]) has that slip taken out, so that cloth held by
    static friction does not creep; one that slid is stopped where the kinetic impulse reversed its tangential
    velocity. Any other: Coulomb friction (`coulomb_friction`) from the impulse the release check measured.
    `slipping_out` marks the contacts left sliding (a diagnostic: the next step's friction starts from their velocity).
    A sewn point's particles (`gather_seam_friction`) take it as one point: the law on their mass-weighted tangential
    velocity and summed impulse, the same change for each (in its own tangent plane), so friction never holds a seam's
    two sides apart (each side stuck where it landed) while the seam spring pulls them together."""
    i = wp.tid()
    slipping_out[i] = 0
    c = contact_collider[i]
    if c < 0:
        return
    d = friction_mass[i]
    if d > 0.0:  # damped: held exactly within the stick speed, past it (creeping): as solved
        n = contact_normal[i]
        rel = v0[i] + dv_out[i] - contact_velocity[i]
        slip = tangential_part(n, rel)
        if wp.length(slip) <= SLIP_ALLOWANCE * stick_speed:
            dv_out[i] = dv_out[i] - slip
        else:
            slipping_out[i] = 1
        return
    slide = friction_impulse[i]
    if wp.dot(slide, slide) > 0.0:
        n_slide = contact_normal[i]
        rel = v0[i] + dv_out[i] - contact_velocity[i]
        tangential = tangential_part(n_slide, rel)
        if wp.dot(tangential, slide) > 0.0:
            dv_out[i] = dv_out[i] - tangential
        else:
            slipping_out[i] = 1  # still sliding
        return
    r = particle_seam_root[i]
    if r >= 0 and contact_impulse[i] > 0.0:
        mass = group_mass[r]
        if mass > 0.0:
            tangential = group_momentum[r] / mass
            normal_change = group_impulse[r] / mass
            speed = wp.length(tangential)
            change = tangential
            if speed > collider_static_friction[c] * normal_change:
                change = (collider_kinetic_friction[c] * normal_change / speed) * tangential
            n = contact_normal[i]
            dv_out[i] = dv_out[i] - (change - wp.dot(change, n) * n)
            return
    dv = coulomb_friction(dv_out[i], v0[i], contact_velocity[i], contact_normal[i], contact_impulse[i], particle_mass[i],
                          collider_static_friction[c], collider_kinetic_friction[c])
    dv_out[i] = dv
    n_new = contact_normal[i]
    rel = v0[i] + dv - contact_velocity[i]
    if contact_impulse[i] > 0.0 and wp.length(tangential_part(n_new, rel)) > 0.0:
        slipping_out[i] = 1  # it slid


@wp.kernel
def eval_contact_friction(
    particle_mass: wp.array(dtype=float),
    contact_collider: wp.array(dtype=wp.int32),
    contact_height: wp.array(dtype=float),
    collider_thickness: wp.array(dtype=float),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_velocity: wp.array(dtype=wp.vec3),
    collider_static_friction: wp.array(dtype=float),
    collider_kinetic_friction: wp.array(dtype=float),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    unfiltered_residual: wp.array(dtype=wp.vec3),
    # outputs
    dv_out: wp.array(dtype=wp.vec3),
):
    """A taped step's friction: `coulomb_friction` with lambda = -n . (b - A dv)_i from the unfiltered residual, into a
    fresh array (differentiable; whether a contact sticks or slides is held fixed, as the contact set is; a pinched
    contact, `contact_height` below the thickness, is frictionless, as `eval_contact_release` takes it)."""
    i = wp.tid()
    c = contact_collider[i]
    if c < 0:
        dv_out[i] = dv[i]
        return
    n = contact_normal[i]
    impulse = -wp.dot(n, unfiltered_residual[i])
    if is_pinched(contact_height[i], collider_thickness[c]):
        impulse = 0.0
    dv_out[i] = coulomb_friction(dv[i], v0[i], contact_velocity[i], n, impulse, particle_mass[i],
                                 collider_static_friction[c], collider_kinetic_friction[c])


@wp.kernel
def constrain_contact_velocity_change(
    contact_normal: wp.array(dtype=wp.vec3),
    contact_crease: wp.array(dtype=wp.vec3),
    contact_dv: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    # outputs
    dv_out: wp.array(dtype=wp.vec3),
):
    """A taped step's dv with its contacts' constrained part prescribed: S_i dv + z_i (z_i a function of x0, v0 and the
    collider, `kernels/contact.py` eval_contact_constraints), as pins are in `compose_velocity_change`."""
    i = wp.tid()
    dv_out[i] = contact_filter(contact_normal[i], contact_crease[i], dv[i]) + contact_dv[i]


@wp.kernel
def filter_contact_residual(
    contact_normal: wp.array(dtype=wp.vec3),
    contact_crease: wp.array(dtype=wp.vec3),
    residual: wp.array(dtype=wp.vec3),
    # outputs
    residual_out: wp.array(dtype=wp.vec3),
):
    """S r: the residual of a step whose contacts are constrained (differentiable, the normal included)."""
    i = wp.tid()
    residual_out[i] = contact_filter(contact_normal[i], contact_crease[i], residual[i])


# -- the solve's loop on the device ---------------------------------------------------------------
# A solve is a wp.capture_while loop over one iteration: the kernels read the iteration from `loop` and a 1-thread
# kernel counts it and tests convergence, so eager, graph-captured and taped (forward) solves run the same
# iterations without a host read.


@wp.func
def relative_residual(rr: wp.float64, reference: wp.float64) -> wp.float64:
    """sqrt(|r|^2 / |r_0|^2), NaN when either is not finite, 0 without a reference."""
    if not (wp.isfinite(rr) and wp.isfinite(reference)):
        return wp.float64(wp.nan)
    if reference > wp.float64(1.0e-300):
        return wp.sqrt(wp.max(rr, wp.float64(0.0)) / reference)
    return wp.float64(0.0)


@wp.func
def stops(relative: wp.float64, stop: wp.float64) -> bool:
    """The solve stops at or below its stop residual, and on a non-finite one."""
    return relative <= stop or not wp.isfinite(relative)


@wp.func
def cg_stops(relative: wp.float64, stop: wp.float64, rs: wp.float64, error_target: wp.float64) -> bool:
    """A CG solve stops at or below its stop residual once its velocity error is within its target too (r.s, the
    preconditioned residual's energy, at or below `error_target`; or the residual at SOLVE_FLOOR), and on a non-finite
    residual."""
    if not wp.isfinite(relative):
        return True
    return relative <= stop and (rs <= error_target or relative <= wp.float64(SOLVE_FLOOR))


@wp.func
def near_rest(motion: wp.array(dtype=wp.float64), w: int, tolerance: wp.float64, velocity_tolerance: wp.float64) -> bool:
    """Whether world w is near rest for a solve to `tolerance`: a velocity tolerance v_tol > 0 [m/s] at least tolerance
    x its RMS speed at the step's start (`sum_motion`)."""
    mass = motion[2 * w + 1]
    if velocity_tolerance <= wp.float64(0.0) or mass <= wp.float64(0.0):
        return False
    return tolerance * wp.sqrt(motion[2 * w] / mass) <= velocity_tolerance


@wp.kernel(enable_backward=False)
def sum_motion(
    particle_mass: wp.array(dtype=float),
    v0: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs (accumulated; zeroed by the caller)
    motion_out: wp.array(dtype=wp.float64),
):
    """Each world's sum m |v0|^2 [kg m^2/s^2] and mass [kg] at the step's start (begin_linear_solve's speed scale)."""
    i = wp.tid()
    w = particle_world_of(i, particle_world, worlds)
    m = wp.float64(particle_mass[i])
    wp.atomic_add(motion_out, 2 * w, m * wp.float64(wp.dot(v0[i], v0[i])))
    wp.atomic_add(motion_out, 2 * w + 1, m)


@wp.kernel(enable_backward=False)
def begin_linear_solve(
    warm_scalars: wp.array2d(dtype=wp.float64),
    warm: wp.array(dtype=wp.int32),
    use_warm: int,
    restarted: int,
    resolve: int,
    tolerance: wp.float64,
    warm_reduction: wp.float64,
    warm_floor: wp.float64,
    max_iterations: int,
    worlds: int,
    release: wp.array(dtype=wp.int32),
    motion: wp.array(dtype=wp.float64),
    velocity_tolerance: wp.float64,
    # outputs
    cg_scalars_out: wp.array2d(dtype=wp.float64),
    status_out: wp.array(dtype=wp.float64),
    loop_out: wp.array(dtype=wp.int32),
):
    """Start a solve (1 thread per world): the reference |r_0|^2 is row 0 of `cg_scalars_out` (the zero guess's residual,
    as assembled); a warm start (use_warm and warm[world]) replaces row 0 by its guess's (`warm_scalars`) and may stop
    at warm_reduction times its starting residual (not below warm_floor); a restart from a composed guess
    (`restarted`: collider contacts in the solve) replaces row 0 too; a re-solve of the step (`resolve`, rows
    zeroed by the caller) keeps the step's reference and the iterations carried from its earlier solves. Iterates when the reference is
    positive and the starting residual above the stop. With batched worlds the batch's loop state (cleared by the
    caller) runs while any world does; in a re-solve, only the worlds taking part (`release`, begin_contact_resolve) start
    again, the others keep their solve as it was.

    With `velocity_tolerance` v_tol > 0 [m/s] (the forward step's last solve with contacts in the solve), in a world
    near rest (tolerance x v_rms <= v_tol, v_rms its RMS speed at the step's start: `motion`, `sum_motion`) a CG solve
    also goes on until its RMS velocity error is within v_tol: r.s <= M v_tol^2 (`cg_stops`; r.s ~ sum m |e|^2 for the
    velocity error e, the block-diagonal preconditioner being ~ the inverse mass), or until the residual reaches
    SOLVE_FLOOR. Relative to the zero guess's residual alone, whose scale is the step's weight h M g, cloth at rest was
    solved to ~5 um/s RMS (0.1 mm/s at a particle), as large as what moved it: a drape's free edge over the ball kept
    waving at 16 mm/s, a limit cycle fed by each step's error (docs/contacts-in-the-solve.md)."""
    w = wp.tid()
    base = world_loop(w, worlds)
    col = w * CG_COLUMNS
    st = w * STATUS_SIZE
    if resolve != 0 and release[world_slot(w, worlds, RELEASE_SIZE) + RELEASE_RESOLVING] == 0:
        return
    error_target = wp.float64(1.0e300)
    if near_rest(motion, w, tolerance, velocity_tolerance):
        error_target = motion[2 * w + 1] * velocity_tolerance * velocity_tolerance
    status_out[st + STATUS_ERROR_TARGET] = error_target
    reference = cg_scalars_out[0, col + CG_RR]
    if resolve != 0:
        reference = status_out[st + STATUS_REFERENCE]  # the step's, measured by its first solve
    is_warm = use_warm != 0 and warm[w] != 0
    if is_warm or restarted != 0:
        cg_scalars_out[0, col + CG_RS] = warm_scalars[0, col + CG_RS]
        cg_scalars_out[0, col + CG_RR] = warm_scalars[0, col + CG_RR]
    relative = relative_residual(cg_scalars_out[0, col + CG_RR], reference)
    stop = tolerance
    if is_warm:
        stop = wp.min(tolerance, wp.max(warm_reduction * relative, warm_floor))
    status_out[st + STATUS_REFERENCE] = reference
    status_out[st + STATUS_STOP] = stop
    status_out[st + STATUS_RELATIVE] = relative
    status_out[st + STATUS_BEST] = wp.float64(1.0e300)  # (the first iteration's residual replaces it)
    loop_out[base + LOOP_ITERATION] = 0
    loop_out[base + LOOP_CHECK] = 0
    if resolve == 0:
        loop_out[base + LOOP_CARRIED] = 0
    loop_out[base + LOOP_RUNNING] = 0
    if reference > wp.float64(1.0e-300) and not cg_stops(relative, stop, cg_scalars_out[0, col + CG_RS], error_target) and max_iterations > 0:
        loop_out[base + LOOP_RUNNING] = 1
        if worlds > 1:
            wp.atomic_max(loop_out, LOOP_RUNNING, 1)


@wp.kernel(enable_backward=False)
def end_cg_iteration(
    check_every: int,
    max_iterations: int,
    worlds: int,
    # outputs
    cg_sums_out: wp.array(dtype=wp.float64),
    cg_scalars_out: wp.array2d(dtype=wp.float64),
    step_out: wp.array(dtype=float),
    status_out: wp.array(dtype=wp.float64),
    loop_out: wp.array(dtype=wp.int32),
):
    """Count a CG iteration (1 thread per world): the new residual's r.s and r.r (summed by `cg_residual_dots` into
    cg_sums_out, cleared here) into the next row, and the next direction's beta into step_out[CG_BETA]; every
    `check_every` iterations and at the cap, measure the relative residual and stop at the tolerance (or a non-finite
    residual); stop at the cap. A world that stopped only clears its sums; with batched worlds the batch's loop runs
    on while any world does (its flag cleared by `cg_step_size`), its iteration count the largest."""
    w = wp.tid()
    base = world_loop(w, worlds)
    col = w * CG_COLUMNS
    st = w * STATUS_SIZE
    rs_new = cg_sums_out[col + CG_RS]
    rr_new = cg_sums_out[col + CG_RR]
    cg_sums_out[col + CG_RS] = wp.float64(0.0)
    cg_sums_out[col + CG_RR] = wp.float64(0.0)
    if loop_out[base + LOOP_RUNNING] == 0:
        return
    k = loop_out[base + LOOP_ITERATION] + 1
    loop_out[base + LOOP_ITERATION] = k
    cg_scalars_out[k, col + CG_RS] = rs_new
    cg_scalars_out[k, col + CG_RR] = rr_new
    rs = cg_scalars_out[k - 1, col + CG_RS]
    beta = float(0.0)
    if rs > wp.float64(0.0):
        beta = float(rs_new / rs)
    step_out[w * 2 + CG_BETA] = beta  # r_new.s_new / r.s: `cg_direction`'s
    loop_out[base + LOOP_BEST] = 0
    if rr_new < status_out[st + STATUS_BEST]:
        status_out[st + STATUS_BEST] = rr_new
        loop_out[base + LOOP_BEST] = 1
    if k % check_every == 0 or k >= max_iterations:
        relative = relative_residual(rr_new, status_out[st + STATUS_REFERENCE])
        status_out[st + STATUS_RELATIVE] = relative
        if cg_stops(relative, status_out[st + STATUS_STOP], rs_new, status_out[st + STATUS_ERROR_TARGET]):
            loop_out[base + LOOP_RUNNING] = 0
    if k >= max_iterations:
        loop_out[base + LOOP_RUNNING] = 0
    if worlds > 1:
        wp.atomic_max(loop_out, LOOP_ITERATION, k)
        if loop_out[base + LOOP_RUNNING] != 0:
            wp.atomic_max(loop_out, LOOP_RUNNING, 1)


@wp.kernel(enable_backward=False)
def check_jacobi_residual(
    cg_scalars: wp.array2d(dtype=wp.float64),
    max_iterations: int,
    worlds: int,
    # outputs
    status_out: wp.array(dtype=wp.float64),
    loop_out: wp.array(dtype=wp.int32),
):
    """Block Jacobi (1 thread per world): when the world's check is due, the relative residual eval_system_residual
    measured; stop the world at the tolerance, a non-finite residual or the cap. (Batched: the batch's flag is cleared
    here and set again by `end_jacobi_iteration`'s worlds that go on.)"""
    w = wp.tid()
    base = world_loop(w, worlds)
    st = w * STATUS_SIZE
    if worlds > 1 and w == 0:
        loop_out[LOOP_RUNNING] = 0
    if loop_out[base + LOOP_CHECK] == 0:
        return
    loop_out[base + LOOP_CHECK] = 0
    relative = relative_residual(cg_scalars[JACOBI_CHECK_ROW, w * CG_COLUMNS + CG_RR], status_out[st + STATUS_REFERENCE])
    status_out[st + STATUS_RELATIVE] = relative
    if stops(relative, status_out[st + STATUS_STOP]) or loop_out[base + LOOP_ITERATION] >= max_iterations:
        loop_out[base + LOOP_RUNNING] = 0


@wp.kernel(enable_backward=False)
def end_jacobi_iteration(
    check_every: int,
    max_iterations: int,
    worlds: int,
    # outputs
    cg_scalars_out: wp.array2d(dtype=wp.float64),
    loop_out: wp.array(dtype=wp.int32),
):
    """Count a block-Jacobi iteration (1 thread per world); every `check_every` iterations and at the cap a residual
    check is due (its accumulator cleared). Batched: the batch's loop runs on while any world does, its iteration count
    the largest."""
    w = wp.tid()
    base = world_loop(w, worlds)
    if loop_out[base + LOOP_RUNNING] == 0:
        return
    k = loop_out[base + LOOP_ITERATION] + 1
    loop_out[base + LOOP_ITERATION] = k
    if k % check_every == 0 or k >= max_iterations:
        loop_out[base + LOOP_CHECK] = 1
        cg_scalars_out[JACOBI_CHECK_ROW, w * CG_COLUMNS + CG_RR] = wp.float64(0.0)
    if worlds > 1:
        wp.atomic_max(loop_out, LOOP_ITERATION, k)
        wp.atomic_max(loop_out, LOOP_RUNNING, 1)


@wp.kernel(enable_backward=False)
def end_linear_solve(
    status: wp.array(dtype=wp.float64),
    loop: wp.array(dtype=wp.int32),
    tolerance: wp.float64,
    keep_start: int,
    contact_counts: wp.array(dtype=wp.int32),
    release: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    record_out: wp.array(dtype=wp.float64),
    previous_ready_out: wp.array(dtype=wp.int32),
):
    """Record a finished solve (1 thread per world, into its record); with `keep_start`, its dv starts the next solve
    unless it failed."""
    w = wp.tid()
    base = world_loop(w, worlds)
    rec = w * RECORD_SIZE
    relative = status[w * STATUS_SIZE + STATUS_RELATIVE]
    iterations = wp.float64(loop[base + LOOP_ITERATION] + loop[base + LOOP_CARRIED])
    solves = record_out[rec + RECORD_SOLVES] + wp.float64(1.0)
    record_out[rec + RECORD_SOLVES] = solves
    record_out[rec + RECORD_ITERATIONS] = record_out[rec + RECORD_ITERATIONS] + iterations
    counts = world_slot(w, worlds, COUNT_SIZE)
    record_out[rec + RECORD_CONTACTS] = record_out[rec + RECORD_CONTACTS] + wp.float64(contact_counts[counts + COUNT_CONTACTS])
    record_out[rec + RECORD_SELF_CONTACTS] = record_out[rec + RECORD_SELF_CONTACTS] + wp.float64(
        contact_counts[counts + COUNT_SELF_CONTACTS])
    record_out[rec + RECORD_RESOLVES] = record_out[rec + RECORD_RESOLVES] + wp.float64(
        release[world_slot(w, worlds, RELEASE_SIZE) + RELEASE_ROUNDS])
    record_out[rec + RECORD_MOST_ITERATIONS] = wp.max(record_out[rec + RECORD_MOST_ITERATIONS], iterations)
    record_out[rec + RECORD_LAST_RESIDUAL] = relative
    failed = not wp.isfinite(relative)
    if failed:
        record_out[rec + RECORD_FAILED] = record_out[rec + RECORD_FAILED] + wp.float64(1.0)
        if record_out[rec + RECORD_FIRST_FAILED] == wp.float64(0.0):
            record_out[rec + RECORD_FIRST_FAILED] = solves
    else:
        record_out[rec + RECORD_WORST_RESIDUAL] = wp.max(record_out[rec + RECORD_WORST_RESIDUAL], relative)
        if relative > tolerance:
            record_out[rec + RECORD_UNCONVERGED] = record_out[rec + RECORD_UNCONVERGED] + wp.float64(1.0)
    if keep_start != 0:
        previous_ready_out[w] = wp.where(failed, 0, 1)


@wp.kernel(enable_backward=False)
def keep_velocity_change(
    previous_ready: wp.array(dtype=wp.int32),
    dv: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    dv_previous_out: wp.array(dtype=wp.vec3),
):
    """The solve's dv as the next solve's start (when its world's solve did not fail)."""
    i = wp.tid()
    if previous_ready[particle_world_of(i, particle_world, worlds)] != 0:
        dv_previous_out[i] = dv[i]


# -- differentiation ---------------------------------------------------------------------------
# The taped implicit step never tapes the iterative solve. It tapes dv (the solve's result, pinned rows
# replaced by their prescribed z) and the residual r = S (b - A dv), evaluated element by element with
# the blocks recomputed from x0, so that every parameter A and b depend on is on the tape. Its backward
# solves S A S lam = S dL/d(dv) (A is symmetric) and seeds dL/dr = lam (the implicit function theorem:
# dL/dtheta = lam . dr/dtheta at the solution).


@wp.kernel
def compose_velocity_change(
    particle_pinned: wp.array(dtype=wp.int32),
    pin_target: wp.array(dtype=wp.vec3),
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dv_solved: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs
    dv_out: wp.array(dtype=wp.vec3),
):
    """dv = the solved value on free particles, z_i (a function of target, x0, v0) on pinned ones."""
    i = wp.tid()
    if particle_pinned[i] != 0:
        dv_out[i] = pinned_velocity_change(i, particle_pinned, pin_target, x0, v0, dt)
    else:
        dv_out[i] = dv_solved[i]


@wp.kernel
def eval_residual_particles(
    particle_mass: wp.array(dtype=float),
    particle_pin_stiffness: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    element_force: wp.array(dtype=wp.vec3),
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    pin_target: wp.array(dtype=wp.vec3),
    gravity: wp.vec3,
    global_damping: float,
    dt: float,
    # outputs (accumulated)
    residual_out: wp.array(dtype=wp.vec3),
):
    """Per-particle part of r = b - A dv: h f0 - h^2 k_pin v0 - M' dv (free particles only)."""
    i = wp.tid()
    if particle_pinned[i] != 0:
        return
    f0 = total_force(i, particle_mass, particle_pin_stiffness, element_force, x0, v0, pin_target, gravity, global_damping)
    m_eff = effective_mass(i, particle_mass, particle_pin_stiffness, global_damping, dt)
    r = dt * (f0 - dt * particle_pin_stiffness[i] * v0[i]) - m_eff * dv[i]
    wp.atomic_add(residual_out, i, r)


@wp.func
def add_free(particle_pinned: wp.array(dtype=wp.int32), i: int, value: wp.vec3, residual_out: wp.array(dtype=wp.vec3)):
    """residual_out[i] += value on free particles (pinned rows of the filtered residual stay 0)."""
    if particle_pinned[i] == 0:
        wp.atomic_add(residual_out, i, value)


@wp.kernel
def eval_residual_springs(
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    spring_middle: wp.array(dtype=wp.int32),
    particle_pinned: wp.array(dtype=wp.int32),
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs (accumulated)
    residual_out: wp.array(dtype=wp.vec3),
):
    """Spring and bend-triple part of r: -h^2 K (v0 + dv) - h D dv, blocks recomputed from x0."""
    s = wp.tid()
    a = spring_indices[s, 0]
    b = spring_indices[s, 1]
    m = spring_middle[s]
    if m < 0:
        k_block = spring_stiffness_block(x0[a], x0[b], spring_rest_length[s], spring_stiffness[s])
        d_block = spring_damping_block(x0[a], x0[b], spring_damping[s])
        q = dt * dt * (k_block * (v0[a] + dv[a] - v0[b] - dv[b])) + dt * (d_block * (dv[a] - dv[b]))
        add_free(particle_pinned, a, -q, residual_out)
        add_free(particle_pinned, b, q, residual_out)
    else:
        g = bending_stiffness_weights(x0[a], x0[m], x0[b], spring_stiffness[s])
        t = dt * dt * (g[0] * (v0[a] + dv[a]) + g[1] * (v0[m] + dv[m]) + g[2] * (v0[b] + dv[b]))
        add_free(particle_pinned, a, -g[0] * t, residual_out)
        add_free(particle_pinned, m, -g[1] * t, residual_out)
        add_free(particle_pinned, b, -g[2] * t, residual_out)


@wp.kernel
def eval_residual_membrane(
    membrane_vertices: wp.array(dtype=wp.vec3i),
    membrane_rest_inverse: wp.array(dtype=wp.mat22),
    membrane_rest_area: wp.array(dtype=float),
    membrane_stiffness: wp.array(dtype=wp.vec4),
    membrane_damping: wp.array(dtype=wp.vec4),
    particle_pinned: wp.array(dtype=wp.int32),
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs (accumulated)
    residual_out: wp.array(dtype=wp.vec3),
):
    """Membrane-element part of r: -h^2 K_e (v0 + dv) - h D_e dv, the element recomputed from x0."""
    e = wp.tid()
    c = membrane_vertices[e]
    a = c[0]
    b = c[1]
    d = c[2]
    area = membrane_rest_area[e]
    b0, b1, b2, voigt_k, geometric = membrane_system(x0[a], x0[b], x0[d], membrane_rest_inverse[e], area, membrane_stiffness[e],
                                                     membrane_damping[e], dt * dt, 0.0)
    k0, k1, k2 = membrane_product(b0, b1, b2, voigt_k, geometric, v0[a] + dv[a], v0[b] + dv[b], v0[d] + dv[d])
    voigt_d = (dt * area) * membrane_voigt(membrane_damping[e])
    d0, d1, d2 = membrane_product(b0, b1, b2, voigt_d, wp.mat33(0.0), dv[a], dv[b], dv[d])
    add_free(particle_pinned, a, -(k0 + d0), residual_out)
    add_free(particle_pinned, b, -(k1 + d1), residual_out)
    add_free(particle_pinned, d, -(k2 + d2), residual_out)


@wp.kernel
def eval_residual_plate(
    plate_offsets: wp.array(dtype=wp.int32),
    plate_points: wp.array(dtype=wp.int32),
    plate_weights: wp.array(dtype=wp.vec3),
    plate_stiffness: wp.array(dtype=wp.mat33),
    particle_pinned: wp.array(dtype=wp.int32),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs (accumulated)
    residual_out: wp.array(dtype=wp.vec3),
):
    """Plate-stencil part of r: -h^2 K (v0 + dv), K = (c_i . S c_j) I (constant: no x0)."""
    s = wp.tid()
    start = plate_offsets[s]
    end = plate_offsets[s + 1]
    u = plate_curvature(plate_points, plate_weights, start, end, v0) + plate_curvature(plate_points, plate_weights, start, end, dv)
    t = (dt * dt) * u * plate_stiffness[s]
    for k in range(start, end):
        add_free(particle_pinned, plate_points[k], -(t * plate_weights[k]), residual_out)


@wp.kernel
def eval_residual_drag(
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_drag: wp.array(dtype=float),
    tri_corner_weights: wp.array(dtype=wp.vec3),
    particle_pinned: wp.array(dtype=wp.int32),
    x0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs (accumulated)
    residual_out: wp.array(dtype=wp.vec3),
):
    """Air-drag part of r: -h w_c g_t (g_t . sum_k w_k dv_k) at each corner c."""
    t = wp.tid()
    a = tri_indices[t, 0]
    b = tri_indices[t, 1]
    c = tri_indices[t, 2]
    w = tri_corner_weights[t]
    # g g^T p = c_A A (n . p) n = -(the drag force at velocities p, no wind); not through g, whose square
    # root has an infinite derivative at c_A = 0
    q = -dt * triangle_drag_force(x0[a], x0[b], x0[c], dv[a], dv[b], dv[c], w, tri_drag[t], wp.vec3(0.0))
    add_free(particle_pinned, a, -w[0] * q, residual_out)
    add_free(particle_pinned, b, -w[1] * q, residual_out)
    add_free(particle_pinned, c, -w[2] * q, residual_out)


@wp.kernel
def jacobi_correct(
    particle_pinned: wp.array(dtype=wp.int32),
    precond: wp.array(dtype=wp.mat33),
    dv_in: wp.array(dtype=wp.vec3),
    residual: wp.array(dtype=wp.vec3),
    # outputs
    dv_out: wp.array(dtype=wp.vec3),
):
    """One block-Jacobi iteration written as dv + P r (the taped, unrolled reference solve)."""
    i = wp.tid()
    if particle_pinned[i] != 0:
        dv_out[i] = dv_in[i]
    else:
        dv_out[i] = dv_in[i] + precond[i] * residual[i]


@wp.kernel(enable_backward=False)
def add_vectors(src: wp.array(dtype=wp.vec3), dst_out: wp.array(dtype=wp.vec3)):
    """dst_out += src (seeding a gradient from a host-side adjoint solve)."""
    i = wp.tid()
    dst_out[i] = dst_out[i] + src[i]
