"""Provot strain limiting (deformation constraints) as colour-wise Gauss-Seidel passes, and the device-side
convergence check and per-step record of the limiter (so graph-captured runs check and report too)."""

import warp as wp

from .worlds import particle_world_of, world_slot

LENGTH_EPS = wp.constant(1.0e-9)
ATTACHMENT_MAX = wp.constant(4)  # long-range attachments per particle
WELD_MEMBERS_MAX = wp.constant(8)  # particles per welded sewn point the strain limiter keeps together
SPLIT_FLOOR = wp.constant(1.0e-2)  # limit_split: the least share of a spring's inverse mass along it that is moved


@wp.func
def limit_split(w_self: float, w_other: float, u: wp.vec3, n_self: wp.vec3, c_self: float, c_other: float):
    """The move per unit excess [m/m] of one end of a spring shortened along u (its unit vector from the other end to
    this one) when an end touches a collider (kernels/collide.py `eval_limit_contact_normals`): an end whose move
    (-u for this one) would go into its collider (c = its normal's component against the move, > 0) moves only in
    its tangent plane, its inverse mass along u w (1 - c^2), and the other end takes the rest of the excess
    (mass-weighted projection with the contact's inverse mass w (I - n n^T), as the implicit solve's filter).
    Zero when neither end can move much along u (a_self + a_other < SPLIT_FLOOR (w_self + w_other): the spring runs
    through the collider), so a blocked end never slides more than 10x the excess."""
    blocked_self = wp.max(c_self, 0.0)
    blocked_other = wp.max(c_other, 0.0)
    total = w_self * (1.0 - blocked_self * blocked_self) + w_other * (1.0 - blocked_other * blocked_other)
    share = wp.where(total < SPLIT_FLOOR * (w_self + w_other), 0.0, w_self / wp.max(total, LENGTH_EPS))
    return share * (u - blocked_self * n_self)


@wp.kernel
def apply_strain_limit_color(
    # Model
    strain_limit_colors: wp.array2d(dtype=wp.int32),
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_rest_length: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    contact_normal: wp.array(dtype=wp.vec3),
    # State in
    x_in: wp.array(dtype=wp.vec3),
    color: int,
    max_strain: float,
    relaxation: float,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    # outputs
    x_out: wp.array(dtype=wp.vec3),
):
    """Shorten the colour's over-stretched springs to (1 + max_strain) L, split by inverse mass (Provot 1995)
    (batched worlds: in the worlds still sweeping, `loop`; the others pass their positions through).

    With relaxation > 1 the excess is over-corrected (successive over-relaxation, never below the rest
    length), which speeds up the propagation of corrections along long chains of active constraints.
    """
    i = wp.tid()
    xi = x_in[i]
    s = strain_limit_colors[color, i]
    sweeping = True
    if worlds > 1:
        sweeping = loop[world_slot(particle_world[i], worlds, LIMIT_LOOP_SIZE)] != 0
    if s < 0 or particle_pinned[i] != 0 or not sweeping:
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
    u = d / length
    ci = wp.dot(u, contact_normal[i])
    cj = -wp.dot(u, contact_normal[j])
    if ci <= 0.0 and cj <= 0.0:
        x_out[i] = xi - (wi / (wi + wj)) * excess / length * d
    else:
        x_out[i] = xi - limit_split(wi, wj, u, contact_normal[i], ci, cj) * excess


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
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    # outputs
    x_out: wp.array(dtype=wp.vec3),
):
    """Long-range attachments (Kim et al. 2012): |x_i - x_p| <= (1 + max_strain) g_ip for pinned p (batched worlds:
    in the worlds still sweeping, `loop`).

    g_ip is the shortest rest length along limited springs from i to p, so any state whose springs all
    satisfy the strain limit satisfies these too; projecting onto them removes in one pass the global
    stretch that local passes would need O(n^2) sweeps for. At most ATTACHMENT_MAX attachments per particle.
    """
    i = wp.tid()
    xi = x_in[i]
    sweeping = True
    if worlds > 1:
        sweeping = loop[world_slot(particle_world[i], worlds, LIMIT_LOOP_SIZE)] != 0
    if particle_pinned[i] == 0 and sweeping:
        for a in range(ATTACHMENT_MAX):  # a constant range is unrolled: xi stays differentiable from one to the next
            p = -1
            if a < attachment_particle.shape[1]:
                p = attachment_particle[i, a]
            if p >= 0:
                d = xi - x_in[p]
                length = wp.length(d)
                limit = (1.0 + max_strain) * attachment_rest_distance[i, a]
                if length > limit:
                    xi = x_in[p] + (limit / length) * d
    x_out[i] = xi


