"""Cloth-cloth contact (Bridson, Fedkiw & Anderson 2002; physics.md 3(f)): proximity repulsion with
friction, continuous collision detection on the step's linear trajectories, and impulse distribution.

A contact couples four particles with weights alpha (point-triangle: (-w1, -w2, -w3, 1), the point
last; edge-edge: (1 - a, a, -(1 - b), -b)) and a unit normal n pointing from the second element toward
the first. The relative velocity is sum_i alpha_i v_i; an impulse P changes particle i by
alpha_i P / m_i, so the relative velocity changes by P sum_i alpha_i^2 / m_i and the total momentum
by P sum_i alpha_i = 0 (pinned particles have 1/m = 0). With equal masses this is Bridson's
I~ = 2 I / (1 + sum w^2) with the corrected signs.

Contacts of one pass run in parallel: each accumulates its velocity changes, and every particle takes
the average of the changes it received (a Jacobi pass; several passes converge where Bridson's loop is
sequential).
"""

import warp as wp

from .broadphase import boxes_overlap, share_vertex

COPLANAR_BISECTIONS = wp.constant(32)
NORMAL_EPS = wp.constant(1.0e-12)

# Indices into the self-collision counter block (int32): counters summed since the last reset, then, for the
# capturable path, the largest need seen for each fixed-capacity buffer (0 when it always fitted).
COUNT_PROXIMITY = wp.constant(0)  # repulsion impulses
COUNT_CCD = wp.constant(1)  # CCD impacts found
COUNT_OVERSIZED = wp.constant(2)  # elements whose box the broad phase clamped
COUNT_SWEEPS = wp.constant(3)  # CCD passes with impulses (capturable path)
COUNT_BUILDS = wp.constant(4)  # full broad-phase builds (capturable path)
COUNT_ZONES = wp.constant(5)  # rigid impact zones formed (each step's last round's, capturable path)
COUNT_PATCHES = wp.constant(6)  # broad-phase patches (capturable path)
COUNT_ZONE_PARTICLES = wp.constant(7)  # the particles of those zones
COUNT_UNRESOLVED = wp.constant(8)  # steps that ended with impacts left after every impact-zone round (capturable path)
NEED_POINT_ENTRIES = wp.constant(9)  # grid entries of the particles
NEED_EDGE_ENTRIES = wp.constant(10)  # grid entries of the edges
NEED_VERTEX_FACE = wp.constant(11)  # vertex-face candidate pairs (close pairs after a patch)
NEED_EDGE_EDGE = wp.constant(12)  # edge-edge candidate pairs (close pairs after a patch)
COUNT_SIZE = 13

# The capturable path's CCD loop state (int32 [4]): loop again, sweep index, impacts of this sweep, respond.
LOOP_CONTINUE = wp.constant(0)
LOOP_SWEEP = wp.constant(1)
LOOP_HITS = wp.constant(2)
LOOP_RESPOND = wp.constant(3)

# The capturable path's impact-zone loop state (int32 [5]): loop again, merge rounds done, impacts found by this
# round's detection, merge now (capture_if), the step's zones are final (capture_if: count them, clear the labels).
ZONE_CONTINUE = wp.constant(0)
ZONE_ROUND = wp.constant(1)
ZONE_HITS = wp.constant(2)
ZONE_MERGE = wp.constant(3)
ZONE_FINISH = wp.constant(4)
ZONE_STATE_SIZE = 5
ZONE_NONE = wp.constant(2147483647)
"""The capturable path's label of a particle in no zone while zones merge (above every particle index, so that
a minimum over labels picks a member's)."""


