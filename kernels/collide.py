"""Cloth-collider contact: signed distances of the collider shapes, continuous detection along the
step's relative trajectory, and the inelastic response with Coulomb friction (Bridson et al. 2002).

Every shape is described in its own frame (``wp.transform`` world <- local):

* plane: the half-space z <= 0 (outward normal +z);
* sphere: radius ``size[0]`` about the origin;
* capsule: radius ``size[0]`` around the segment z in [-size[1], size[1]];
* box: half extents ``size``;
* cylinder: radius ``size[0]``, z in [-size[1], size[1]] (flat caps);
* mesh: a ``wp.Mesh`` in local coordinates (signed by the nearest face's normal, or at an edge or a corner by the
  angle-weighted pseudo normal: watertight meshes are solid; an open mesh is solid behind its triangles' winding).

A particle is in contact with a collider when its distance to the surface is below the collider's
`thickness`. The response acts on the step's average velocity vbar = (x_end - x_start) / h and on the
end velocity (physics.md 3(f)): the normal part of vbar relative to the collider gains what puts the
end point back at the thickness; the end velocity keeps no approaching normal component (inelastic,
dv_N = the approach speed removed); both tangential parts get Coulomb friction, ``v_T <- 0`` if
``|v_T| <= mu_s dv_N`` else ``(1 - mu_k dv_N / |v_T|) v_T``. Nothing adds energy: relative normal
speeds only shrink, tangential speeds only shrink.
"""

import warp as wp

from .selfcollide import closest_point_triangle

SHAPE_PLANE = wp.constant(0)
SHAPE_SPHERE = wp.constant(1)
SHAPE_CAPSULE = wp.constant(2)
SHAPE_BOX = wp.constant(3)
SHAPE_CYLINDER = wp.constant(4)
SHAPE_MESH = wp.constant(5)

TRACE_STEPS = wp.constant(48)
# Two surfaces pinch a particle between them when they face each other within this angle's cosine (45 degrees): an
# armpit's or a fold's two sides, not an open corner (the particle leaves that along the bisector).
PINCH_COSINE = wp.constant(0.7)
# How far [x the thickness] along the normal a facing surface is sought: one farther cannot pinch (pinched needs
# c g / (1 + c) < thickness, so a gap g < thickness (1 + c) / c <= 2.43 thickness).
PINCH_REACH = wp.constant(2.5)
DISTANCE_EPS = wp.constant(1.0e-9)
# A mesh's nearest point is inside a face (not on an edge or a corner) when its barycentric weights all pass this.
FACE_INTERIOR = wp.constant(1.0e-6)
# The colliders pass resolves a particle that comes within this fraction of the thickness inside it (its contact band;
# kernels/contact.py admit_collider_contacts admits into the solve the particles the pass would resolve).
CONTACT_BAND = wp.constant(1.0e-3)
# The colliders pass pushes a particle out of a mesh collider at most this many times (each from the face nearest to
# it then: a concave crease's two sides, or three at a corner).
END_PUSHES = wp.constant(3)

# Indices into the counters array of a collision pass.
COUNT_COLLIDER_CONTACTS = wp.constant(0)
COUNT_COLLIDER_CCD = wp.constant(1)
COUNT_COLLIDER_SAMPLES = wp.constant(2)


@wp.func
def shape_distance(shape: int, size: wp.vec3, mesh: wp.uint64, max_distance: float, p: wp.vec3):
    """Signed distance [m] from the local point p to the shape's surface (negative inside) and the
    outward unit normal of the nearest surface point."""
    up = wp.vec3(0.0, 0.0, 1.0)
    if shape == SHAPE_PLANE:
        return p[2], up
    if shape == SHAPE_SPHERE:
        r = wp.length(p)
        if r < DISTANCE_EPS:
            return -size[0], up
        return r - size[0], p / r
    if shape == SHAPE_CAPSULE:
        d = p - wp.vec3(0.0, 0.0, wp.clamp(p[2], -size[1], size[1]))
        r = wp.length(d)
        if r < DISTANCE_EPS:
            return -size[0], wp.vec3(1.0, 0.0, 0.0)
        return r - size[0], d / r
    if shape == SHAPE_BOX:
        q = wp.vec3(wp.abs(p[0]) - size[0], wp.abs(p[1]) - size[1], wp.abs(p[2]) - size[2])
        s = wp.vec3(wp.sign(p[0]), wp.sign(p[1]), wp.sign(p[2]))
        outside = wp.vec3(wp.max(q[0], 0.0), wp.max(q[1], 0.0), wp.max(q[2], 0.0))
        lo = wp.length(outside)
        if lo > 0.0:
            return lo, wp.cw_mul(s, outside) / lo
        # inside: the nearest face
        if q[0] >= q[1] and q[0] >= q[2]:
            return q[0], wp.vec3(s[0], 0.0, 0.0)
        if q[1] >= q[2]:
            return q[1], wp.vec3(0.0, s[1], 0.0)
        return q[2], wp.vec3(0.0, 0.0, s[2])
    if shape == SHAPE_CYLINDER:
        rho = wp.sqrt(p[0] * p[0] + p[1] * p[1])
        radial = wp.vec3(1.0, 0.0, 0.0)
        if rho > DISTANCE_EPS:
            radial = wp.vec3(p[0] / rho, p[1] / rho, 0.0)
        axial = wp.vec3(0.0, 0.0, wp.sign(p[2]))
        dr = rho - size[0]
        dz = wp.abs(p[2]) - size[1]
        if dr > 0.0 or dz > 0.0:
            a = wp.max(dr, 0.0)
            b = wp.max(dz, 0.0)
            dist = wp.sqrt(a * a + b * b)
            return dist, (a * radial + b * axial) / dist
        if dr > dz:
            return dr, radial
        return dz, axial
    # SHAPE_MESH
    query = wp.mesh_query_point_sign_normal(mesh, p, max_distance, 1.0e-3)
    if not query.result:
        return max_distance, up
    closest = wp.mesh_eval_position(mesh, query.face, query.u, query.v)
    d = p - closest
    r = wp.length(d)
    if r < 1.0e-7:
        return 0.0, wp.mesh_eval_face_normal(mesh, query.face)
    # The query's pseudo-normal sums the normals of every face within a tie band (1e-3 of the mesh's mean edge) of the
    # nearest, and halfway between two facing surfaces (a particle pinched in an armpit, a slot) those cancel: the
    # sign came out at random. Nearest to a face's interior, that face's own normal signs it exactly; nearest to an
    # edge or a corner, the point halfway to it has the same sign (every point between a point and its nearest has
    # that nearest) and no tie with the facing surface (at least twice as far).
    sign = float(0.0)
    if wp.min(wp.min(query.u, query.v), 1.0 - query.u - query.v) > FACE_INTERIOR:
        sign = wp.sign(wp.dot(d, wp.mesh_eval_face_normal(mesh, query.face)))
    else:
        sign = wp.mesh_query_point_sign_normal(mesh, closest + 0.5 * d, max_distance, 1.0e-3).sign
    return sign * r, sign * d / r