@wp.kernel
def weld_limited_points(
    # Strain limiter data: per particle, the particles of its welded sewn point (itself among them; -1 padded)
    point_members: wp.array2d(dtype=wp.int32),
    particle_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    # State in
    x_in: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    # outputs
    x_out: wp.array(dtype=wp.vec3),
):
    """Each free particle of a welded sewn point to the point's centre of mass, or where its pinned particles are (the
    sewing weld, cloth_warp/sewing.py, as a pass of a strain-limit sweep: the limiter moves a point's particles as one;
    batched worlds: in the worlds still sweeping, `loop`)."""
    i = wp.tid()
    xi = x_in[i]
    sweeping = True
    if worlds > 1:
        sweeping = loop[world_slot(particle_world[i], worlds, LIMIT_LOOP_SIZE)] != 0
    if particle_pinned[i] != 0 or not sweeping or point_members[i, 0] < 0:
        x_out[i] = xi
        return
    mass = float(0.0)
    moment = wp.vec3(0.0)
    pinned_mass = float(0.0)
    pinned_moment = wp.vec3(0.0)
    for k in range(WELD_MEMBERS_MAX):  # a constant range is unrolled: the sums stay differentiable
        j = -1
        if k < point_members.shape[1]:
            j = point_members[i, k]
        if j >= 0:
            mj = particle_mass[j]
            if particle_pinned[j] != 0:
                pinned_mass = pinned_mass + mj
                pinned_moment = pinned_moment + mj * x_in[j]
            else:
                mass = mass + mj
                moment = moment + mj * x_in[j]
    if pinned_mass > 0.0:
        x_out[i] = pinned_moment / pinned_mass
    else:
        x_out[i] = moment / mass


@wp.kernel(enable_backward=False)
def apply_strain_limit_springs(
    # Model
    color_springs: wp.array(dtype=wp.int32),
    first: int,
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_rest_length: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    contact_normal: wp.array(dtype=wp.vec3),
    max_strain: float,
    relaxation: float,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    loop: wp.array(dtype=wp.int32),
    # updated in place (forward only: no two springs of a colour share a particle, so no races)
    x_out: wp.array(dtype=wp.vec3),
):
    """The same projection as apply_strain_limit_color, one thread per spring of the colour, in place (batched
    worlds: only in the worlds still sweeping, `loop`)."""
    s = color_springs[first + wp.tid()]
    a = spring_indices[s, 0]
    b = spring_indices[s, 1]
    if worlds > 1:
        if loop[world_slot(particle_world[a], worlds, LIMIT_LOOP_SIZE)] == 0:
            return
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
    u = d / length
    ca = wp.dot(u, contact_normal[a])
    cb = -wp.dot(u, contact_normal[b])
    if ca <= 0.0 and cb <= 0.0:
        corr = (excess / ((wa + wb) * length)) * d
        x_out[a] = x_out[a] - wa * corr
        x_out[b] = x_out[b] + wb * corr
    else:
        x_out[a] = x_out[a] - limit_split(wa, wb, u, contact_normal[a], ca, cb) * excess
        x_out[b] = x_out[b] - limit_split(wb, wa, -u, contact_normal[b], cb, ca) * excess


# -- convergence bookkeeping (on the device, so a captured graph checks too) ---------------------------------
# status: [excess before limiting, structural excess, shear excess] of the last apply (l / L - 1 - max_strain);
# loop: [continue (the capture_while condition), sweeps done]; record: see StrainLimiter.read_report.
# Batched worlds (cloth_warp.worlds): excess, status and record per world (world w's at w * their size), the loop state
# of world w at LIMIT_LOOP_SIZE * (1 + w) after the batch's (kernels/worlds.py world_slot).
LIMIT_LOOP_SIZE = wp.constant(2)
EXCESS_SIZE = wp.constant(2)
STATUS_SIZE = wp.constant(3)
EXCESS_FLOOR = wp.constant(-1.0e30)
RECORD_STRUCTURAL = wp.constant(0)
RECORD_SHEAR = wp.constant(1)
RECORD_INITIAL = wp.constant(2)
RECORD_STEPS = wp.constant(3)
RECORD_MISSED = wp.constant(4)
RECORD_SWEEPS = wp.constant(5)
RECORD_MOST_SWEEPS = wp.constant(6)
RECORD_SIZE = wp.constant(7)