@wp.func
def closest_point_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Barycentric weights (of a, b, c) of the point of triangle abc closest to p (Ericson 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.vec3(1.0, 0.0, 0.0)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.vec3(0.0, 1.0, 0.0)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        s = d1 / (d1 - d3)
        return wp.vec3(1.0 - s, s, 0.0)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.vec3(0.0, 0.0, 1.0)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        s = d2 / (d2 - d6)
        return wp.vec3(1.0 - s, 0.0, s)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        s = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3(0.0, 1.0 - s, s)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return wp.vec3(1.0 - v - w, v, w)


@wp.func
def closest_points_segments(p1: wp.vec3, q1: wp.vec3, p2: wp.vec3, q2: wp.vec3):
    """Parameters (a, b) in [0, 1]^2 of the closest points p1 + a (q1 - p1), p2 + b (q2 - p2) (Ericson 5.1.9;
    parallel segments take a = 0 or the clamped projection)."""
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    aa = wp.dot(d1, d1)
    ee = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    s = float(0.0)
    t = float(0.0)
    if aa <= NORMAL_EPS and ee <= NORMAL_EPS:
        return wp.vec2(0.0, 0.0)
    if aa <= NORMAL_EPS:
        return wp.vec2(0.0, wp.clamp(f / ee, 0.0, 1.0))
    c = wp.dot(d1, r)
    if ee <= NORMAL_EPS:
        return wp.vec2(wp.clamp(-c / aa, 0.0, 1.0), 0.0)
    bb = wp.dot(d1, d2)
    denom = aa * ee - bb * bb
    if denom > 1.0e-7 * aa * ee:
        s = wp.clamp((bb * f - c * ee) / denom, 0.0, 1.0)
    t = (bb * s + f) / ee
    if t < 0.0:
        t = 0.0
        s = wp.clamp(-c / aa, 0.0, 1.0)
    elif t > 1.0:
        t = 1.0
        s = wp.clamp((bb - c) / aa, 0.0, 1.0)
    return wp.vec2(s, t)


@wp.func
def weighted_sum(alpha: wp.vec4, a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3):
    return alpha[0] * a + alpha[1] * b + alpha[2] * c + alpha[3] * d


@wp.func
def vertex_face_weights(x: wp.array(dtype=wp.vec3), idx: wp.vec4i):
    """Weights of the point idx[3] against the triangle idx[0..2] at positions x."""
    w = closest_point_triangle(x[idx[3]], x[idx[0]], x[idx[1]], x[idx[2]])
    return wp.vec4(-w[0], -w[1], -w[2], 1.0)


@wp.func
def edge_edge_weights(x: wp.array(dtype=wp.vec3), idx: wp.vec4i):
    """Weights of edge idx[0]idx[1] against edge idx[2]idx[3] at positions x."""
    ab = closest_points_segments(x[idx[0]], x[idx[1]], x[idx[2]], x[idx[3]])
    return wp.vec4(1.0 - ab[0], ab[0], -(1.0 - ab[1]), -ab[1])


@wp.func
def start_weights(kind: int, x: wp.array(dtype=wp.vec3), idx: wp.vec4i):
    """Contact weights of a vertex-face (kind 0) or edge-edge (kind 1) pair at positions x."""
    if kind == 0:
        return vertex_face_weights(x, idx)
    return edge_edge_weights(x, idx)


@wp.func
def closing_speed_bound(kind: int, v: wp.array(dtype=wp.vec3), idx: wp.vec4i):
    """The largest relative speed [m/s] between a vertex of the first element and one of the second: a point
    of each element is a convex combination of its vertices, so their separation changes at
    sum_ij a_i b_j (v_i - v_j), no faster than that (elements moving together, as in a pile, stay close)."""
    bound = float(0.0)
    if kind == 0:
        for k in range(3):
            bound = wp.max(bound, wp.length(v[idx[k]] - v[idx[3]]))
        return bound
    for k in range(2):
        for j in range(2, 4):
            bound = wp.max(bound, wp.length(v[idx[k]] - v[idx[j]]))
    return bound


@wp.func
def in_zone(label: int, count: int):
    """Whether a zone label names a zone: a zone is named by its smallest particle index, in [0, count); -1 (the host
    path) and ZONE_NONE (the capturable path) mean no zone."""
    return label >= 0 and label < count


@wp.func
def pair_indices(pair: wp.vec2i, kind: int, tri_indices: wp.array2d(dtype=wp.int32), edge_indices: wp.array2d(dtype=wp.int32)):
    """The four particles of a vertex-face (kind 0: triangle, point) or edge-edge (kind 1) pair."""
    if kind == 0:
        t = pair[0]
        return wp.vec4i(tri_indices[t, 0], tri_indices[t, 1], tri_indices[t, 2], pair[1])
    return wp.vec4i(edge_indices[pair[0], 0], edge_indices[pair[0], 1], edge_indices[pair[1], 0], edge_indices[pair[1], 1])


@wp.func
def inverse_mass_weight(alpha: wp.vec4, idx: wp.vec4i, inv_mass: wp.array(dtype=float)):
    """sum_i alpha_i^2 / m_i: the relative velocity change per unit impulse."""
    s = float(0.0)
    for i in range(4):
        s += alpha[i] * alpha[i] * inv_mass[idx[i]]
    return s


@wp.func
def add_impulse(idx: wp.vec4i, alpha: wp.vec4, inv_mass: wp.array(dtype=float), impulse: wp.vec3,
                dv_out: wp.array(dtype=wp.vec3), weight_out: wp.array(dtype=float)):
    """Distribute `impulse` [N s] over the pair: particle i gains alpha_i impulse / m_i."""
    for i in range(4):
        im = inv_mass[idx[i]]
        if im > 0.0 and alpha[i] != 0.0:
            wp.atomic_add(dv_out, idx[i], alpha[i] * im * impulse)
            wp.atomic_add(weight_out, idx[i], 1.0)


@wp.func
def pair_impulse(v_rel: wp.vec3, n: wp.vec3, normal_change: float, friction: float, mass_weight: float):
    """Impulse changing the relative normal velocity by `normal_change` [m/s] and slowing the tangential
    part by Coulomb friction, v_T <- max(1 - mu dv_N / |v_T|, 0) v_T."""
    v_n = wp.dot(v_rel, n)
    v_t = v_rel - v_n * n
    speed_t = wp.length(v_t)
    change = normal_change * n
    if speed_t > 0.0 and friction > 0.0:
        keep = wp.max(1.0 - friction * normal_change / speed_t, 0.0)
        change = change + (keep - 1.0) * v_t
    return change / mass_weight


@wp.func
def proximity_response(
    pair: wp.vec2i,
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    x_start: wp.array(dtype=wp.vec3),
    vbar: wp.array(dtype=wp.vec3),
    thickness: float,
    stiffness: float,
    friction: float,
    dt: float,
    dv_out: wp.array(dtype=wp.vec3),
    weight_out: wp.array(dtype=float),
    counts_out: wp.array(dtype=wp.int32),
):
    """Repulsion between elements closer than `thickness` at the step's start (Bridson's proximity
    pass): overlap d = thickness - distance; if the relative normal velocity v_N < 0.1 d / dt, change it
    by min(dt k d / m, 0.1 d / dt - v_N) (never pushing apart faster than 10 % of the overlap per step),
    with friction on the tangential part."""
    idx = pair_indices(pair, kind, tri_indices, edge_indices)
    alpha = start_weights(kind, x_start, idx)
    gap = weighted_sum(alpha, x_start[idx[0]], x_start[idx[1]], x_start[idx[2]], x_start[idx[3]])
    distance = wp.length(gap)
    if distance >= thickness or distance <= NORMAL_EPS:
        return
    mass_weight = inverse_mass_weight(alpha, idx, inv_mass)
    if mass_weight <= 0.0:
        return
    n = gap / distance
    v_rel = weighted_sum(alpha, vbar[idx[0]], vbar[idx[1]], vbar[idx[2]], vbar[idx[3]])
    v_n = wp.dot(v_rel, n)
    overlap = thickness - distance
    target = 0.1 * overlap / dt
    if v_n >= target:
        return
    change = wp.min(dt * stiffness * overlap * mass_weight, target - v_n)
    add_impulse(idx, alpha, inv_mass, pair_impulse(v_rel, n, change, friction, mass_weight), dv_out, weight_out)
    wp.atomic_add(counts_out, COUNT_PROXIMITY, 1)


@wp.kernel
def self_proximity(
    pairs: wp.array(dtype=wp.vec2i),
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    x_start: wp.array(dtype=wp.vec3),
    vbar: wp.array(dtype=wp.vec3),
    thickness: float,
    stiffness: float,
    friction: float,
    dt: float,
    dv_out: wp.array(dtype=wp.vec3),
    weight_out: wp.array(dtype=float),
    counts_out: wp.array(dtype=wp.int32),
):
    """:func:`proximity_response` of each pair."""
    tid = wp.tid()
    proximity_response(pairs[tid], kind, tri_indices, edge_indices, inv_mass, x_start, vbar, thickness, stiffness, friction, dt,
                       dv_out, weight_out, counts_out)


@wp.kernel(enable_backward=False)
def self_proximity_listed(
    count: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    x_start: wp.array(dtype=wp.vec3),
    vbar: wp.array(dtype=wp.vec3),
    thickness: float,
    stiffness: float,
    friction: float,
    dt: float,
    dv_out: wp.array(dtype=wp.vec3),
    weight_out: wp.array(dtype=float),
    counts_out: wp.array(dtype=wp.int32),
):
    """:func:`self_proximity` launched over the list's capacity, the first count[0] pairs (capturable path)."""
    tid = wp.tid()
    if tid >= count[0]:
        return
    proximity_response(pairs[tid], kind, tri_indices, edge_indices, inv_mass, x_start, vbar, thickness, stiffness, friction, dt,
                       dv_out, weight_out, counts_out)


@wp.func
def coplanarity_cubic(x1: wp.vec3, x2: wp.vec3, x3: wp.vec3, x4: wp.vec3, v1: wp.vec3, v2: wp.vec3, v3: wp.vec3, v4: wp.vec3):
    """Coefficients (a0, a1, a2, a3) of f(t) = (x21 + t v21) x (x31 + t v31) . (x41 + t v41)."""
    x21 = x2 - x1
    x31 = x3 - x1
    x41 = x4 - x1
    v21 = v2 - v1
    v31 = v3 - v1
    v41 = v4 - v1
    c0 = wp.cross(x21, x31)
    c1 = wp.cross(v21, x31) + wp.cross(x21, v31)
    c2 = wp.cross(v21, v31)
    return wp.vec4(wp.dot(c0, x41), wp.dot(c1, x41) + wp.dot(c0, v41), wp.dot(c2, x41) + wp.dot(c1, v41), wp.dot(c2, v41))


@wp.func
def cubic_at(c: wp.vec4, t: float):
    return ((c[3] * t + c[2]) * t + c[1]) * t + c[0]


@wp.func
def root_in(c: wp.vec4, lo: float, hi: float):
    """A root of the cubic in [lo, hi] when f changes sign there (or vanishes at lo), else -1."""
    f_lo = cubic_at(c, lo)
    f_hi = cubic_at(c, hi)
    if f_lo == 0.0:
        return lo
    if f_lo * f_hi > 0.0:
        return -1.0
    a = lo
    b = hi
    for _ in range(COPLANAR_BISECTIONS):
        m = 0.5 * (a + b)
        f_m = cubic_at(c, m)
        if (f_m < 0.0) == (f_lo < 0.0):
            a = m
            f_lo = f_m
        else:
            b = m
    return b


@wp.func
def monotone_breaks(c: wp.vec4, h: float):
    """The roots of f' inside (0, h) (where f changes monotonicity), as (t1, t2), -1 for none; f' = 3 a3 t^2
    + 2 a2 t + a1, with the quadratic and linear degenerate cases (a3 = 0, a3 = a2 = 0) handled."""
    qa = 3.0 * c[3]
    qb = 2.0 * c[2]
    qc = c[1]
    t1 = float(-1.0)
    t2 = float(-1.0)
    scale = wp.abs(qa) * h * h + wp.abs(qb) * h + wp.abs(qc)
    if wp.abs(qa) * h * h <= 1.0e-7 * scale:
        if wp.abs(qb) * h > 1.0e-7 * scale:
            t1 = -qc / qb
    else:
        disc = qb * qb - 4.0 * qa * qc
        if disc >= 0.0:
            sq = wp.sqrt(disc)
            # numerically stable pair of roots
            qq = -0.5 * (qb + wp.sign(qb) * sq)
            if qb == 0.0:
                qq = -0.5 * sq
            r1 = qq / qa
            r2 = r1
            if qq != 0.0:
                r2 = qc / qq
            t1 = wp.min(r1, r2)
            t2 = wp.max(r1, r2)
    if not (t1 > 0.0 and t1 < h):
        t1 = -1.0
    if not (t2 > 0.0 and t2 < h):
        t2 = -1.0
    if t1 < 0.0:
        t1 = t2
        t2 = -1.0
    return wp.vec2(t1, t2)


@wp.func
def lerp_positions(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), i: int, t: float):
    return x[i] + t * v[i]