@wp.func
def pinch_height(collider_count: int, collider_shape: wp.array(dtype=wp.int32), collider_size: wp.array(dtype=wp.vec3),
                 collider_mesh: wp.array(dtype=wp.uint64), collider_deforming: wp.array(dtype=wp.int32), max_distance: float,
                 collider_transform: wp.array(dtype=wp.transform), x: wp.vec3, n: wp.vec3, d: float, thickness: float, dt: float):
    """Where a particle at x, distance d [m] above a contact's surface along its outward unit normal n (world), is
    pinched: a surface faces that one across a crease (the other side of a body's armpit, another collider), within
    PINCH_REACH x `thickness` [m] along n and turned towards it (cosine c = -n . n2 > PINCH_COSINE). Returns the height
    s [m] above the contact's surface at which the particle is as far from both, s = c g / (1 + c) with g = d + t the
    gap along n (t: the distance along n to the other surface, a mesh's by a ray, an analytic shape's by its tangent
    plane), the least over the colliders, and the outward unit normal (world) of the surface that gives it (zero where
    none faces it, s then that reach). The particle is pinched where s is below the thickness. A mesh deforming over
    the step (`dt` > 0, its surface in the end shape) is queried at x carried along by its motion, as
    `collide_colliders` does."""
    reach = PINCH_REACH * thickness
    height = reach
    facing = wp.vec3(0.0)
    for c in range(collider_count):
        shape = collider_shape[c]
        mesh = collider_mesh[c]
        to_local = wp.transform_inverse(collider_transform[c])
        p = wp.transform_point(to_local, x)
        direction = wp.transform_vector(to_local, n)
        if shape == SHAPE_MESH and collider_deforming[c] != 0 and dt > 0.0:
            p = p + dt * mesh_surface_velocity(mesh, max_distance, p)
        cosine = float(0.0)
        gap = float(0.0)
        other = wp.vec3(0.0)  # (local)
        if shape == SHAPE_MESH:
            query = wp.mesh_query_ray(mesh, p, direction, reach)
            if query.result and query.t > 0.0:
                other = query.normal
                cosine = -wp.dot(direction, other)
                gap = d + query.t
        else:
            d_other, n_other = shape_distance(shape, collider_size[c], mesh, max_distance, p)
            other = n_other
            cosine = -wp.dot(direction, n_other)
            if cosine > PINCH_COSINE and d_other >= 0.0:
                gap = d + d_other / cosine
            else:
                cosine = 0.0
        if cosine > PINCH_COSINE and cosine * gap / (1.0 + cosine) < height:
            height = cosine * gap / (1.0 + cosine)
            facing = wp.transform_vector(collider_transform[c], other)
    return height, facing


@wp.func
def mesh_surface_velocity(mesh: wp.uint64, max_distance: float, p: wp.vec3):
    """Velocity [m/s] (local frame) of a deforming mesh's surface at its point nearest to p (zero when none)."""
    query = wp.mesh_query_point_sign_normal(mesh, p, max_distance, 1.0e-3)
    if not query.result:
        return wp.vec3(0.0)
    return wp.mesh_eval_velocity(mesh, query.face, query.u, query.v)


@wp.func
def surface_velocity(deforming: int, mesh: wp.uint64, max_distance: float, t_start: wp.transform, t_end: wp.transform,
                     p: wp.vec3, inv_dt: float):
    """World velocity [m/s] of the collider's surface point at local p: the rigid motion from t_start to
    t_end, plus, for a deforming mesh, its vertices' interpolated velocity there."""
    u = (wp.transform_point(t_end, p) - wp.transform_point(t_start, p)) * inv_dt
    if deforming != 0:
        u = u + wp.transform_vector(t_end, mesh_surface_velocity(mesh, max_distance, p))
    return u