@wp.kernel(enable_backward=False)
def reset_strain_excess(excess_out: wp.array(dtype=float)):
    """Empty the per-kind excess accumulator (before eval_strain_excess_kinds; one thread per world)."""
    w = wp.tid()
    excess_out[w * EXCESS_SIZE] = EXCESS_FLOOR
    excess_out[w * EXCESS_SIZE + 1] = EXCESS_FLOOR


@wp.func
def strain_excess(s: int, spring_indices: wp.array2d(dtype=wp.int32), spring_rest_length: wp.array(dtype=float),
                  spring_limited: wp.array(dtype=wp.int32), x: wp.array(dtype=wp.vec3), max_strain: float):
    """l / L - 1 - max_strain of spring s; EXCESS_FLOOR when it is not limited."""
    if spring_limited[s] == 0:
        return EXCESS_FLOOR
    return wp.length(x[spring_indices[s, 0]] - x[spring_indices[s, 1]]) / spring_rest_length[s] - 1.0 - max_strain


@wp.kernel(enable_backward=False)
def eval_strain_excess_kinds(
    # Model
    spring_count: int,
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_rest_length: wp.array(dtype=float),
    spring_limited: wp.array(dtype=wp.int32),
    spring_kind: wp.array(dtype=wp.int32),
    # State
    x: wp.array(dtype=wp.vec3),
    max_strain: float,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs (reset by the caller)
    excess_out: wp.array(dtype=float),
):
    """excess_out[k] = max over limited springs of kind k (0 structural, 1 shear) of l / L - 1 - max_strain (per world
    when batched); one thread per spring (the CPU's form, and batched worlds'; see cloth_warp.reductions)."""
    s = wp.tid()
    if spring_limited[s] == 0:
        return
    w = particle_world_of(spring_indices[s, 0], particle_world, worlds)
    wp.atomic_max(excess_out, w * EXCESS_SIZE + wp.min(spring_kind[s], 1),
                  strain_excess(s, spring_indices, spring_rest_length, spring_limited, x, max_strain))


@wp.kernel(enable_backward=False)
def eval_strain_excess_kinds_blocks(
    # Model
    spring_count: int,
    spring_indices: wp.array2d(dtype=wp.int32),
    spring_rest_length: wp.array(dtype=float),
    spring_limited: wp.array(dtype=wp.int32),
    spring_kind: wp.array(dtype=wp.int32),
    # State
    x: wp.array(dtype=wp.vec3),
    max_strain: float,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs (reset by the caller)
    excess_out: wp.array(dtype=float),
):
    """:func:`eval_strain_excess_kinds` with the maxima taken per block, then once per block (the GPU's form, one world)."""
    block, lane = wp.tid()
    s = block * wp.block_dim() + lane
    structural = EXCESS_FLOOR
    shear = EXCESS_FLOOR
    if s < spring_count:
        if spring_kind[s] == 0:
            structural = strain_excess(s, spring_indices, spring_rest_length, spring_limited, x, max_strain)
        else:
            shear = strain_excess(s, spring_indices, spring_rest_length, spring_limited, x, max_strain)
    structural = wp.tile_extract(wp.tile_max(wp.tile(structural)), 0)
    shear = wp.tile_extract(wp.tile_max(wp.tile(shear)), 0)
    if lane == 0:
        wp.atomic_max(excess_out, 0, structural)
        wp.atomic_max(excess_out, 1, shear)


@wp.func
def take_strain_excess(w: int, excess_out: wp.array(dtype=float), status_out: wp.array(dtype=float)):
    """Move world w's accumulated per-kind excess into its status [1:3] and empty its accumulator."""
    status_out[w * STATUS_SIZE + 1] = excess_out[w * EXCESS_SIZE]
    status_out[w * STATUS_SIZE + 2] = excess_out[w * EXCESS_SIZE + 1]
    excess_out[w * EXCESS_SIZE] = EXCESS_FLOOR
    excess_out[w * EXCESS_SIZE + 1] = EXCESS_FLOOR