@wp.func
def contact_at(kind: int, idx: wp.vec4i, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), t: float, tolerance: float):
    """At time t of the linear trajectories: the contact weights, or weights with alpha[3] = 0 when the
    elements are farther apart than `tolerance`."""
    p0 = lerp_positions(x, v, idx[0], t)
    p1 = lerp_positions(x, v, idx[1], t)
    p2 = lerp_positions(x, v, idx[2], t)
    p3 = lerp_positions(x, v, idx[3], t)
    alpha = wp.vec4()
    if kind == 0:
        w = closest_point_triangle(p3, p0, p1, p2)
        alpha = wp.vec4(-w[0], -w[1], -w[2], 1.0)
    else:
        ab = closest_points_segments(p0, p1, p2, p3)
        alpha = wp.vec4(1.0 - ab[0], ab[0], -(1.0 - ab[1]), -ab[1])
    if wp.length(weighted_sum(alpha, p0, p1, p2, p3)) > tolerance:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    return alpha


@wp.func
def is_contact(alpha: wp.vec4):
    """contact_at found the elements within the tolerance (valid weights are never all zero)."""
    return wp.dot(alpha, alpha) > 0.0


@wp.func
def contact_normal(kind: int, idx: wp.vec4i, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), t: float, alpha: wp.vec4):
    """Unit normal at time t (triangle normal / cross product of the edges), oriented from the second
    element toward the side the first one came from (its start-of-step side)."""
    p0 = lerp_positions(x, v, idx[0], t)
    p1 = lerp_positions(x, v, idx[1], t)
    p2 = lerp_positions(x, v, idx[2], t)
    p3 = lerp_positions(x, v, idx[3], t)
    n = wp.vec3()
    if kind == 0:
        n = wp.cross(p1 - p0, p2 - p0)
    else:
        n = wp.cross(p1 - p0, p3 - p2)
    start_gap = weighted_sum(alpha, x[idx[0]], x[idx[1]], x[idx[2]], x[idx[3]])
    ln = wp.length(n)
    if ln <= NORMAL_EPS:
        # parallel edges or a degenerate triangle: the direction between the elements at the start
        n = start_gap
        ln = wp.length(n)
        if ln <= NORMAL_EPS:
            return wp.vec3(0.0, 0.0, 0.0)
    n = n / ln
    if wp.dot(start_gap, n) < 0.0:
        n = -n
    return n