@wp.func
def first_contact(shape: int, size: wp.vec3, mesh: wp.uint64, max_distance: float, p_start: wp.vec3, p_end: wp.vec3,
                  thickness: float, tolerance: float):
    """Earliest fraction t in [0, 1] of the segment p_start -> p_end whose distance to the shape is
    within `thickness` (+ `tolerance`), by sphere tracing (exact for these distance functions: a step never
    jumps over the surface). Returns (1, t) on a hit, (0, 1) when the segment stays clear (or the trace
    has not reached the end after TRACE_STEPS; the end point is still checked by the caller)."""
    seg = p_end - p_start
    seg_len = wp.length(seg)
    t = float(0.0)
    hit = int(0)
    k = int(0)
    while k < TRACE_STEPS:
        dist, n = shape_distance(shape, size, mesh, max_distance, p_start + t * seg)
        gap = dist - thickness
        if gap <= tolerance:
            hit = 1
            k = TRACE_STEPS
        elif seg_len < DISTANCE_EPS:
            k = TRACE_STEPS
        else:
            t = t + gap / seg_len
            if t > 1.0:
                t = 1.0
                k = TRACE_STEPS
        k += 1
    if hit == 0:
        t = 1.0
    return hit, t


@wp.func
def friction_factor(tangential_speed: float, normal_speed_change: float, static_friction: float, kinetic_friction: float):
    """Velocity-level Coulomb friction as a factor on the tangential velocity: 0 (stick) when
    |v_T| <= mu_s dv_N, else 1 - mu_k dv_N / |v_T| (Bridson et al. 2002, physics.md 3(f))."""
    if tangential_speed <= static_friction * normal_speed_change:
        return 0.0
    return 1.0 - kinetic_friction * normal_speed_change / tangential_speed


@wp.func
def contact_response(vbar: wp.vec3, v_end: wp.vec3, surface_velocity: wp.vec3, n: wp.vec3, push: float,
                     static_friction: float, kinetic_friction: float):
    """New (average velocity, end velocity) after a contact with unit normal n.

    push >= 0 [m/s] is the normal average velocity (relative to the surface) the end point needs to get
    back to the thickness. The friction's dv_N is the approach speed the contact removes from the end
    velocity, -min(v_N, 0): taken from velocities, not from position differences, so that it is exact
    in float32 at small steps (a resting particle's per-step penetration is only g h^2). The same
    stick / slide factor scales the tangential parts of both velocities.
    """
    er = v_end - surface_velocity
    en = wp.dot(er, n)
    et = er - en * n
    dvn = wp.max(-en, 0.0)
    factor = friction_factor(wp.length(et), dvn, static_friction, kinetic_friction)
    rel = vbar - surface_velocity
    rn = wp.dot(rel, n)
    vbar_new = surface_velocity + (rn + push) * n + factor * (rel - rn * n)
    v_new = surface_velocity + wp.max(en, 0.0) * n + factor * et
    return vbar_new, v_new