@wp.kernel(enable_backward=False)
def begin_strain_limit(
    max_sweeps: int,
    tolerance: float,
    check: int,
    worlds: int,
    # outputs
    excess_out: wp.array(dtype=float),
    status_out: wp.array(dtype=float),
    loop_out: wp.array(dtype=wp.int32),
):
    """Read the excess before limiting, empty the accumulator and decide whether to sweep at all (with `check`,
    only when the excess is above the tolerance); one thread per world (batched: the batch sweeps while any world
    does, its flag cleared by the caller)."""
    w = wp.tid()
    base = world_slot(w, worlds, LIMIT_LOOP_SIZE)
    e = wp.max(excess_out[w * EXCESS_SIZE], excess_out[w * EXCESS_SIZE + 1])
    status_out[w * STATUS_SIZE] = e
    take_strain_excess(w, excess_out, status_out)
    loop_out[base + 1] = 0
    go = max_sweeps > 0
    if check != 0 and e <= tolerance:
        go = False
    loop_out[base] = wp.where(go, 1, 0)
    if worlds > 1 and go:
        wp.atomic_max(loop_out, 0, 1)


@wp.kernel(enable_backward=False)
def end_strain_limit_sweep(
    max_sweeps: int,
    tolerance: float,
    check: int,
    worlds: int,
    # outputs
    excess_out: wp.array(dtype=float),
    status_out: wp.array(dtype=float),
    loop_out: wp.array(dtype=wp.int32),
):
    """Count a sweep; with `check`, take the excess it left (and empty the accumulator): sweep on while it is
    above the tolerance and fewer than max_sweeps sweeps were done. One thread per world; a world that stopped
    only empties its accumulator; batched, the batch's flag (cleared by the caller) is set while any world sweeps on."""
    w = wp.tid()
    base = world_slot(w, worlds, LIMIT_LOOP_SIZE)
    if loop_out[base] == 0:
        excess_out[w * EXCESS_SIZE] = EXCESS_FLOOR
        excess_out[w * EXCESS_SIZE + 1] = EXCESS_FLOOR
        return
    n = loop_out[base + 1] + 1
    loop_out[base + 1] = n
    go = n < max_sweeps
    if check != 0:
        take_strain_excess(w, excess_out, status_out)
        if wp.max(status_out[w * STATUS_SIZE + 1], status_out[w * STATUS_SIZE + 2]) <= tolerance:
            go = False
    loop_out[base] = wp.where(go, 1, 0)
    if worlds > 1 and go:
        wp.atomic_max(loop_out, 0, 1)


@wp.kernel(enable_backward=False)
def finish_strain_limit(
    # outputs
    excess_out: wp.array(dtype=float),
    status_out: wp.array(dtype=float),
):
    """Take the excess measured after the last sweep (fixed-sweep runs measure once, at the end; one thread per world)."""
    take_strain_excess(wp.tid(), excess_out, status_out)


@wp.kernel(enable_backward=False)
def record_strain_limit(
    status: wp.array(dtype=float),
    loop: wp.array(dtype=wp.int32),
    tolerance: float,
    worlds: int,
    # outputs
    record_out: wp.array(dtype=float),
    backup_out: wp.array(dtype=float),
):
    """Add the last step to the record (kept first in backup_out, so a rejected step can be taken back):
    worst excess after limiting per kind and before it (floored at 0), steps, steps left above the
    tolerance, sweeps and the most sweeps in one step. One thread per world, into its record."""
    w = wp.tid()
    r = w * RECORD_SIZE
    st = w * STATUS_SIZE
    for k in range(RECORD_SIZE):
        backup_out[r + k] = record_out[r + k]
    record_out[r + RECORD_STRUCTURAL] = wp.max(record_out[r + RECORD_STRUCTURAL], status[st + 1])
    record_out[r + RECORD_SHEAR] = wp.max(record_out[r + RECORD_SHEAR], status[st + 2])
    record_out[r + RECORD_INITIAL] = wp.max(record_out[r + RECORD_INITIAL], status[st])
    record_out[r + RECORD_STEPS] = record_out[r + RECORD_STEPS] + 1.0
    if wp.max(status[st + 1], status[st + 2]) > tolerance:
        record_out[r + RECORD_MISSED] = record_out[r + RECORD_MISSED] + 1.0
    sweeps = float(loop[world_slot(w, worlds, LIMIT_LOOP_SIZE) + 1])
    record_out[r + RECORD_SWEEPS] = record_out[r + RECORD_SWEEPS] + sweeps
    record_out[r + RECORD_MOST_SWEEPS] = wp.max(record_out[r + RECORD_MOST_SWEEPS], sweeps)