@wp.func
def first_contact_time(kind: int, idx: wp.vec4i, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), h: float, tolerance: float):
    """Earliest t in [0, h] at which the four points are coplanar and the elements within `tolerance`,
    -1 if none (the end of the step is also tested, so round-off there cannot hide a contact)."""
    c = coplanarity_cubic(x[idx[0]], x[idx[1]], x[idx[2]], x[idx[3]], v[idx[0]], v[idx[1]], v[idx[2]], v[idx[3]])
    breaks = monotone_breaks(c, h)
    lo = float(0.0)
    for k in range(3):
        hi = h
        if k < 2 and breaks[k] > 0.0:
            hi = breaks[k]
        if hi > lo or (k == 0 and hi == lo):
            t = root_in(c, lo, hi)
            if t >= 0.0:
                if is_contact(contact_at(kind, idx, x, v, t, tolerance)):
                    return t
        lo = hi
        if lo >= h:
            break
    if is_contact(contact_at(kind, idx, x, v, h, tolerance)):
        return h
    return -1.0


@wp.func
def may_touch(kind: int, idx: wp.vec4i, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), dt: float, tolerance: float):
    """Conservative filter: pairs farther apart at the start than dt times their closing-speed bound plus
    the tolerance cannot touch during the step. Culls the many nearby but separated pairs of a smooth
    cloth before the cubic is solved."""
    alpha = start_weights(kind, x, idx)
    gap = wp.length(weighted_sum(alpha, x[idx[0]], x[idx[1]], x[idx[2]], x[idx[3]]))
    return gap - dt * closing_speed_bound(kind, v, idx) <= tolerance