@wp.kernel
def collide_colliders(
    # Model
    particle_pinned: wp.array(dtype=wp.int32),
    collider_count: int,
    collider_shape: wp.array(dtype=wp.int32),
    collider_size: wp.array(dtype=wp.vec3),
    collider_mesh: wp.array(dtype=wp.uint64),
    collider_deforming: wp.array(dtype=wp.int32),
    collider_thickness: wp.array(dtype=float),
    collider_static_friction: wp.array(dtype=float),
    collider_kinetic_friction: wp.array(dtype=float),
    mesh_max_distance: float,
    # Control: collider poses at the start and the end of the step
    collider_transform_start: wp.array(dtype=wp.transform),
    collider_transform_end: wp.array(dtype=wp.transform),
    # State: start of step, candidate end of step
    x_start: wp.array(dtype=wp.vec3),
    x_end: wp.array(dtype=wp.vec3),
    v_end: wp.array(dtype=wp.vec3),
    dt: float,
    pinch: int,
    # outputs
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    counts_out: wp.array(dtype=wp.int32),
):
    """Resolve every free particle against every collider, colliders in order (see the module docstring).

    Per collider: trace the particle's path relative to the collider (start point in the start pose, end
    point in the end pose). If it was clear at the start and touches on the way, or was touching at the
    start and the path crosses the solid, take the tangent plane at the first touch and push the end point
    onto it (offset by the thickness) with friction. Then, if the end point is within the thickness
    (resting and sliding contact, curved or concave surfaces), push it out along the surface normal
    there; on a mesh, again from the face then nearest while it is still within the thickness (a concave crease's
    other side: at most END_PUSHES pushes, those after the first along the normal alone), so that a second pass finds
    nothing to push. A particle that slides off an edge is therefore let go, not held up on the face's plane.
    With `pinch` (the implicit solve's contacts in it), a particle pinched between two surfaces facing each other
    closer than twice the thickness (an armpit's crease, `pinch_height`) is pushed out only to where it is as far from
    both, where the solve lands it: pushed to the thickness, it would be pushed into the other, and back out of it by
    the next step.
    A deforming mesh is tested in its end-of-step shape: the start point is first carried along by the
    surface's motion there (its vertex velocities x dt), and contacts take the surface's velocity.
    """
    i = wp.tid()
    xs = x_start[i]
    xe = x_end[i]
    ve = v_end[i]
    if particle_pinned[i] != 0:
        x_out[i] = xe
        v_out[i] = ve
        return
    inv_dt = 1.0 / dt
    for c in range(collider_count):
        shape = collider_shape[c]
        size = collider_size[c]
        mesh = collider_mesh[c]
        thickness = collider_thickness[c]
        mu_s = collider_static_friction[c]
        mu_k = collider_kinetic_friction[c]
        t_start = collider_transform_start[c]
        t_end = collider_transform_end[c]
        deforming = collider_deforming[c]
        ps = wp.transform_point(wp.transform_inverse(t_start), xs)
        pe = wp.transform_point(wp.transform_inverse(t_end), xe)
        if deforming != 0:
            ps = ps + dt * mesh_surface_velocity(mesh, mesh_max_distance, ps)
        tolerance = CONTACT_BAND * thickness + 1.0e-7
        end_dist0, end_n0 = shape_distance(shape, size, mesh, mesh_max_distance, pe)
        hit, t = first_contact(shape, size, mesh, mesh_max_distance, ps, pe, thickness, tolerance)
        touched = int(0)
        plane = int(0)
        if hit != 0:
            if t > 0.0:
                # Clear at the start, touching on the way: the swept (CCD) case when the path goes on into
                # the solid: the end point is clear again behind it (a thin collider), or inside with the
                # normal turned away from the first touch's. A path that only grazes a corner or a curved
                # surface is left to the end-point pass (projecting onto the first touch's tangent plane
                # would hold cloth out sideways at a corner and stretch it).
                touch_dist, touch_n = shape_distance(shape, size, mesh, mesh_max_distance, ps + t * (pe - ps))
                if end_dist0 >= thickness:
                    back_hit, back_t = first_contact(shape, size, mesh, mesh_max_distance, pe, ps, thickness, tolerance)
                    mid = ps + 0.5 * (t + 1.0 - back_t) * (pe - ps)
                    mid_dist, mid_n = shape_distance(shape, size, mesh, mesh_max_distance, mid)
                    if back_hit != 0 and mid_dist < thickness - wp.max(0.25 * thickness, tolerance):
                        plane = 1
                elif wp.dot(end_n0, touch_n) < 0.5:
                    plane = 1
            else:
                # In contact at the start. Resting or sliding contact is resolved at the end point below,
                # unless the relative path crosses the solid (a fast collider pushing the particle): then
                # the end point is clear again behind it, or deep inside with a flipped normal.
                start_dist, start_n = shape_distance(shape, size, mesh, mesh_max_distance, ps)
                if end_dist0 >= thickness:
                    back_hit, back_t = first_contact(shape, size, mesh, mesh_max_distance, pe, ps, thickness, tolerance)
                    if back_hit != 0:
                        # crossing only if the path between start and the back hit dips clearly below the
                        # band (a chord of a curved surface sags by a hair without crossing anything)
                        mid = ps + 0.5 * (1.0 - back_t) * (pe - ps)
                        mid_dist, mid_n = shape_distance(shape, size, mesh, mesh_max_distance, mid)
                        if mid_dist < thickness - wp.max(0.25 * thickness, tolerance):
                            plane = 1
                elif wp.dot(end_n0, start_n) < 0.0:
                    # (not when pinched: between two facing surfaces, the nearest changes sides without crossing anything)
                    across = thickness
                    if pinch != 0:
                        across, _facing = pinch_height(collider_count, collider_shape, collider_size, collider_mesh,
                                                       collider_deforming, mesh_max_distance, collider_transform_end, xe,
                                                       wp.transform_vector(t_end, end_n0), end_dist0, thickness, 0.0)
                    if across >= thickness:
                        plane = 1
        if plane != 0:
            pc = ps + t * (pe - ps)
            dist, nl = shape_distance(shape, size, mesh, mesh_max_distance, pc)
            gap = dist - thickness + wp.dot(pe - pc, nl)
            if gap < 0.0:
                n = wp.transform_vector(t_end, nl)
                u = surface_velocity(deforming, mesh, mesh_max_distance, t_start, t_end, pc, inv_dt)
                vbar, ve = contact_response((xe - xs) * inv_dt, ve, u, n, -gap * inv_dt, mu_s, mu_k)
                xe = xs + dt * vbar
                pe = wp.transform_point(wp.transform_inverse(t_end), xe)
                touched = 1
                if end_dist0 >= thickness:
                    # the end point alone would not have seen this contact: a continuous (CCD) catch
                    wp.atomic_add(counts_out, COUNT_COLLIDER_CCD, 1)
        # The end point within the thickness: pushed out along the normal at its nearest point. In a mesh's concave
        # crease (a body's shoulder meeting its torso) that can leave it within the thickness of the other side's face:
        # pushed again from there, up to END_PUSHES times, so that one pass leaves it clear of both and the next round
        # has nothing left to push (a second round pushing it from the other face undid the strain limiter's work).
        done = int(0)
        for k in range(END_PUSHES):  # (a static loop, unrolled: the taped kernel's adjoint follows it)
            if done == 0:
                dist_end, n_end = shape_distance(shape, size, mesh, mesh_max_distance, pe)
                pushed = int(0)
                # (a push after the first only beyond the contact band: not the last one's rounding again)
                if dist_end < thickness - float(wp.min(k, 1)) * tolerance:
                    n = wp.transform_vector(t_end, n_end)
                    height = thickness
                    if pinch != 0:
                        # pinched (a surface faces this one within twice the thickness): out only to where it is as far
                        # from both (less the tolerance: the solve lands it there, to rounding)
                        midway, _facing = pinch_height(collider_count, collider_shape, collider_size, collider_mesh,
                                                       collider_deforming, mesh_max_distance, collider_transform_end, xe, n,
                                                       dist_end, thickness, 0.0)
                        height = wp.min(thickness, midway - tolerance)
                    if dist_end < height:
                        u = surface_velocity(deforming, mesh, mesh_max_distance, t_start, t_end, pe, inv_dt)
                        vbar, ve = contact_response((xe - xs) * inv_dt, ve, u, n, (height - dist_end) * inv_dt, mu_s, mu_k)
                        if k == 0:
                            xe = xs + dt * vbar
                        else:
                            # out along this side's normal alone: its friction on the step's path would take back the
                            # push out of the side before (the end velocity takes it)
                            xe = xe + (height - dist_end) * n
                        pe = wp.transform_point(wp.transform_inverse(t_end), xe)
                        touched = 1
                        pushed = 1
                if pushed == 0 or shape != SHAPE_MESH:
                    done = 1
        if touched != 0:
            wp.atomic_add(counts_out, COUNT_COLLIDER_CONTACTS, 1)
    x_out[i] = xe
    v_out[i] = ve