@wp.kernel(enable_backward=False)
def accumulate_vectors(src: wp.array(dtype=wp.vec3), dst_out: wp.array(dtype=wp.vec3)):
    """dst_out += src (hands the limiter's input gradient back to the tape)."""
    i = wp.tid()
    dst_out[i] = dst_out[i] + src[i]


@wp.kernel
def gather_sewn_points(
    particle_seam_root: wp.array(dtype=wp.int32),
    particle_mass: wp.array(dtype=float),
    particle_pinned: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # outputs: per slot (the point's root; + particle count for its pinned particles)
    slot_mass_out: wp.array(dtype=float),
    slot_moment_out: wp.array(dtype=wp.vec3),
    slot_momentum_out: wp.array(dtype=wp.vec3),
):
    """Sum the mass, m x and m v of each welded sewn point's particles (`particle_seam_root` >= 0), its pinned ones apart."""
    i = wp.tid()
    r = particle_seam_root[i]
    if r < 0:
        return
    slot = r
    if particle_pinned[i] != 0:
        slot = r + particle_seam_root.shape[0]
    m = particle_mass[i]
    wp.atomic_add(slot_mass_out, slot, m)
    wp.atomic_add(slot_moment_out, slot, m * x[i])
    wp.atomic_add(slot_momentum_out, slot, m * v[i])


@wp.kernel
def weld_sewn_points(
    particle_seam_root: wp.array(dtype=wp.int32),
    particle_pinned: wp.array(dtype=wp.int32),
    slot_mass: wp.array(dtype=float),
    slot_moment: wp.array(dtype=wp.vec3),
    slot_momentum: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # outputs
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    """Move each free particle of a welded sewn point to the point's centre of mass with its mean velocity
    (momentum kept); a point with pinned particles goes where they are, with their velocity."""
    i = wp.tid()
    r = particle_seam_root[i]
    if r < 0 or particle_pinned[i] != 0:
        x_out[i] = x[i]
        v_out[i] = v[i]
        return
    slot = r
    pinned = r + particle_seam_root.shape[0]
    if slot_mass[pinned] > 0.0:
        slot = pinned
    x_out[i] = slot_moment[slot] / slot_mass[slot]
    v_out[i] = slot_momentum[slot] / slot_mass[slot]


@wp.kernel
def follow_point_roots(
    particle_point_root: wp.array(dtype=wp.int32),
    dv: wp.array(dtype=wp.vec3),
    # outputs
    dv_out: wp.array(dtype=wp.vec3),
):
    """Each particle of a welded point an implicit solve took as one particle (`particle_point_root` >= 0: its root,
    cloth_warp/sewing.py `welded_view`) takes the root's velocity change [m/s]; any other particle keeps its own."""
    i = wp.tid()
    r = particle_point_root[i]
    if r >= 0:
        dv_out[i] = dv[r]
    else:
        dv_out[i] = dv[i]


@wp.kernel
def gather_point_masses(
    particle_point_root: wp.array(dtype=wp.int32),
    particle_mass: wp.array(dtype=float),
    # outputs (zeroed by the caller)
    mass_out: wp.array(dtype=float),
):
    """The masses [kg] an implicit solve that takes each welded point as one particle sees: a point's root carries the
    point's (its own and its other particles'), every particle its own besides (the others are out of the system)."""
    i = wp.tid()
    m = particle_mass[i]
    r = particle_point_root[i]
    if r >= 0 and r != i:
        wp.atomic_add(mass_out, r, m)
    wp.atomic_add(mass_out, i, m)