@wp.func
def ccd_response(
    pair: wp.vec2i,
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    zone: wp.array(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    vbar: wp.array(dtype=wp.vec3),
    dt: float,
    tolerance: float,
    separation_speed: float,
    respond: int,
    dv_out: wp.array(dtype=wp.vec3),
    weight_out: wp.array(dtype=float),
    counts_out: wp.array(dtype=wp.int32),
):
    """Continuous collision detection on x_start + t vbar, t in [0, dt]; 1 on an impact, else 0. At the first
    contact, if the pair is not already separating at `separation_speed` / 2, an inelastic impulse sets its
    relative normal velocity to `separation_speed` [m/s] (when `respond`). Pairs whose four particles belong
    to one rigid impact zone (:func:`in_zone`) are skipped: they move rigidly together."""
    idx = pair_indices(pair, kind, tri_indices, edge_indices)
    z = zone[idx[0]]
    if in_zone(z, zone.shape[0]) and zone[idx[1]] == z and zone[idx[2]] == z and zone[idx[3]] == z:
        return 0
    if not may_touch(kind, idx, x_start, vbar, dt, tolerance):
        return 0
    t = first_contact_time(kind, idx, x_start, vbar, dt, tolerance)
    if t < 0.0:
        return 0
    alpha = contact_at(kind, idx, x_start, vbar, t, tolerance)
    n = contact_normal(kind, idx, x_start, vbar, t, alpha)
    if wp.length(n) == 0.0:
        return 0
    v_rel = weighted_sum(alpha, vbar[idx[0]], vbar[idx[1]], vbar[idx[2]], vbar[idx[3]])
    v_n = wp.dot(v_rel, n)
    if v_n >= 0.5 * separation_speed:
        return 0
    mass_weight = inverse_mass_weight(alpha, idx, inv_mass)
    if mass_weight <= 0.0:
        return 0
    wp.atomic_add(counts_out, COUNT_CCD, 1)
    if respond != 0:
        add_impulse(idx, alpha, inv_mass, pair_impulse(v_rel, n, separation_speed - v_n, 0.0, mass_weight), dv_out, weight_out)
    return 1


@wp.kernel
def self_ccd(
    pairs: wp.array(dtype=wp.vec2i),
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    zone: wp.array(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    vbar: wp.array(dtype=wp.vec3),
    dt: float,
    tolerance: float,
    separation_speed: float,
    respond: int,
    dv_out: wp.array(dtype=wp.vec3),
    weight_out: wp.array(dtype=float),
    hit_out: wp.array(dtype=wp.int32),
    counts_out: wp.array(dtype=wp.int32),
):
    """:func:`ccd_response` of each pair, flagging the pairs that hit (the impact zones' input)."""
    tid = wp.tid()
    hit_out[tid] = ccd_response(pairs[tid], kind, tri_indices, edge_indices, inv_mass, zone, x_start, vbar, dt, tolerance,
                                separation_speed, respond, dv_out, weight_out, counts_out)


@wp.kernel(enable_backward=False)
def self_ccd_listed(
    count: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    zone: wp.array(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    vbar: wp.array(dtype=wp.vec3),
    dt: float,
    tolerance: float,
    separation_speed: float,
    dv_out: wp.array(dtype=wp.vec3),
    weight_out: wp.array(dtype=float),
    counts_out: wp.array(dtype=wp.int32),
    loop_out: wp.array(dtype=wp.int32),
):
    """:func:`self_ccd` launched over the list's capacity, the first count[0] pairs, responding when
    loop_out[LOOP_RESPOND] and counting the sweep's impacts in loop_out[LOOP_HITS] (capturable path)."""
    tid = wp.tid()
    if tid >= count[0]:
        return
    hit = ccd_response(pairs[tid], kind, tri_indices, edge_indices, inv_mass, zone, x_start, vbar, dt, tolerance, separation_speed,
                       loop_out[LOOP_RESPOND], dv_out, weight_out, counts_out)
    if hit != 0:
        wp.atomic_add(loop_out, LOOP_HITS, 1)


@wp.kernel(enable_backward=False)
def begin_sweeps(sweeps: int, loop_out: wp.array(dtype=wp.int32)):
    """One thread: the CCD loop starts at sweep 0 (responding unless `sweeps` is 0)."""
    loop_out[LOOP_CONTINUE] = 1
    loop_out[LOOP_SWEEP] = 0
    loop_out[LOOP_HITS] = 0
    loop_out[LOOP_RESPOND] = wp.where(sweeps > 0, 1, 0)


@wp.kernel(enable_backward=False)
def end_sweep(sweeps: int, loop_out: wp.array(dtype=wp.int32), counts_out: wp.array(dtype=wp.int32)):
    """One thread after a CCD sweep: count it (if it responded); stop when it found no impact, or when it was
    the check after the last responding sweep (impacts remain: rigid impact zones follow); otherwise
    go on to the next sweep."""
    k = loop_out[LOOP_SWEEP]
    if k < sweeps:
        counts_out[COUNT_SWEEPS] = counts_out[COUNT_SWEEPS] + 1
    if loop_out[LOOP_HITS] == 0:
        loop_out[LOOP_CONTINUE] = 0
    elif k >= sweeps:
        loop_out[LOOP_CONTINUE] = 0
    else:
        loop_out[LOOP_CONTINUE] = 1
        loop_out[LOOP_SWEEP] = k + 1
        loop_out[LOOP_HITS] = 0
        loop_out[LOOP_RESPOND] = wp.where(k + 1 < sweeps, 1, 0)


@wp.kernel(enable_backward=False)
def increment_count(index: int, counts_out: wp.array(dtype=wp.int32)):
    """One thread: counts_out[index] += 1."""
    counts_out[index] = counts_out[index] + 1


@wp.func
def is_close(
    pair: wp.vec2i,
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    velocity: wp.array(dtype=wp.vec3),
    dt: float,
    margin: float,
    reach: float,
):
    """Whether a broad-phase pair can come within `reach` [m] during the step: every vertex moves at most
    dt |velocity| + margin (the broad phase is reused while end points stay within `margin`), so a pair
    farther apart at the start than reach plus both elements' largest moves never gets close."""
    idx = pair_indices(pair, kind, tri_indices, edge_indices)
    alpha = start_weights(kind, x_start, idx)
    gap = wp.length(weighted_sum(alpha, x_start[idx[0]], x_start[idx[1]], x_start[idx[2]], x_start[idx[3]]))
    return gap <= reach + dt * closing_speed_bound(kind, velocity, idx) + 2.0 * margin


@wp.kernel(enable_backward=False)
def select_close_pairs(
    pairs: wp.array(dtype=wp.vec2i),
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    velocity: wp.array(dtype=wp.vec3),
    dt: float,
    margin: float,
    reach: float,
    selected_out: wp.array(dtype=wp.vec2i),
    count_out: wp.array(dtype=wp.int32),
):
    """Keep the broad phase's pairs that can come within `reach` [m] during the step (:func:`is_close`)."""
    tid = wp.tid()
    if is_close(pairs[tid], kind, tri_indices, edge_indices, x_start, velocity, dt, margin, reach):
        slot = wp.atomic_add(count_out, 0, 1)
        selected_out[slot] = pairs[tid]


@wp.kernel(enable_backward=False)
def select_close_pairs_listed(
    count: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    velocity: wp.array(dtype=wp.vec3),
    dt: float,
    margin: float,
    reach: float,
    selected_out: wp.array(dtype=wp.vec2i),
    count_out: wp.array(dtype=wp.int32),
):
    """:func:`select_close_pairs` launched over the capacity, the first count[0] pairs (capturable path)."""
    tid = wp.tid()
    if tid >= count[0]:
        return
    if is_close(pairs[tid], kind, tri_indices, edge_indices, x_start, velocity, dt, margin, reach):
        slot = wp.atomic_add(count_out, 0, 1)
        selected_out[slot] = pairs[tid]


@wp.func
def append_pair(pair: wp.vec2i, capacity: int, pairs_out: wp.array(dtype=wp.vec2i), count_out: wp.array(dtype=wp.int32)):
    """Count the pair, store it when it fits (a larger count is clamped and recorded afterwards)."""
    slot = wp.atomic_add(count_out, 0, 1)
    if slot < capacity:
        pairs_out[slot] = pair


@wp.func
def element_row(elements: wp.array2d(dtype=wp.int32), e: int):
    return wp.vec3i(elements[e, 0], elements[e, 1], elements[e, 2])


@wp.kernel(enable_backward=False)
def patch_vertex_face_points(
    fresh_triangle_count: wp.array(dtype=wp.int32),
    fresh_triangles: wp.array(dtype=wp.int32),
    triangle_lo: wp.array(dtype=wp.vec3),
    triangle_hi: wp.array(dtype=wp.vec3),
    point_lo: wp.array(dtype=wp.vec3),
    point_hi: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    tri_adjacency: wp.array2d(dtype=wp.int32),
    point_adjacency: wp.array2d(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    velocity: wp.array(dtype=wp.vec3),
    dt: float,
    margin: float,
    reach: float,
    capacity: int,
    pairs_out: wp.array(dtype=wp.vec2i),
    count_out: wp.array(dtype=wp.int32),
):
    """Per particle, its close pairs with the freshly registered triangles (boxes overlap, no shared vertex,
    :func:`is_close`), appended to the close list (a patch of the capturable path's broad phase)."""
    p = wp.tid()
    p_lo = point_lo[p]
    p_hi = point_hi[p]
    p_row = element_row(point_adjacency, p)
    for k in range(fresh_triangle_count[0]):
        t = fresh_triangles[k]
        if not boxes_overlap(triangle_lo[t], triangle_hi[t], p_lo, p_hi):
            continue
        if share_vertex(element_row(tri_adjacency, t), p_row):
            continue
        pair = wp.vec2i(t, p)
        if is_close(pair, 0, tri_indices, edge_indices, x_start, velocity, dt, margin, reach):
            append_pair(pair, capacity, pairs_out, count_out)


@wp.kernel(enable_backward=False)
def patch_vertex_face_triangles(
    triangle_flags: wp.array(dtype=wp.int32),
    fresh_point_count: wp.array(dtype=wp.int32),
    fresh_points: wp.array(dtype=wp.int32),
    triangle_lo: wp.array(dtype=wp.vec3),
    triangle_hi: wp.array(dtype=wp.vec3),
    point_lo: wp.array(dtype=wp.vec3),
    point_hi: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    tri_adjacency: wp.array2d(dtype=wp.int32),
    point_adjacency: wp.array2d(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    velocity: wp.array(dtype=wp.vec3),
    dt: float,
    margin: float,
    reach: float,
    capacity: int,
    pairs_out: wp.array(dtype=wp.vec2i),
    count_out: wp.array(dtype=wp.int32),
):
    """Per triangle not registered again (a fresh one has all its pairs from :func:`patch_vertex_face_points`), its
    close pairs with the freshly registered particles."""
    t = wp.tid()
    if triangle_flags[t] != 0:
        return
    t_lo = triangle_lo[t]
    t_hi = triangle_hi[t]
    t_row = element_row(tri_adjacency, t)
    for k in range(fresh_point_count[0]):
        p = fresh_points[k]
        if not boxes_overlap(t_lo, t_hi, point_lo[p], point_hi[p]):
            continue
        if share_vertex(t_row, element_row(point_adjacency, p)):
            continue
        pair = wp.vec2i(t, p)
        if is_close(pair, 0, tri_indices, edge_indices, x_start, velocity, dt, margin, reach):
            append_pair(pair, capacity, pairs_out, count_out)


@wp.kernel(enable_backward=False)
def patch_edge_edge(
    edge_flags: wp.array(dtype=wp.int32),
    fresh_edge_count: wp.array(dtype=wp.int32),
    fresh_edges: wp.array(dtype=wp.int32),
    edge_lo: wp.array(dtype=wp.vec3),
    edge_hi: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    edge_adjacency: wp.array2d(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    velocity: wp.array(dtype=wp.vec3),
    dt: float,
    margin: float,
    reach: float,
    capacity: int,
    pairs_out: wp.array(dtype=wp.vec2i),
    count_out: wp.array(dtype=wp.int32),
):
    """Per edge, its close pairs with the freshly registered edges (a pair of two fresh edges once, from the lower
    id), as (lower id, higher id) like the full search."""
    e = wp.tid()
    own = edge_flags[e] != 0
    e_lo = edge_lo[e]
    e_hi = edge_hi[e]
    e_row = element_row(edge_adjacency, e)
    for k in range(fresh_edge_count[0]):
        f = fresh_edges[k]
        if f == e or (own and f < e):
            continue
        if not boxes_overlap(e_lo, e_hi, edge_lo[f], edge_hi[f]):
            continue
        if share_vertex(e_row, element_row(edge_adjacency, f)):
            continue
        pair = wp.vec2i(wp.min(e, f), wp.max(e, f))
        if is_close(pair, 1, tri_indices, edge_indices, x_start, velocity, dt, margin, reach):
            append_pair(pair, capacity, pairs_out, count_out)


@wp.kernel(enable_backward=False)
def mark_changed(vbar: wp.array(dtype=wp.vec3), vbar_ref: wp.array(dtype=wp.vec3), changed_out: wp.array(dtype=float)):
    """1 where vbar differs from the reference, else 0 (a change flag in the form of an impulse weight)."""
    i = wp.tid()
    a = vbar[i]
    b = vbar_ref[i]
    changed_out[i] = 0.0
    if a[0] != b[0] or a[1] != b[1] or a[2] != b[2]:
        changed_out[i] = 1.0


@wp.kernel
def average_velocity(x_start: wp.array(dtype=wp.vec3), x_end: wp.array(dtype=wp.vec3), dt: float, vbar_out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    vbar_out[i] = (x_end[i] - x_start[i]) / dt


@wp.kernel
def apply_velocity_changes(vbar: wp.array(dtype=wp.vec3), dv: wp.array(dtype=wp.vec3), weight: wp.array(dtype=float),
                           vbar_out: wp.array(dtype=wp.vec3)):
    """Each particle takes the average of the velocity changes its contacts proposed."""
    i = wp.tid()
    w = weight[i]
    if w > 0.0:
        vbar_out[i] = vbar[i] + dv[i] / w
    else:
        vbar_out[i] = vbar[i]


@wp.kernel
def set_zone_velocity(zone: wp.array(dtype=wp.int32), zone_vbar: wp.array(dtype=wp.vec3), vbar: wp.array(dtype=wp.vec3),
                      vbar_out: wp.array(dtype=wp.vec3)):
    """Particles of a rigid impact zone take zone_vbar (the host path: its zones' rigid motion), the others vbar."""
    i = wp.tid()
    if zone[i] >= 0:
        vbar_out[i] = zone_vbar[i]
    else:
        vbar_out[i] = vbar[i]


@wp.kernel
def finish_step(x_start: wp.array(dtype=wp.vec3), vbar: wp.array(dtype=wp.vec3), vbar_candidate: wp.array(dtype=wp.vec3),
                v_end: wp.array(dtype=wp.vec3), dt: float, x_out: wp.array(dtype=wp.vec3), v_out: wp.array(dtype=wp.vec3)):
    """x = x_start + dt vbar; the end velocity gets the same correction as the average one."""
    i = wp.tid()
    x_out[i] = x_start[i] + dt * vbar[i]
    v_out[i] = v_end[i] + (vbar[i] - vbar_candidate[i])


@wp.kernel(enable_backward=False)
def eval_first_contact(
    pairs: wp.array(dtype=wp.vec2i),
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    vbar: wp.array(dtype=wp.vec3),
    dt: float,
    tolerance: float,
    time_out: wp.array(dtype=float),
):
    """Each candidate pair's first contact time [s] in [0, dt] (-1 for none), without the filter (diagnostics)."""
    tid = wp.tid()
    idx = pair_indices(pairs[tid], kind, tri_indices, edge_indices)
    time_out[tid] = first_contact_time(kind, idx, x_start, vbar, dt, tolerance)


# -- rigid impact zones (Provot 1997; Bridson et al. 2002, section 7.4) ------------------------------------
# A zone is a set of particles that move rigidly together, named by its smallest particle index. The particles of
# pairs still colliding after the CCD sweeps join zones (with the zones they are already in, and with the whole of a
# welded sewn point one of them is in) on the device as a forest: every member's label points to a smaller or equal
# index, a tree's root to itself; each link hooks the larger of its two roots under the smaller (atomic minimum), and
# pointer jumping flattens the trees. Passes repeat until no link joins two trees and no label moves: then every
# member's label is the smallest particle index of its connected component, whatever the order of the updates (a
# hook lost to a concurrent one is retried by the next pass). Sums over a zone are float64 and indexed by its name.


@wp.func
def zone_root(label_out: wp.array(dtype=wp.int32), p: int):
    """The root of the tree particle p is in (p itself when it is in no zone)."""
    n = label_out.shape[0]
    r = p
    up = label_out[r]
    while in_zone(up, n) and up != r:
        r = up
        up = label_out[r]
    return r


@wp.func
def join_zones(label_out: wp.array(dtype=wp.int32), a: int, b: int):
    """Particles a and b join one zone (each joins as its own when in none; then the larger root hooks under the
    smaller); 1 when they were in different trees or a label changed (another pass is needed)."""
    changed = int(0)
    if wp.atomic_min(label_out, a, a) > a:
        changed = 1
    if wp.atomic_min(label_out, b, b) > b:
        changed = 1
    ra = zone_root(label_out, a)
    rb = zone_root(label_out, b)
    if ra != rb:
        wp.atomic_min(label_out, wp.max(ra, rb), wp.min(ra, rb))
        changed = 1
    return changed


@wp.kernel(enable_backward=False)
def merge_colliding_pairs(
    count: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    hit: wp.array(dtype=wp.int32),
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    label_out: wp.array(dtype=wp.int32),
    changed_out: wp.array(dtype=wp.int32),
):
    """The four particles of each listed pair flagged in `hit` join one zone."""
    tid = wp.tid()
    if tid >= count[0] or hit[tid] == 0:
        return
    idx = pair_indices(pairs[tid], kind, tri_indices, edge_indices)
    c = join_zones(label_out, idx[0], idx[1]) + join_zones(label_out, idx[0], idx[2]) + join_zones(label_out, idx[0], idx[3])
    if c > 0:
        changed_out[0] = 1


@wp.kernel(enable_backward=False)
def merge_sewn_points(seam_root: wp.array(dtype=wp.int32), label_out: wp.array(dtype=wp.int32), changed_out: wp.array(dtype=wp.int32)):
    """A welded sewn point with a particle in a zone joins it whole (each particle with its point's root)."""
    i = wp.tid()
    r = seam_root[i]
    if r < 0 or r == i:
        return
    n = label_out.shape[0]
    if in_zone(label_out[i], n) or in_zone(label_out[r], n):
        if join_zones(label_out, i, r) > 0:
            changed_out[0] = 1


@wp.kernel(enable_backward=False)
def follow_zone_names(label_out: wp.array(dtype=wp.int32), changed_out: wp.array(dtype=wp.int32)):
    """Pointer jumping: a member's label takes its label's label."""
    i = wp.tid()
    z = label_out[i]
    if not in_zone(z, label_out.shape[0]):
        return
    zz = label_out[z]
    if zz < z:
        label_out[i] = zz
        changed_out[0] = 1


@wp.kernel(enable_backward=False)
def gather_zone_mass(
    label: wp.array(dtype=wp.int32),
    particle_mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    mass_out: wp.array(dtype=wp.float64),
    moment_out: wp.array(dtype=wp.vec3d),
    momentum_out: wp.array(dtype=wp.vec3d),
    pinned_out: wp.array(dtype=wp.int32),
    heaviest_out: wp.array(dtype=wp.float64),
):
    """Per zone: the free members' mass [kg], first moment sum m x and momentum sum m v; the pinned members' count
    and the heaviest member's mass."""
    i = wp.tid()
    z = label[i]
    if not in_zone(z, label.shape[0]):
        return
    m = wp.float64(particle_mass[i])
    wp.atomic_max(heaviest_out, z, m)
    if inv_mass[i] > 0.0:
        wp.atomic_add(mass_out, z, m)
        wp.atomic_add(moment_out, z, m * wp.vec3d(x[i]))
        wp.atomic_add(momentum_out, z, m * wp.vec3d(v[i]))
    else:
        wp.atomic_add(pinned_out, z, 1)


@wp.func
def pinned_zone_weight(free: bool, m: wp.float64, heaviest: wp.float64):
    """A member's weight in the fit of a zone with pinned members: its mass, or (pinned) a million times the heaviest."""
    if free:
        return m
    return wp.float64(1.0e6) * wp.max(heaviest, wp.float64(1.0e-12))


@wp.kernel(enable_backward=False)
def gather_zone_moments(
    label: wp.array(dtype=wp.int32),
    particle_mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    mass: wp.array(dtype=wp.float64),
    moment: wp.array(dtype=wp.vec3d),
    momentum: wp.array(dtype=wp.vec3d),
    pinned: wp.array(dtype=wp.int32),
    heaviest: wp.array(dtype=wp.float64),
    angular_out: wp.array(dtype=wp.vec3d),
    inertia_out: wp.array(dtype=wp.mat33d),
    weight_out: wp.array(dtype=wp.float64),
    start_out: wp.array(dtype=wp.vec3d),
    end_out: wp.array(dtype=wp.vec3d),
):
    """A zone of free particles: its angular momentum and inertia tensor about the centre of mass. A zone with pinned
    members: the weights and weighted sums of its members' start and end points (x, x + dt v) for the rigid fit."""
    i = wp.tid()
    z = label[i]
    if not in_zone(z, label.shape[0]) or mass[z] == wp.float64(0.0):
        return
    m = wp.float64(particle_mass[i])
    xi = wp.vec3d(x[i])
    vi = wp.vec3d(v[i])
    if pinned[z] == 0:
        r = xi - moment[z] / mass[z]
        wp.atomic_add(angular_out, z, m * wp.cross(r, vi - momentum[z] / mass[z]))
        wp.atomic_add(inertia_out, z, m * (wp.dot(r, r) * wp.identity(n=3, dtype=wp.float64) - wp.outer(r, r)))
    else:
        w = pinned_zone_weight(inv_mass[i] > 0.0, m, heaviest[z])
        wp.atomic_add(weight_out, z, w)
        wp.atomic_add(start_out, z, w * xi)
        wp.atomic_add(end_out, z, w * (xi + wp.float64(dt) * vi))


@wp.kernel(enable_backward=False)
def gather_zone_covariance(
    label: wp.array(dtype=wp.int32),
    particle_mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    mass: wp.array(dtype=wp.float64),
    pinned: wp.array(dtype=wp.int32),
    heaviest: wp.array(dtype=wp.float64),
    weight: wp.array(dtype=wp.float64),
    start: wp.array(dtype=wp.vec3d),
    end: wp.array(dtype=wp.vec3d),
    covariance_out: wp.array(dtype=wp.mat33d),
):
    """A zone with pinned members: the weighted covariance of its start and end points about their centres."""
    i = wp.tid()
    z = label[i]
    if not in_zone(z, label.shape[0]) or mass[z] == wp.float64(0.0) or pinned[z] == 0:
        return
    m = wp.float64(particle_mass[i])
    w = pinned_zone_weight(inv_mass[i] > 0.0, m, heaviest[z])
    xi = wp.vec3d(x[i])
    p = xi - start[z] / weight[z]
    q = xi + wp.float64(dt) * wp.vec3d(v[i]) - end[z] / weight[z]
    wp.atomic_add(covariance_out, z, w * wp.outer(p, q))


@wp.func
def rotation_of(omega: wp.vec3d, dt: float):
    """The rotation by the angle |omega| dt about omega (Rodrigues)."""
    angle = wp.length(omega) * wp.float64(dt)
    rot = wp.identity(n=3, dtype=wp.float64)
    if angle > wp.float64(0.0):
        k = wp.normalize(omega)
        kx = wp.skew(k)
        rot = rot + wp.sin(angle) * kx + (wp.float64(1.0) - wp.cos(angle)) * (kx * kx)
    return rot


@wp.kernel(enable_backward=False)
def solve_zone_motion(
    label: wp.array(dtype=wp.int32),
    dt: float,
    mass: wp.array(dtype=wp.float64),
    moment: wp.array(dtype=wp.vec3d),
    momentum: wp.array(dtype=wp.vec3d),
    pinned: wp.array(dtype=wp.int32),
    angular: wp.array(dtype=wp.vec3d),
    inertia: wp.array(dtype=wp.mat33d),
    weight: wp.array(dtype=wp.float64),
    start: wp.array(dtype=wp.vec3d),
    end: wp.array(dtype=wp.vec3d),
    covariance: wp.array(dtype=wp.mat33d),
    rotation_out: wp.array(dtype=wp.mat33d),
    origin_out: wp.array(dtype=wp.vec3d),
    target_out: wp.array(dtype=wp.vec3d),
):
    """Per zone (its named particle's thread), the rigid step x -> target + R (x - origin) of its free members.
    Free zone: about the centre of mass x_c, target x_c + dt v_c, R the rotation by dt omega with omega the
    least-squares solution of I omega = L (singular values below 1e-12 of the largest dropped). Zone with pinned
    members: the weighted best rigid fit (Kabsch) of their start points to their end points; the pinned members,
    weighted a million times the heaviest, decide it where they can, the free members' motion what they leave open."""
    i = wp.tid()
    if label[i] != i or mass[i] == wp.float64(0.0):
        return
    U = wp.mat33d()
    s = wp.vec3d()
    V = wp.mat33d()
    if pinned[i] == 0:
        xc = moment[i] / mass[i]
        wp.svd3(inertia[i], U, s, V)
        b = wp.transpose(U) * angular[i]
        cutoff = wp.float64(1.0e-12) * wp.abs(s[0])
        c = wp.vec3d()
        for k in range(3):
            if wp.abs(s[k]) > cutoff and s[k] != wp.float64(0.0):
                c[k] = b[k] / s[k]
        rotation_out[i] = rotation_of(V * c, dt)
        origin_out[i] = xc
        target_out[i] = xc + wp.float64(dt) * momentum[i] / mass[i]
    else:
        wp.svd3(covariance[i], U, s, V)  # U, V rotations (the smallest singular value carries the sign)
        rotation_out[i] = V * wp.transpose(U)
        origin_out[i] = start[i] / weight[i]
        target_out[i] = end[i] / weight[i]


@wp.kernel(enable_backward=False)
def set_zone_motion(
    label: wp.array(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    x: wp.array(dtype=wp.vec3),
    dt: float,
    mass: wp.array(dtype=wp.float64),
    rotation: wp.array(dtype=wp.mat33d),
    origin: wp.array(dtype=wp.vec3d),
    target: wp.array(dtype=wp.vec3d),
    v_out: wp.array(dtype=wp.vec3),
):
    """The free members of a zone with free members take its rigid step's velocity (target + R (x - origin) - x) / dt;
    every other particle keeps v_out."""
    i = wp.tid()
    z = label[i]
    if not in_zone(z, label.shape[0]) or inv_mass[i] <= 0.0 or mass[z] == wp.float64(0.0):
        return
    xi = wp.vec3d(x[i])
    v_out[i] = wp.vec3((target[z] + rotation[z] * (xi - origin[z]) - xi) / wp.float64(dt))


@wp.kernel(enable_backward=False)
def detect_impacts_listed(
    count: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    zone: wp.array(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    vbar: wp.array(dtype=wp.vec3),
    dt: float,
    tolerance: float,
    separation_speed: float,
    dv_unused: wp.array(dtype=wp.vec3),
    weight_unused: wp.array(dtype=float),
    counts_unused: wp.array(dtype=wp.int32),
    hit_out: wp.array(dtype=wp.int32),
    counts_out: wp.array(dtype=wp.int32),
    zones_out: wp.array(dtype=wp.int32),
):
    """CCD without response on the first count[0] listed pairs (zones' own pairs skipped): each pair's hit flag, the
    impacts counted in zones_out[ZONE_HITS] and, after a merge (the first detection finds the last sweep's impacts
    again), in counts_out[COUNT_CCD] (capturable path; the impulse arrays and counts_unused are not read)."""
    tid = wp.tid()
    if tid >= count[0]:
        return
    hit = ccd_response(pairs[tid], kind, tri_indices, edge_indices, inv_mass, zone, x_start, vbar, dt, tolerance, separation_speed, 0,
                       dv_unused, weight_unused, counts_unused)
    hit_out[tid] = hit
    if hit != 0:
        wp.atomic_add(zones_out, ZONE_HITS, 1)
        if zones_out[ZONE_ROUND] > 0:
            wp.atomic_add(counts_out, COUNT_CCD, 1)


@wp.kernel(enable_backward=False)
def begin_zones(loop: wp.array(dtype=wp.int32), zones_out: wp.array(dtype=wp.int32)):
    """One thread after the CCD sweeps: impact zones start when the last sweep left impacts."""
    zones_out[ZONE_CONTINUE] = wp.where(loop[LOOP_HITS] > 0, 1, 0)
    zones_out[ZONE_ROUND] = 0
    zones_out[ZONE_HITS] = 0
    zones_out[ZONE_MERGE] = 0
    zones_out[ZONE_FINISH] = 0


@wp.kernel(enable_backward=False)
def end_zone_detection(zone_iterations: int, zones_out: wp.array(dtype=wp.int32), counts_out: wp.array(dtype=wp.int32)):
    """One thread after a detection on the zones: stop when no impact remains, or (counted unresolved) when
    `zone_iterations` merge rounds were done; otherwise merge again."""
    hits = zones_out[ZONE_HITS]
    done = zones_out[ZONE_ROUND]
    zones_out[ZONE_HITS] = 0
    if hits == 0 or done >= zone_iterations:
        zones_out[ZONE_CONTINUE] = 0
        zones_out[ZONE_MERGE] = 0
        zones_out[ZONE_FINISH] = 1
        if hits > 0:
            counts_out[COUNT_UNRESOLVED] = counts_out[COUNT_UNRESOLVED] + 1
    else:
        zones_out[ZONE_MERGE] = 1
        zones_out[ZONE_ROUND] = done + 1


@wp.kernel(enable_backward=False)
def finish_zones(label_out: wp.array(dtype=wp.int32), counts_out: wp.array(dtype=wp.int32)):
    """Count the step's zones and their particles, and clear the labels (ZONE_NONE) for the next step."""
    i = wp.tid()
    z = label_out[i]
    if not in_zone(z, label_out.shape[0]):
        return
    wp.atomic_add(counts_out, COUNT_ZONE_PARTICLES, 1)
    if z == i:
        wp.atomic_add(counts_out, COUNT_ZONES, 1)
    label_out[i] = ZONE_NONE


@wp.kernel(enable_backward=False)
def set_flag(value: int, flag_out: wp.array(dtype=wp.int32)):
    """One thread: flag_out[0] = value."""
    flag_out[0] = value