# The colliders pass's element samples (points in the cloth's edges and triangles, cloth_warp/collision.py
# `sampled_elements`) found inside a mesh collider are pushed out to this fraction of its thickness. The particles are
# held at the thickness; an edge or a triangle between them sags toward a convex surface by about L^2 / (8 R) (1.6 mm
# for a 2.5 cm edge on a 5 cm arm, 3.8 mm for 3.5 cm on 4 cm), and a body mesh's ridge or corner pokes through it
# between its particles (the 3.5 cm T-shirt: a 15 cm shoulder edge through a garment triangle, a shoulder corner 0.3 mm
# from a triangle's centroid). A sample outside is left alone, however close: the implicit solve does not see the
# samples and pulls back what they push (held at a quarter of the thickness, a 3.3 cm cloth on a 4 cm mesh cylinder,
# which no element crossed, was kept moving at 63 mm/s instead of 3). Mesh colliders only (bodies): the 16^2 drape over
# the ball, whose 8.8 cm diagonals sag 3.9 mm and cut the ball at 19 samples a step, never rested with them (8-108 mm/s
# after 4 s). With the collider contacts in the solve, a particle a sample pushed keeps that height as a contact
# (SAMPLE_HOLD_SLACK below), which rests a coarse cloth over a faceted mesh ball (analytic shapes still have no samples).
SAMPLE_CLEARANCE = wp.constant(0.25)
# A particle the element samples pushed keeps the height over the mesh they left it at (`sample_height`) until it is
# farther than that by this many thicknesses: the implicit solve with collider contacts in it holds such a particle
# there as a contact (kernels/contact.py eval_collider_contacts) instead of letting the cloth carry it back to where its
# element sagged into the body and the samples pushed again (a T-shirt's shoulder particle pushed 1.14 mm out every
# other step; a coarse cloth over a faceted ball at 79-226 mm/s after 5 s: benchmarks/bench_sample_holds.py).
SAMPLE_HOLD_SLACK = wp.constant(0.5)


@wp.func
def edge_inside_middle(mesh: wp.uint64, a: wp.vec3, b: wp.vec3):
    """Where the segment a -> b (a mesh's local frame) runs inside the mesh: its first entry and the exit after it, found
    by following it as a ray from each end through the mesh's BVH. Returns (1, s), s the fraction of the way from a to
    the middle of that stretch, or (0, 0.5) when the segment does not enter and leave the mesh."""
    length = wp.length(b - a)
    if length <= DISTANCE_EPS:
        return int(0), 0.5
    d = (b - a) / length
    enter = wp.mesh_query_ray(mesh, a, d, length)
    if not enter.result or wp.dot(enter.normal, d) >= 0.0:
        return int(0), 0.5
    leave = wp.mesh_query_ray(mesh, b, -d, length)
    if not leave.result or wp.dot(leave.normal, d) <= 0.0 or length - leave.t <= enter.t:
        return int(0), 0.5
    return int(1), 0.5 * (enter.t + length - leave.t) / length


@wp.kernel
def collide_element_samples(
    # Model
    particle_pinned: wp.array(dtype=wp.int32),
    collider_count: int,
    collider_shape: wp.array(dtype=wp.int32),
    collider_mesh: wp.array(dtype=wp.uint64),
    collider_deforming: wp.array(dtype=wp.int32),
    collider_thickness: wp.array(dtype=float),
    mesh_max_distance: float,
    collider_transform_start: wp.array(dtype=wp.transform),
    collider_transform_end: wp.array(dtype=wp.transform),
    # the elements: an edge's two particles and -1, or a triangle's three
    elements: wp.array(dtype=wp.vec3i),
    # State: the particles' end of step (after the particle contacts), their end velocities
    x_end: wp.array(dtype=wp.vec3),
    v_end: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs: per particle, the weighted sums of the samples' position and velocity changes and the weights; whether any
    # sample pushed (the rounds' loop flag)
    dx_out: wp.array(dtype=wp.vec3),
    dv_out: wp.array(dtype=wp.vec3),
    pushes_out: wp.array(dtype=float),
    counts_out: wp.array(dtype=wp.int32),
    pushed_out: wp.array(dtype=wp.int32),
    sample_pushed_out: wp.array(dtype=wp.int32),
):
    """Each element's sample inside a mesh collider is moved out to SAMPLE_CLEARANCE x its thickness along the surface
    normal n by the least change of its particles (dx_k = w_k delta n / sum w_j^2; an element with a pinned or attached
    particle has no sample), and its end velocity relative to the surface loses its approaching normal part the same way
    (inelastic, no friction: the particles' own contacts carry that). An edge's sample is the middle of the stretch it
    runs inside the mesh (`edge_inside_middle`: a ridge that crosses it anywhere). A triangle's is its centroid or, when
    that lies within half the thickness, the point over a corner of the surface's nearest face poking through it,
    whichever is deeper (the 3.5 cm T-shirt's shoulder pole, 3-4.5 mm from a triangle's centroid and 0.04-0.18 mm
    through it: searches down the distance within the triangle passed beside it, the stretch inside being a fraction of
    a millimetre across); only surfaces within twice the thickness of the centroid are sought (a short search). Changes
    are summed per particle, each weighted by its length, with the weights (kernels/selfcollide.py
    `apply_velocity_changes` takes their weighted mean: a particle follows mostly its deepest sample). Each particle a
    sample pushes is marked in `sample_pushed_out` (see SAMPLE_HOLD_SLACK)."""
    s = wp.tid()
    idx = elements[s]
    for k in range(3):
        if idx[k] >= 0 and particle_pinned[idx[k]] != 0:
            # pinned or attached: where the user puts it, often on the body (pushed by its free particles alone, an
            # attached strap's element on a keyframed body threw them out at 77 m/s)
            return
    inv_dt = 1.0 / dt
    for c in range(collider_count):
        if collider_shape[c] == SHAPE_MESH:  # (see SAMPLE_CLEARANCE)
            mesh = collider_mesh[c]
            t_start = collider_transform_start[c]
            t_end = collider_transform_end[c]
            to_local = wp.transform_inverse(t_end)
            reach = 2.0 * collider_thickness[c]
            a = wp.transform_point(to_local, x_end[idx[0]])
            b = wp.transform_point(to_local, x_end[idx[1]])
            w = wp.vec3(0.0)
            dist = reach
            nl = wp.vec3(0.0)
            if idx[2] < 0:
                crossing, along = edge_inside_middle(mesh, a, b)
                if crossing != 0:
                    w = wp.vec3(1.0 - along, along, 0.0)
                    dist, nl = shape_distance(SHAPE_MESH, wp.vec3(0.0), mesh, mesh_max_distance, a + along * (b - a))  # (however deep)
            else:
                cl = wp.transform_point(to_local, x_end[idx[2]])
                w = wp.vec3(1.0 / 3.0)
                dist, nl = shape_distance(SHAPE_MESH, wp.vec3(0.0), mesh, reach, (a + b + cl) / 3.0)  # (reach: none nearer)
                if dist < 0.5 * collider_thickness[c]:  # (farther, its triangle is clear: sagging no more than that)
                    # a corner of the surface's face nearest the centroid poking through the triangle: beyond its plane
                    # (outward: the surface's normal there), over its inside
                    query = wp.mesh_query_point_sign_normal(mesh, (a + b + cl) / 3.0, reach, 1.0e-3)
                    face = wp.cross(b - a, cl - a)
                    if query.result and wp.length(face) > DISTANCE_EPS:
                        out = wp.normalize(face)
                        if wp.dot(out, nl) < 0.0:
                            out = -out
                        for k in range(3):
                            corner = wp.mesh_eval_position(mesh, query.face, wp.where(k == 0, 1.0, 0.0),
                                                           wp.where(k == 1, 1.0, 0.0))
                            height = wp.dot(corner - a, out)
                            wk = closest_point_triangle(corner, a, b, cl)
                            if height > 0.0 and -height < dist and wp.min(wk) > FACE_INTERIOR:
                                w = wk
                                dist = -height
                                nl = out
            if dist < 0.0:
                v = wp.vec3(0.0)
                for k in range(3):
                    if idx[k] >= 0:
                        v = v + w[k] * v_end[idx[k]]
                norm = wp.dot(w, w)
                if norm > 0.0:
                    n = wp.transform_vector(t_end, nl)
                    moved = (SAMPLE_CLEARANCE * collider_thickness[c] - dist) * n
                    pl = w[0] * a + w[1] * b
                    if idx[2] >= 0:
                        pl = pl + w[2] * wp.transform_point(to_local, x_end[idx[2]])
                    u = surface_velocity(collider_deforming[c], mesh, mesh_max_distance, t_start, t_end, pl, inv_dt)
                    stopped = wp.max(-wp.dot(v - u, n), 0.0) * n
                    for k in range(3):
                        if idx[k] >= 0 and w[k] > 0.0:
                            # weighted by its length: a particle takes mostly its deepest sample's push
                            push = (w[k] / norm) * moved
                            weight = wp.length(push)
                            wp.atomic_add(dx_out, idx[k], weight * push)
                            wp.atomic_add(dv_out, idx[k], (weight * w[k] / norm) * stopped)
                            wp.atomic_add(pushes_out, idx[k], weight)
                            sample_pushed_out[idx[k]] = 1
                    wp.atomic_add(counts_out, COUNT_COLLIDER_SAMPLES, 1)
                    pushed_out[0] = 1


@wp.kernel(enable_backward=False)
def hold_sample_heights(
    collider_count: int,
    collider_shape: wp.array(dtype=wp.int32),
    collider_mesh: wp.array(dtype=wp.uint64),
    collider_thickness: wp.array(dtype=float),
    mesh_max_distance: float,
    collider_transform_end: wp.array(dtype=wp.transform),
    x: wp.array(dtype=wp.vec3),
    sample_pushed: wp.array(dtype=wp.int32),
    sample_height_out: wp.array(dtype=float),
):
    """Per particle, at `x` (the end of the step): one the element samples pushed (`sample_pushed`) keeps its height [m]
    over the nearest mesh collider in `sample_height_out`; one they left alone keeps the height it has there until it
    is farther from every mesh than that by SAMPLE_HOLD_SLACK thicknesses, then none (0)."""
    i = wp.tid()
    held = sample_height_out[i]
    if sample_pushed[i] == 0 and held <= 0.0:
        return
    nearest = float(mesh_max_distance)
    slack = float(0.0)
    for c in range(collider_count):
        if collider_shape[c] == SHAPE_MESH:
            d, n = world_distance(SHAPE_MESH, wp.vec3(0.0), collider_mesh[c], mesh_max_distance, collider_transform_end[c], x[i])
            if d < nearest:
                nearest = d
                slack = SAMPLE_HOLD_SLACK * collider_thickness[c]
    if sample_pushed[i] != 0:
        if nearest > 0.0 and nearest < mesh_max_distance:
            sample_height_out[i] = nearest
    elif nearest > held + slack:
        sample_height_out[i] = 0.0


@wp.kernel
def next_sample_round(rounds: int, loop_out: wp.array(dtype=wp.int32)):
    """After a round of the element samples: loop_out[1] counts it; loop_out[0] says whether another runs (this one
    pushed a sample, loop_out[2], and fewer than `rounds` ran); loop_out[2] is cleared for the next."""
    loop_out[1] = loop_out[1] + 1
    more = int(0)
    if loop_out[2] != 0 and loop_out[1] < rounds:
        more = 1
    loop_out[0] = more
    loop_out[2] = 0


@wp.func
def world_distance(shape: int, size: wp.vec3, mesh: wp.uint64, max_distance: float, transform: wp.transform, x: wp.vec3):
    """Signed distance [m] of the world point x to a collider's surface in its pose `transform` (world <- local) and the
    outward unit normal there (world)."""
    d, n = shape_distance(shape, size, mesh, max_distance, wp.transform_point(wp.transform_inverse(transform), x))
    return d, wp.transform_vector(transform, n)


@wp.kernel(enable_backward=False)
def eval_collider_distance(
    collider: int,
    collider_shape: wp.array(dtype=wp.int32),
    collider_size: wp.array(dtype=wp.vec3),
    collider_mesh: wp.array(dtype=wp.uint64),
    mesh_max_distance: float,
    collider_transform: wp.array(dtype=wp.transform),
    x: wp.array(dtype=wp.vec3),
    # outputs
    distance_out: wp.array(dtype=float),
    normal_out: wp.array(dtype=wp.vec3),
):
    """Signed distance [m] of world points to one collider's surface and the outward normal (world)."""
    i = wp.tid()
    d, n = world_distance(collider_shape[collider], collider_size[collider], collider_mesh[collider], mesh_max_distance,
                          collider_transform[collider], x[i])
    distance_out[i] = d
    normal_out[i] = n


LIMIT_CONTACT_REACH = wp.constant(1.0)
"""How far beyond a collider's thickness, in thicknesses, a particle counts as touching it for the strain limiter."""


@wp.kernel(enable_backward=False)
def eval_limit_contacts(
    particle_pinned: wp.array(dtype=wp.int32),
    collider_count: int,
    collider_shape: wp.array(dtype=wp.int32),
    collider_size: wp.array(dtype=wp.vec3),
    collider_mesh: wp.array(dtype=wp.uint64),
    collider_thickness: wp.array(dtype=float),
    mesh_max_distance: float,
    collider_transform: wp.array(dtype=wp.transform),
    x: wp.array(dtype=wp.vec3),
    # outputs
    collider_out: wp.array(dtype=wp.int32),
    normal_out: wp.array(dtype=wp.vec3),
):
    """The collider each free particle touches, for the strain limiter: the one whose surface it is nearest relative to
    the thickness, when outside the solid and within (1 + LIMIT_CONTACT_REACH) thicknesses of it (-1 for none), and
    its outward normal there (world; zero for none), as `eval_limit_contact_normals` gives it (whose adjoint a taped
    limiter runs)."""
    i = wp.tid()
    touched = int(-1)
    normal = wp.vec3(0.0)
    if particle_pinned[i] == 0:
        best = LIMIT_CONTACT_REACH
        for c in range(collider_count):
            d, n = world_distance(collider_shape[c], collider_size[c], collider_mesh[c], mesh_max_distance, collider_transform[c], x[i])
            gap = d / wp.max(collider_thickness[c], DISTANCE_EPS) - 1.0
            if d > 0.0 and gap < best:  # inside the solid: left to the colliders pass (and a dressing), as it traces it
                best = gap
                touched = c
                normal = n
    collider_out[i] = touched
    normal_out[i] = normal


@wp.kernel
def eval_limit_contact_normals(
    contact_collider: wp.array(dtype=wp.int32),
    collider_shape: wp.array(dtype=wp.int32),
    collider_size: wp.array(dtype=wp.vec3),
    collider_mesh: wp.array(dtype=wp.uint64),
    mesh_max_distance: float,
    collider_transform: wp.array(dtype=wp.transform),
    x: wp.array(dtype=wp.vec3),
    # outputs
    normal_out: wp.array(dtype=wp.vec3),
):
    """The outward normal (world) at x of the collider each particle touches (`eval_limit_contacts`), zero for none
    (kernels/constraints.py `limit_split`). Differentiable in x with the contacts held fixed (a curved surface's normal
    turns with the point; the choice, a loop over the colliders, is a kernel of its own: Warp's adjoint does not carry
    what a dynamic loop chose)."""
    i = wp.tid()
    c = contact_collider[i]
    if c < 0:
        normal_out[i] = wp.vec3(0.0)
    else:
        d, n = world_distance(collider_shape[c], collider_size[c], collider_mesh[c], mesh_max_distance, collider_transform[c], x[i])
        normal_out[i] = n


EDGE_CROSSING_HITS = wp.constant(8)  # the most triangles one edge's ray is followed through (those at its own ends skipped)


@wp.kernel(enable_backward=False)
def find_edge_crossings(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), edges: wp.array(dtype=wp.vec2i),
                        tri_indices: wp.array(dtype=wp.int32), vertex_root: wp.array(dtype=wp.int32),
                        edge_root: wp.array(dtype=wp.int32), crossed_out: wp.array2d(dtype=wp.int32)):
    """The triangles of `mesh` (its vertex indices `tri_indices`) that each edge (of `points`: the mesh's own, or another
    surface's) crosses, the triangle touching neither end of the edge (two surfaces, or one and itself, intersect iff
    an edge of one crosses a triangle of the other): each edge is followed as a ray from end to end through the mesh's
    BVH, up to EDGE_CROSSING_HITS triangles. An edge's end touches a triangle when its `edge_root` is one of the
    triangle's vertices' `vertex_root` (a cloth's own edges: the same array, a sewn point's particles one vertex, the
    smallest particle it is sewn to; another surface's: roots that match none). One thread per edge; crossed_out[e]
    (edges, EDGE_CROSSING_HITS) gets the faces it crosses in the order met along it, -1 after the last."""
    e = wp.tid()
    for k in range(EDGE_CROSSING_HITS):
        crossed_out[e, k] = -1
    a = edges[e][0]
    b = edges[e][1]
    p = points[a]
    length = wp.length(points[b] - p)
    if length <= 0.0:
        return
    d = (points[b] - p) / length
    ra = edge_root[a]
    rb = edge_root[b]
    t = float(0.0)
    found = int(0)
    for _ in range(EDGE_CROSSING_HITS):
        query = wp.mesh_query_ray(mesh, p + t * d, d, length - t)
        if not query.result:
            return
        f = query.face
        r0 = vertex_root[tri_indices[3 * f]]
        r1 = vertex_root[tri_indices[3 * f + 1]]
        r2 = vertex_root[tri_indices[3 * f + 2]]
        touches = r0 == ra or r1 == ra or r2 == ra or r0 == rb or r1 == rb or r2 == rb
        if not touches:
            crossed_out[e, found] = f
            found += 1
        t = t + query.t + 1.0e-6 * length
        if t >= length:
            return


@wp.kernel(enable_backward=False)
def mesh_signed_distance(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_distance: float,
                         distance_out: wp.array(dtype=float)):
    """Signed distance [m] of each point to a closed mesh (negative inside), inside by the generalised winding number:
    a mesh of overlapping closed parts (a ball-jointed body) counts as their union (the mesh built with
    ``support_winding_number``, else Warp signs by rays). `max_distance` where none is near."""
    i = wp.tid()
    p = points[i]
    query = wp.mesh_query_point_sign_winding_number(mesh, p, max_distance, 2.0, 0.5)
    if not query.result:
        distance_out[i] = max_distance
        return
    distance_out[i] = query.sign * wp.length(p - wp.mesh_eval_position(mesh, query.face, query.u, query.v))


@wp.kernel(enable_backward=False)
def mesh_inner_thickness(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3), max_distance: float,
                         thickness_out: wp.array(dtype=float)):
    """How far [m] a closed mesh (one closed part of a body) extends inward from each of its vertices along the inward
    normal: the distance to the surface met first from just inside; `max_distance` where none is."""
    i = wp.tid()
    n = normals[i]
    start = points[i] - 1.0e-5 * n
    query = wp.mesh_query_ray(mesh, start, -n, max_distance)
    thickness_out[i] = max_distance
    if query.result:
        thickness_out[i] = query.t


@wp.kernel(enable_backward=False)
def mesh_closest_points(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_distance: float,
                        face_out: wp.array(dtype=wp.int32), weights_out: wp.array(dtype=wp.vec3)):
    """Per point, the closest point of a mesh (open or closed) within `max_distance` [m]: its triangle (-1: none that
    near) and the barycentric weights of the triangle's three corners."""
    i = wp.tid()
    query = wp.mesh_query_point_no_sign(mesh, points[i], max_distance)
    face_out[i] = -1
    if query.result:
        face_out[i] = query.face
        weights_out[i] = wp.vec3(query.u, query.v, 1.0 - query.u - query.v)
