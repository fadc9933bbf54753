"""Collider contacts for the implicit solve: which particles touch a collider at the start of a step, along
which normal, and what end-of-step normal velocity puts them at the collider's thickness (Baraff & Witkin 1998,
physics.md 3(c): contacts as constraints of the filtered PCG, S_i = I - n n^T, prescribed dv . n).

A free particle is in contact with a collider when, at the start of the step, its distance to the surface
(the collider in its start pose) is below ``thickness (1 + margin)`` and it is not lifting off (moving away
fast enough to leave that band within the step), or when it is inside the thickness, or when its predicted
end point x0 + h v0 + h^2 g (the collider in its end pose) is within the thickness (an approach this step would
finish, gravity included: cloth resting a hair above comes down). A particle hovering above the band and not
predicted to reach the surface stays free: prescribing its landing would only pull it down (to be released).
The deepest such collider is kept. The constraint asks the end velocity's normal part,
relative to the surface, to be

    (v1 - u) . n = (thickness (1 + clearance) - d0) / h,

so that the step ends at the thickness (plus a clearance of 2e-3 of it, against rounding): a particle inside is
pushed out, one arriving lands on it; u is the surface velocity (rigid motion over the step, plus a deforming
mesh's vertex velocities) and n the outward normal in the end pose. Releasing a contact whose constraint force pulls, friction, and
the filter itself belong to the solver; this module only finds the contacts.
"""

import warp as wp

from .collide import CONTACT_BAND, SAMPLE_HOLD_SLACK, SHAPE_MESH, mesh_surface_velocity, pinch_height, shape_distance, surface_velocity, world_distance
from .implicit import (ADMITTED, COUNT_CONTACTS, COUNT_SELF_CONTACTS, COUNT_SIZE, RELEASE_FLAG, RELEASE_ROUNDS, RELEASE_SIZE,
                       SLIP_ALLOWANCE, contact_block_inverse, filtered_block_inverse, is_pinched, stick_damper,
                       take_back_contact)
from .worlds import particle_world_of, world_slot
from .selfcollide import NORMAL_EPS, add_impulse, inverse_mass_weight, pair_indices, start_weights, vertex_face_weights, weighted_sum

wp.set_module_options({"enable_backward": False})

# Self-contacts in the solve hold elements this fraction of the cloth thickness apart beyond it, clear of the
# self-collision pass's proximity band (the thickness), so that layers at rest leave the pass nothing to do.
SELF_CLEARANCE = wp.constant(0.05)
# A loaded self-contact element gives way by load / stiffness; with the solver's self_contact_stiffening, one whose load
# holds it near the self-collision pass's reach is stiffened for the next steps (a gain per particle,
# eval_self_contact_gain_targets): at most this many times the model's self-collision stiffness, changed at most 2x a step.
SELF_CONTACT_GAIN_MAX = wp.constant(32.0)
# An edge-edge pair whose nearest points have a weight this small is nearest at an edge's end (eval_self_contacts).
EDGE_END = wp.constant(1.0e-4)
# [m] two faces' distances to a point within this are one contact's (keeps_nearest_feature: the face with the point
# nearest inside it keeps it, else the lower-numbered)
FEATURE_TIE = wp.constant(1.0e-6)
# A candidate pair that started beyond the self-contacts' rest distance by more than this fraction of the clearance and
# whose solved end points are inside it by as much becomes an element within the step (admit_self_contacts); one that
# starts within it, a vertex nearest inside a face, is an element from the step's start, with no force there
# (eval_self_contacts) ...
SELF_ADMIT_DEPTH = wp.constant(0.1)
# ... when it starts within this fraction of the thickness beyond the rest distance (farther, what the start normal
# predicts is no measure of where the pair ends: admitted from up to 1 thickness out, a cloth dropped from 3 cm onto
# another, at 0.7 m/s, threw it up and ended 2.3 mm into it; 3.8 mm apart from 0.5).
SELF_ADMIT_REACH = wp.constant(0.5)
# ... and, a point-face pair, when its start normal is within ~25 degrees of the face's normal, an edge-edge pair, when
# its edges cross at more than ~25 degrees (admit_self_contacts).
SELF_ADMIT_COSINE = wp.constant(0.9)
# A sliding self-contact element (start slip beyond this many times the stick speed) that fell in within the last step
# has its friction bounded by the load its overlap explains, but never below FRICTION_LOAD_LAYERS layers' weight
# (friction_load_overlap).
FRICTION_LOAD_SLIP = wp.constant(10.0)
FRICTION_LOAD_LAYERS = wp.constant(10.0)
# The solve lands a contact this fraction of the thickness above it, clear of the colliders pass's contact band
# (CONTACT_BAND, 1e-3 of the thickness, kernels/collide.py), so that float32 rounding does not leave the
# end point a hair inside, where the colliders pass after the step would push it again (8 um for 4 mm).
CLEARANCE = wp.constant(2.0e-3)
# A contact within the band above the landing height that is not predicted to reach the surface settles onto it at
# most this fast [m/s] (eval_collider_contacts), instead of landing in one step.
SETTLE_SPEED = wp.constant(1.0e-3)
# A pinched contact whose facing surface's normal leans less than this sine off the contact normal's opposite (two sides
# within ~3 degrees of parallel: a slot) is held along its normal only; one between sides at a larger angle (a crease,
# as an armpit's) along the facing normal's part orthogonal to it too (eval_collider_contacts).
CREASE_SINE = wp.constant(0.05)


@wp.func
def surface_contact(shape: int, size: wp.vec3, mesh: wp.uint64, mesh_max_distance: float, deforming: int, t_start: wp.transform,
                    t_end: wp.transform, x: wp.vec3, dt: float):
    """A particle at x against one collider over a step: its distance d0 [m] to the surface (start pose), the outward
    unit normal n (world, end pose) and the surface velocity u [m/s] there."""
    p = wp.transform_point(wp.transform_inverse(t_start), x)
    if deforming != 0:
        p = p + dt * mesh_surface_velocity(mesh, mesh_max_distance, p)
    d0, n_local = shape_distance(shape, size, mesh, mesh_max_distance, p)
    u = surface_velocity(deforming, mesh, mesh_max_distance, t_start, t_end, p, 1.0 / dt)
    return d0, wp.transform_vector(t_end, n_local), u


@wp.func
def landing_height(thickness: float):
    """The height [m] above a collider's surface at which a contact in the solve ends its step: the thickness plus the
    clearance."""
    return thickness * (1.0 + CLEARANCE)


@wp.func
def prescribed_velocity_change(n: wp.vec3, u: wp.vec3, v0: wp.vec3, d0: float, height: float, dt: float, descent: float):
    """z = ((u . n + push) - v0 . n) n [m/s], push = (height - d0) / h: the normal velocity change that ends the step
    at `height` [m] above the surface (`landing_height`, or a pinched particle's); with `descent` >= 0, a particle
    above that height moves down towards it at most that fast [m/s] (0: keeps its height)."""
    push = (height - d0) * (1.0 / dt)
    if descent >= 0.0:
        push = wp.max(push, -descent)
    return (wp.dot(u, n) + push - wp.dot(v0, n)) * n


@wp.func
def pinch_frame(n: wp.vec3, facing: wp.vec3):
    """A pinched contact's normal and height scale: the unit normal b = (n - f) / |n - f| of the plane of points as far
    from its own side (outward normal n) as from the side facing it (f), and k = sqrt((1 - n . f) / 2), the rate at
    which a height above its own side along n changes per metre along b at the plane (so heights k d0 and k s measured
    along b put the particle on it where s, `pinch_height`, does along n). The same frame (b up to its sign) whichever
    side is the nearer: held along its own side's normal, a particle halfway across a T-shirt's shoulder was held along
    one side's normal or the other's as the nearer changed from step to step, its free plane turning with it, and the
    T-shirt held still kept moving there at 1.5 mm/s."""
    return wp.normalize(n - facing), wp.sqrt(0.5 * (1.0 - wp.dot(n, facing)))


@wp.func
def crease_direction(n: wp.vec3, facing: wp.vec3):
    """The second direction a contact pinched in a crease is held along: the unit part of the facing surface's outward
    normal orthogonal to the contact normal n (zero when the two sides are within CREASE_SINE of parallel)."""
    m = facing - wp.dot(facing, n) * n
    if wp.length(m) <= CREASE_SINE:
        return wp.vec3(0.0)
    return wp.normalize(m)


@wp.func
def crease_velocity_change(m: wp.vec3, u: wp.vec3, v0: wp.vec3):
    """z_m = ((u - v0) . m) m [m/s]: the velocity change along a crease direction m (zero: none) that leaves the
    particle moving with the surface (velocity u) along it, where it is as far from both sides."""
    return wp.dot(u - v0, m) * m



@wp.kernel
def eval_collider_contacts(
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
    # Control
    collider_transform_start: wp.array(dtype=wp.transform),
    collider_transform_end: wp.array(dtype=wp.transform),
    # State in
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    gravity: wp.vec3,
    dt: float,
    margin: float,
    hold_band: int,
    dv_previous: wp.array(dtype=wp.vec3),
    previous_ready: wp.array(dtype=wp.int32),
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    contact_impulse: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    load_speed: float,
    sample_height: wp.array(dtype=float),
    # outputs
    contact_collider_out: wp.array(dtype=wp.int32),
    contact_normal_out: wp.array(dtype=wp.vec3),
    contact_velocity_out: wp.array(dtype=wp.vec3),
    contact_dv_out: wp.array(dtype=wp.vec3),
    contact_height_out: wp.array(dtype=float),
    contact_crease_out: wp.array(dtype=wp.vec3),
    contact_facing_out: wp.array(dtype=wp.vec3),
    counts_out: wp.array(dtype=wp.int32),
):
    """Per particle: the collider it touches (-1: none), the outward unit normal n (world, end pose; zero without a
    contact), the surface velocity u [m/s] there and the velocity change it prescribes, z = ((u . n + push) - v0 . n) n
    [m/s] with push = (thickness (1 + clearance) - d0) / h the relative normal speed that ends the step at the
    thickness (zero without a contact). With `hold_band` (forward steps), a particle within the band above the landing
    height that is not predicted to pass the thickness (moved by its last step's velocity change, `dv_previous`, where
    its world has one, else by gravity) is not pulled down onto it in one step: it keeps its height when its contact
    bore no load in the last step, and settles at SETTLE_SPEED when it did (`contact_impulse` above `load_speed` [m/s]
    times the particle's mass: the release check's threshold, below which an impulse is the solve's round-off). The
    cloth often holds such a particle up: pulled down every step, it was found pulling, released and the step solved
    again (and the warm start around it was off); held at its height while loaded, the lower of two layers stayed
    bumpy. Settled on any positive impulse, a T-shirt's particle that the cloth round it held above its landing height
    (impulses of 1.6e-9 and 1.7e-7 kg m/s in the steps before) was pulled down at 1 mm/s every 10-13 frames, and rose
    again when released.
    A particle the colliders pass's element samples pushed out of a mesh collider (forward steps: `sample_height`
    [m], the height over the mesh they left it at, 0 for none; kernels/collide.py SAMPLE_HOLD_SLACK) is in the band of
    a mesh up to that height and SAMPLE_HOLD_SLACK thicknesses, and keeps its height there, loaded or not: its element,
    not the particle, touches the surface. Landed or settled, the
    cloth carried it back to where its edge or triangle sagged into the body, and the samples, which the solve does not
    see, pushed it out again (a T-shirt's shoulder particle moved 1.14 mm every other step: 48 mm/s held still).
    `contact_height_out`: the height [m] above the surface the contact ends the step at, `landing_height`, or, for a
    particle pinched between that surface and one facing it closer than twice the thickness (`pinch_height`: an
    armpit's crease), the height at which it is as far from both, below the thickness; a pinched contact's normal,
    heights and crease direction are those of `pinch_frame` (the frame of the points as far from both sides), and
    `contact_facing_out` is the facing side's outward normal (zero for every other particle). A pinched contact is two-sided:
    the solve does not release it (`eval_contact_release`), for it cannot leave one surface but towards the other; with
    one side held and released, the cloth pulled it off the first and the colliders pass pushed it out of the other,
    every step (a T-shirt's armpit: 3.6 mm in a step). Where the two sides meet at an angle (a crease: more than
    CREASE_SINE off parallel), moving in the contact's tangent plane takes the particle nearer the other side, and
    held along its normal alone it slid into the crease and the colliders pass pushed it back (two welded points in a
    T-shirt's armpits, 10 mm/s held still): such a contact is also held along the facing normal's part orthogonal to
    n, `contact_crease_out` (unit; zero on every other particle), z keeping it with the surface along it, so only the
    crease's line is free (the solve's filter S = I - n n^T - m m^T, kernels/implicit.py `contact_projector`)."""
    i = wp.tid()
    pressed = contact_impulse[i] > load_speed * particle_mass[i]  # (the last step's, read before this step's contacts replace it)
    held = float(0.0)  # (the height the element samples left it at: see above)
    if hold_band != 0:
        held = sample_height[i]
    contact_collider_out[i] = -1
    contact_normal_out[i] = wp.vec3(0.0)
    contact_velocity_out[i] = wp.vec3(0.0)
    contact_dv_out[i] = wp.vec3(0.0)
    contact_height_out[i] = 0.0
    contact_crease_out[i] = wp.vec3(0.0)
    contact_facing_out[i] = wp.vec3(0.0)
    if particle_pinned[i] != 0:
        return
    xs = x0[i]
    xp = xs + dt * v0[i] + (dt * dt) * gravity
    xh = xp  # the band's landing test: moved by the last step's velocity change where there is one (the cloth's support in it)
    if hold_band != 0 and previous_ready[particle_world_of(i, particle_world, worlds)] != 0:
        xh = xs + dt * (v0[i] + dv_previous[i])
    best = float(0.0)
    found = int(-1)
    found_d0 = float(0.0)
    found_descent = float(-1.0)
    for c in range(collider_count):
        shape = collider_shape[c]
        size = collider_size[c]
        mesh = collider_mesh[c]
        thickness = collider_thickness[c]
        t_start = collider_transform_start[c]
        t_end = collider_transform_end[c]
        deforming = collider_deforming[c]
        d0, n, u = surface_contact(shape, size, mesh, mesh_max_distance, deforming, t_start, t_end, xs, dt)
        pe = wp.transform_point(wp.transform_inverse(t_end), xp)
        d_end, n_end = shape_distance(shape, size, mesh, mesh_max_distance, pe)
        depth = d0 - thickness
        band = thickness * (1.0 + margin)
        kept = held > 0.0 and shape == SHAPE_MESH
        if kept:
            band = wp.max(band, held + SAMPLE_HOLD_SLACK * thickness)
        if d0 < band or d_end < thickness:
            # within the margin: not when lifting off (moving away fast enough to leave the band this step; a
            # slower one stays in contact, and is released by the solve if it pulls); inside, or arriving, always
            leaving = d0 >= thickness and d0 + dt * wp.dot(v0[i] - u, n) >= band
            if not leaving and (found < 0 or depth < best):
                found = c
                best = depth
                found_d0 = d0
                contact_normal_out[i] = n
                contact_velocity_out[i] = u
                found_descent = -1.0  # (lands in one step)
                if hold_band != 0 and d0 < band:
                    d_held, n_held = shape_distance(shape, size, mesh, mesh_max_distance, wp.transform_point(wp.transform_inverse(t_end), xh))
                    if d_held >= thickness:
                        found_descent = 0.0
                        if pressed and not kept:
                            found_descent = SETTLE_SPEED
    contact_collider_out[i] = found
    if found >= 0:
        thickness = collider_thickness[found]
        n = contact_normal_out[i]
        height = landing_height(thickness)
        pinch, facing = pinch_height(collider_count, collider_shape, collider_size, collider_mesh, collider_deforming,
                                     mesh_max_distance, collider_transform_start, xs, n, found_d0, thickness, dt)
        crease = wp.vec3(0.0)
        if is_pinched(pinch, thickness):
            found_descent = -1.0
            n, scale = pinch_frame(n, facing)
            contact_normal_out[i] = n
            contact_facing_out[i] = facing
            found_d0 = scale * found_d0
            height = scale * pinch
            crease = crease_direction(n, facing)
        contact_height_out[i] = height
        contact_crease_out[i] = crease
        u = contact_velocity_out[i]
        contact_dv_out[i] = (prescribed_velocity_change(n, u, v0[i], found_d0, height, dt, found_descent)
                             + crease_velocity_change(crease, u, v0[i]))
        wp.atomic_add(counts_out, world_slot(particle_world_of(i, particle_world, worlds), worlds, COUNT_SIZE) + COUNT_CONTACTS, 1)


@wp.kernel
def admit_collider_contacts(
    # Model
    particle_pinned: wp.array(dtype=wp.int32),
    collider_count: int,
    collider_shape: wp.array(dtype=wp.int32),
    collider_size: wp.array(dtype=wp.vec3),
    collider_mesh: wp.array(dtype=wp.uint64),
    collider_deforming: wp.array(dtype=wp.int32),
    collider_thickness: wp.array(dtype=float),
    mesh_max_distance: float,
    # Control
    collider_transform_start: wp.array(dtype=wp.transform),
    collider_transform_end: wp.array(dtype=wp.transform),
    # State in, the solved step
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    dt: float,
    max_rounds: int,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    released_normal: wp.array(dtype=wp.vec3),
    released_dv: wp.array(dtype=wp.vec3),
    friction_mass: wp.array(dtype=float),
    # outputs
    contact_collider_out: wp.array(dtype=wp.int32),
    contact_normal_out: wp.array(dtype=wp.vec3),
    contact_velocity_out: wp.array(dtype=wp.vec3),
    contact_dv_out: wp.array(dtype=wp.vec3),
    contact_height_out: wp.array(dtype=float),
    contact_crease_out: wp.array(dtype=wp.vec3),
    precond_out: wp.array(dtype=wp.mat33),
    precond_free_out: wp.array(dtype=wp.mat33),
    release_out: wp.array(dtype=wp.int32),
    released_out: wp.array(dtype=wp.int32),
    counts_out: wp.array(dtype=wp.int32),
):
    """A particle with no collider contact in its step (none found at the start, none released) whose solved end point
    x0 + h (v0 + dv) lies inside a collider's thickness (below it by more than the colliders pass's band, CONTACT_BAND
    of it, the collider in its end pose) becomes a contact of the deepest such collider, as `eval_collider_contacts` would
    have made it at the start (normal, surface velocity, z landing it at `landing_height`; frictionless in the solve,
    friction after it from the measured impulse; `released_out` ADMITTED), and the step is solved again, while fewer than `max_rounds`
    re-solves were run (the release rounds and flag, kernels/implicit.py eval_contact_release, which releases it again
    if it pulls in a later check, and takes it back if a re-solve then carries it in). The start's test misses cloth
    the solve carries into a collider: pulled by the cloth round it, or swept into by a moving body (the T-shirt's
    walk: ~40 particles a step the colliders pass pushed out after the solve, up to 7 mm deep; its largest strain
    13.6 % over 60 frames, 10.7 % with them admitted). Admitted contacts not released again in their step (as a
    contact taken back is not) made the T-shirt held still move at 48 mm/s: a contact admitted on a check's loose solve
    was held pulling for the rest of the step.
    The start's normal is its nearest face's; in a concave part of a body (the front of an armhole) the solve moves a
    held contact along that face's plane, and its end point can lie inside the collider by another face while the plane
    says it is at the thickness (a T-shirt at 2.8 cm edges: 2.7 mm from the body where the plane said 4). So a held,
    unpinched contact whose solved end lies inside its collider (beyond the band) by a face whose normal n_e leans more
    than CREASE_SINE off its own is held along n_e's part orthogonal to n too (`contact_crease_out`, as a pinched
    contact in a crease is: `eval_collider_contacts`), moving with the surface along it, and the step solved again; and
    a contact released in the step whose free re-solve ends it inside the collider is taken back (`released_out` -1,
    as `eval_contact_release` takes one back that ends below the thickness along the released normal, which misses a
    concave part; held along n_e's part too, as above). Without these the cloth there was released, carried 1.0-1.5 mm
    from the body by the free re-solve, and pushed out 2.6-2.8 mm by the colliders pass every frame (docs/garments.md)."""
    i = wp.tid()
    if particle_pinned[i] != 0:
        return
    w = particle_world_of(i, particle_world, worlds)
    rb = world_slot(w, worlds, RELEASE_SIZE)
    if release_out[rb + RELEASE_ROUNDS] >= max_rounds:
        return
    xs = x0[i]
    xe = xs + dt * (v0[i] + dv[i])
    held = contact_collider_out[i]
    r = released_out[i]
    if held >= 0:
        thickness = collider_thickness[held]
        crease = contact_crease_out[i]
        if is_pinched(contact_height_out[i], thickness) or wp.dot(crease, crease) > 0.0:
            return
        d_end, n_end = world_distance(collider_shape[held], collider_size[held], collider_mesh[held], mesh_max_distance,
                                      collider_transform_end[held], xe)
        if d_end >= thickness * (1.0 - CONTACT_BAND):
            return
        n = contact_normal_out[i]
        m = crease_direction(n, n_end)
        if wp.dot(m, m) == 0.0:
            return
        contact_crease_out[i] = m
        contact_dv_out[i] = contact_dv_out[i] + crease_velocity_change(m, contact_velocity_out[i], v0[i])
        precond_out[i] = contact_block_inverse(precond_free_out[i], friction_mass[i], n, m)
        release_out[rb + RELEASE_FLAG] = 1
        release_out[RELEASE_FLAG] = 1
        return
    if r > 0:  # released in this step
        c = r - 1
        d_end, n_end = world_distance(collider_shape[c], collider_size[c], collider_mesh[c], mesh_max_distance,
                                      collider_transform_end[c], xe)
        if d_end < collider_thickness[c] * (1.0 - CONTACT_BAND):
            nr = released_normal[i]
            m = crease_direction(nr, n_end)
            take_back_contact(i, c, nr, m, released_dv[i] + crease_velocity_change(m, contact_velocity_out[i], v0[i]),
                              precond_free_out[i], rb, contact_collider_out, contact_normal_out, contact_crease_out, contact_dv_out,
                              precond_out, released_out, release_out)
        return
    if r != 0:
        return
    found = int(-1)
    best = float(0.0)
    for c in range(collider_count):
        thickness = collider_thickness[c]
        d_end, n_end = world_distance(collider_shape[c], collider_size[c], collider_mesh[c], mesh_max_distance,
                                      collider_transform_end[c], xe)
        depth = d_end - thickness
        if d_end < thickness * (1.0 - CONTACT_BAND) and (found < 0 or depth < best):
            found = c
            best = depth
    if found < 0:
        return
    d0, n, u = surface_contact(collider_shape[found], collider_size[found], collider_mesh[found], mesh_max_distance,
                               collider_deforming[found], collider_transform_start[found], collider_transform_end[found], xs, dt)
    height = landing_height(collider_thickness[found])
    contact_collider_out[i] = found
    contact_normal_out[i] = n
    contact_velocity_out[i] = u
    contact_dv_out[i] = prescribed_velocity_change(n, u, v0[i], d0, height, dt, -1.0)
    contact_height_out[i] = height
    block = precond_out[i]  # (a free particle's: A_ii^-1, kept for the contact as kernels/implicit.py filter_contact_preconditioner keeps it)
    precond_free_out[i] = block
    precond_out[i] = filtered_block_inverse(wp.inverse(block), n, wp.vec3(0.0))
    released_out[i] = ADMITTED  # (re-solved from z: SolverImplicitEuler._restart)
    release_out[rb + RELEASE_FLAG] = 1
    release_out[RELEASE_FLAG] = 1
    wp.atomic_add(counts_out, world_slot(w, worlds, COUNT_SIZE) + COUNT_CONTACTS, 1)


@wp.kernel(enable_backward=True)
def eval_contact_constraints(
    # Model
    collider_shape: wp.array(dtype=wp.int32),
    collider_size: wp.array(dtype=wp.vec3),
    collider_mesh: wp.array(dtype=wp.uint64),
    collider_deforming: wp.array(dtype=wp.int32),
    mesh_max_distance: float,
    # Control
    collider_transform_start: wp.array(dtype=wp.transform),
    collider_transform_end: wp.array(dtype=wp.transform),
    # the contact set, held fixed (a solved step's: `eval_collider_contacts`, less the released), the heights its
    # contacts end the step at and the pinched ones' crease directions
    contact_collider: wp.array(dtype=wp.int32),
    contact_height: wp.array(dtype=float),
    contact_crease: wp.array(dtype=wp.vec3),
    contact_facing: wp.array(dtype=wp.vec3),
    # State in
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs
    contact_normal_out: wp.array(dtype=wp.vec3),
    contact_velocity_out: wp.array(dtype=wp.vec3),
    contact_dv_out: wp.array(dtype=wp.vec3),
):
    """The normal, surface velocity and prescribed velocity change of each contact of a given set, as
    `eval_collider_contacts` finds them, as differentiable functions of x0, v0 and the colliders' poses (a taped
    step's contacts: the set itself, a discrete choice, is held fixed, and so are a pinched contact's height and
    crease direction and facing normal)."""
    i = wp.tid()
    c = contact_collider[i]
    if c < 0:
        return
    d0, n, u = surface_contact(collider_shape[c], collider_size[c], collider_mesh[c], mesh_max_distance, collider_deforming[c],
                               collider_transform_start[c], collider_transform_end[c], x0[i], dt)
    facing = contact_facing[i]
    if wp.length_sq(facing) > 0.0:  # pinched: held along the normal of the points as far from both sides
        n, scale = pinch_frame(n, facing)
        d0 = scale * d0
    contact_normal_out[i] = n
    contact_velocity_out[i] = u
    contact_dv_out[i] = (prescribed_velocity_change(n, u, v0[i], d0, contact_height[i], dt, -1.0)
                         + crease_velocity_change(contact_crease[i], u, v0[i]))


# -- self-contacts in the solve ----------------------------------------------------------------------------------
# A close vertex-face or edge-edge pair enters the implicit system as a repulsion element (Baraff & Witkin 1998 §6,
# Bridson et al. 2002): with the pair's weights alpha (vertex 1, face -w, or edge a, -b), gap g = sum alpha_r x_r,
# distance d = |g| and normal n = g / d at the step's start, the energy E = k/2 (r - d)^2 for d < r (r: the thickness
# plus the clearance) gives each member the force alpha_r k (r - d) n and the Gauss-Newton stiffness K = k G G^T,
# G_r = alpha_r n (positive semi-definite, as the system needs). The element is a rank-1 stencil as a bend triple is:
# A p gets h^2 k alpha_r n (n . sum alpha_s p_s). Measured on layered cloth and the pile, this plain spring with the
# friction below rests best: a cubic energy (force and stiffness vanishing where the element starts) left the layers
# at 0.5-0.8 mm/s, and element damping c = m / h at 0.9 mm/s, against 0.015 mm/s.


@wp.func
def self_contact_friction_terms(v_t: wp.vec3, impulse: float, mass_weight: float, friction: float, stick_speed: float):
    """A self-contact element's Coulomb friction in the solve, on the pair's relative tangential velocity v_t [m/s] at
    the step's start, with its normal impulse over the step lambda = h k (r - d0) [kg m/s] and mass weight
    w = sum_r alpha_r^2 / m_r [1/kg], as the collider contacts' (kernels/implicit.py eval_contact_friction_terms): a
    pair sliding faster than friction could stop in a step (|v_t| > mu lambda w) takes the kinetic impulse
    J = -mu lambda v_t / |v_t| (member r: alpha_r J); any other a tangential damper of mass d = mu lambda / max(eps, |v_t|)
    [kg] on its relative velocity (A += d alpha_r alpha_s T, b_r -= d alpha_r T v_rel0). Returns (d, J)."""
    if impulse <= 0.0 or mass_weight <= 0.0 or friction <= 0.0:
        return wp.vec4(0.0)
    speed = wp.length(v_t)
    bound = friction * impulse
    if speed > bound * mass_weight:
        j = (-bound / speed) * v_t
        return wp.vec4(0.0, j[0], j[1], j[2])
    return wp.vec4(stick_damper(bound, speed, stick_speed), 0.0, 0.0, 0.0)


@wp.func
def friction_load_overlap(overlap: float, v_n: float, slip: float, stiffness: float, mass_weight: float, dt: float,
                          gravity: float, stick_speed: float):
    """The part o_f [m] of a self-contact element's start overlap o = r - d0 that bounds its friction, mu h k o_f. h k o
    is the normal impulse the element delivers over the step where the overlap is its load / k. A pair that fell in
    within the last step (its approach -h v_n0 at least half its overlap, v_n0 [m/s] its start normal velocity) is
    pushed out by the stiff penalty within the step: it delivers about what a free pair of inverse mass w [1/kg] would,
    h k (o - h v_n0) / (1 + h^2 k w), plus the load of the overlap its approach does not explain, h k max(0, o + h v_n0).
    Where such a pair slides (start slip [m/s] beyond FRICTION_LOAD_SLIP x `stick_speed`), o_f is that, never below
    the overlap of FRICTION_LOAD_LAYERS layers' weight (|g| / (k w) each, `gravity` |g| [m/s^2]), nor above o; else o.
    With h k o, upper vertices of a cloth sliding down a cloth that fell 0.4-0.5 mm into the lower one got static
    friction dampers of 160 times their mass and stopped it in a step (-2255 % of the analytic rate), and edge pairs
    7 um in, each bearing the whole upper cloth's weight, stopped it for a step (-455 %). Resting and pressed pairs keep
    h k o: bounded for every pair, the T-shirt held still ended at 1.6 mm/s (0.41 without), at 14.9 mm/s with the
    fall-in test alone (docs/contacts-in-the-solve.md, "A deep self-contact's friction")."""
    if overlap <= 0.0 or mass_weight <= 0.0 or slip <= FRICTION_LOAD_SLIP * stick_speed or -dt * v_n < 0.5 * overlap:
        return overlap
    # (fell in: -h v_n0 >= o / 2 > 0, so o - h v_n0 > 0)
    delivered = (overlap - dt * v_n) / (1.0 + dt * dt * stiffness * mass_weight) + wp.max(overlap + dt * v_n, 0.0)
    layers = FRICTION_LOAD_LAYERS * gravity / (stiffness * mass_weight)
    return wp.min(overlap, wp.max(delivered, layers))


@wp.kernel
def eval_friction_load_overlaps(cases: wp.array(dtype=wp.vec4), stiffness: float, dt: float, gravity: float,
                                stick_speed: float, friction_overlap_out: wp.array(dtype=float)):
    """`friction_load_overlap` of each case (overlap [m], start normal velocity [m/s], start slip [m/s], inverse mass
    weight [1/kg]), for checks of the rule on its own."""
    i = wp.tid()
    c = cases[i]
    friction_overlap_out[i] = friction_load_overlap(c[0], c[1], c[2], stiffness, c[3], dt, gravity, stick_speed)


@wp.func
def solved_pair(pair: wp.vec2i, kind: int, tri_indices: wp.array2d(dtype=wp.int32), edge_indices: wp.array2d(dtype=wp.int32),
                particle_point_root: wp.array(dtype=wp.int32), particle_offset: int):
    """A candidate pair's four particles as the solve takes them: offset into the batch's arrays, a welded point's
    particle replaced by its root (cloth_warp/sewing.py `welded_view`)."""
    o = particle_offset
    idx = pair_indices(pair, kind, tri_indices, edge_indices) + wp.vec4i(o, o, o, o)
    for r in range(4):
        root = particle_point_root[idx[r]]
        if root >= 0:
            idx[r] = root
    return idx


@wp.func
def any_pinned(idx: wp.vec4i, particle_pinned: wp.array(dtype=wp.int32)):
    """Whether a pair has a pinned particle (no element: the pin holds it)."""
    for r in range(4):
        if particle_pinned[idx[r]] != 0:
            return True
    return False


@wp.func
def at_edge_end(kind: int, alpha: wp.vec4):
    """Whether an edge-edge pair (kind 1) is nearest at an edge's end: that vertex's contact, which its vertex-face
    pairs hold (as edge pairs it came once per edge at the vertex: eight at a T-shirt's armpit, one contact eight times
    as stiff, throwing the cloth out 3.4 mm in a step and back: 220-390 mm/s, against 7-18 without them)."""
    return kind == 1 and wp.min(wp.min(alpha[0], alpha[1]), wp.min(-alpha[2], -alpha[3])) <= EDGE_END


@wp.func
def zero_weight_count(alpha: wp.vec4):
    """How many of a vertex-face pair's face weights are zero (to EDGE_END): 0 nearest inside the face, 1 at an edge,
    2 at a corner."""
    count = int(0)
    for j in range(3):
        if -alpha[j] <= EDGE_END:
            count += 1
    return count


@wp.func
def keeps_nearest_feature(pair: wp.vec2i, idx: wp.vec4i, alpha: wp.vec4, d: float, ring_offsets: wp.array(dtype=wp.int32),
                          ring_faces: wp.array(dtype=wp.int32), tri_indices: wp.array2d(dtype=wp.int32),
                          edge_indices: wp.array2d(dtype=wp.int32), particle_point_root: wp.array(dtype=wp.int32),
                          particle_offset: int, x0: wp.array(dtype=wp.vec3)):
    """Whether vertex-face pair `pair` (its solved particles `idx`, weights `alpha` and distance d [m] at x0) keeps its
    contact. A point nearest at a face's edge or corner may be as near, or nearer, to another face at that edge or
    corner: one contact met once from each (an element each: twice or six times as stiff, and as much friction, where
    a cloth sliding over a cloth crossed an edge). The pair keeps it where no face round its nearest edge's or
    corner's vertices (`ring_offsets`, `ring_faces`: per particle its faces, the model's numbering) is nearer by more
    than FEATURE_TIE, and none as near has the point nearest inside it or a lower number (a pair nearest inside its
    face always keeps its contact)."""
    zeros = zero_weight_count(alpha)
    if zeros == 0 or zeros == 3:
        return True
    f = pair[0]
    p = x0[idx[3]]
    for j in range(3):
        if -alpha[j] > EDGE_END:  # a vertex of the nearest edge or corner
            u = tri_indices[f, j]
            for k in range(ring_offsets[u], ring_offsets[u + 1]):
                g = ring_faces[k]
                if g != f:
                    other = solved_pair(wp.vec2i(g, pair[1]), 0, tri_indices, edge_indices, particle_point_root, particle_offset)
                    if other[0] != idx[3] and other[1] != idx[3] and other[2] != idx[3]:
                        beta = vertex_face_weights(x0, other)
                        d_g = wp.length(weighted_sum(beta, x0[other[0]], x0[other[1]], x0[other[2]], p))
                        if d_g < d - FEATURE_TIE or (d_g <= d + FEATURE_TIE and (g < f or zero_weight_count(beta) == 0)):
                            return False
    return True


@wp.func
def nearest_inside(kind: int, alpha: wp.vec4):
    """Whether a pair is a vertex-face one (kind 0) nearest inside its face, not at its edge."""
    return kind == 0 and zero_weight_count(alpha) == 0


@wp.func
def store_element(e: int, idx: wp.vec4i, alpha: wp.vec4, n: wp.vec3, overlap: float, friction_mass: float, slide: wp.vec3,
                  stiffness: float, coefficient: float, element_indices_out: wp.array(dtype=wp.vec4i),
                  element_weights_out: wp.array(dtype=wp.vec4), element_normal_out: wp.array(dtype=wp.vec3),
                  element_overlap_out: wp.array(dtype=float), element_friction_mass_out: wp.array(dtype=float),
                  element_friction_impulse_out: wp.array(dtype=wp.vec3), element_stiffness_out: wp.array(dtype=float),
                  element_coefficient_out: wp.array(dtype=float)):
    """Write self-contact element e."""
    element_indices_out[e] = idx
    element_weights_out[e] = alpha
    element_normal_out[e] = n
    element_overlap_out[e] = overlap
    element_friction_mass_out[e] = friction_mass
    element_friction_impulse_out[e] = slide
    element_stiffness_out[e] = stiffness
    element_coefficient_out[e] = coefficient


@wp.func
def element_gain(idx: wp.vec4i, alpha: wp.vec4, gain: wp.array(dtype=float)):
    """A self-contact element's stiffness gain: the largest of its particles' (those with a weight), at least 1."""
    g = float(1.0)
    for r in range(4):
        if alpha[r] != 0.0:
            g = wp.max(g, gain[idx[r]])
    return g


@wp.func
def admit_depth(rest_distance: float):
    """How far [m] beyond the self-contacts' rest distance r an admissible pair starts, and inside it its solved end lies,
    for admission: SELF_ADMIT_DEPTH of the clearance (r = thickness (1 + SELF_CLEARANCE))."""
    return SELF_ADMIT_DEPTH * rest_distance * SELF_CLEARANCE / (1.0 + SELF_CLEARANCE)


@wp.func
def leaves_contact(d: float, v_n: float, rest_distance: float, dt: float, gravity: float):
    """Whether a self-contact pair d [m] apart, separating at v_n [m/s] at the step's start, leaves the contact within
    the step even if its separation slows by `gravity` |g| [m/s^2] over it (a layer whose support is gone): its end
    d + h v_n - h^2 |g| is beyond the rest distance r by more than the admission depth. Such a pair gets no element at
    the step's start (its linear force k (r - d1) would pull the layers together past r, where the penalty has none: a
    cloth thrown up at 0.5 m/s off another left it at 7e-5 m/s), but is admissible, so that a solve that carries it back
    inside r makes it an element within the step (admit_self_contacts)."""
    return d + dt * v_n - dt * dt * gravity >= rest_distance + admit_depth(rest_distance)


@wp.func
def admissible(kind: int, x0: wp.array(dtype=wp.vec3), idx: wp.vec4i, gap: wp.vec3, d: float, rest_distance: float):
    """Whether a pair d [m] apart at the step's start (beyond the rest distance r, along gap) is one the contact checks may
    admit (admit_self_contacts): beyond r by more than SELF_ADMIT_DEPTH of the clearance (within it, a vertex nearest
    inside a face has a force-free element from the step's start: eval_self_contacts), within SELF_ADMIT_REACH of the
    thickness (farther, its start normal is no measure of where it ends), a point-face pair's normal within
    SELF_ADMIT_COSINE of the face's (beside the face it may pass it by), an edge pair's edges crossing at an angle whose
    cosine is below it (side by side, their normal may lie in the layers)."""
    if d < rest_distance + admit_depth(rest_distance) or d >= rest_distance + SELF_ADMIT_REACH * rest_distance / (1.0 + SELF_CLEARANCE):
        return False
    n = gap / d
    if kind == 0:
        face = wp.cross(x0[idx[1]] - x0[idx[0]], x0[idx[2]] - x0[idx[0]])
        return wp.abs(wp.dot(face, n)) >= SELF_ADMIT_COSINE * wp.length(face)
    a = x0[idx[1]] - x0[idx[0]]
    b = x0[idx[3]] - x0[idx[2]]
    return wp.abs(wp.dot(a, b)) <= SELF_ADMIT_COSINE * wp.length(a) * wp.length(b)


@wp.kernel
def eval_self_contacts(
    # candidates: the last step's close pairs of one kind (the first count[0] of `pairs`)
    count: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    kind: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    ring_offsets: wp.array(dtype=wp.int32),
    ring_faces: wp.array(dtype=wp.int32),
    particle_pinned: wp.array(dtype=wp.int32),
    particle_point_root: wp.array(dtype=wp.int32),
    # State in
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    rest_distance: float,
    stiffness: float,
    dt: float,
    gravity: float,
    capacity: int,
    # friction in the solve (friction_in_solve != 0)
    inv_mass: wp.array(dtype=float),
    friction: float,
    stick_speed: float,
    friction_in_solve: int,
    particle_offset: int,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    coefficient: float,
    gain: wp.array(dtype=float),
    # outputs: the elements (appended) and their force, K v0 and diagonal blocks (accumulated per particle)
    element_indices_out: wp.array(dtype=wp.vec4i),
    element_weights_out: wp.array(dtype=wp.vec4),
    element_normal_out: wp.array(dtype=wp.vec3),
    element_overlap_out: wp.array(dtype=float),
    element_friction_mass_out: wp.array(dtype=float),
    element_friction_impulse_out: wp.array(dtype=wp.vec3),
    element_count_out: wp.array(dtype=wp.int32),
    force_out: wp.array(dtype=wp.vec3),
    kv_out: wp.array(dtype=wp.vec3),
    diag_out: wp.array(dtype=wp.mat33),
    counts_out: wp.array(dtype=wp.int32),
    element_stiffness_out: wp.array(dtype=float),
    element_coefficient_out: wp.array(dtype=float),
    # the pairs beyond r the contact checks may admit (admit_self_contacts), appended: particles, weights, start gap
    # [m], k, h^2 k, admitted (0 here)
    admissible_indices_out: wp.array(dtype=wp.vec4i),
    admissible_weights_out: wp.array(dtype=wp.vec4),
    admissible_gap_out: wp.array(dtype=wp.vec3),
    admissible_stiffness_out: wp.array(dtype=float),
    admissible_coefficient_out: wp.array(dtype=float),
    admissible_admitted_out: wp.array(dtype=wp.int32),
    admissible_count_out: wp.array(dtype=wp.int32),
):
    """Each candidate pair closer than `rest_distance` r [m] at x0, none of its particles pinned and not leaving the
    contact within the step (`leaves_contact`, with `gravity` |g| [m/s^2]), becomes a repulsion element of `stiffness`
    k [N/m] (see above); the overlap r - d [m] that bounds its friction is kept (`friction_load_overlap`). So does a
    vertex-face pair resting beyond r within the admission depth (`admit_depth`) and nearest inside its face
    (`nearest_inside`), with no force at the start (its
    overlap 0) and its stiffness in the matrix: without it, a landing that ended at r left half its pairs a hair
    beyond r, to fall g h^2 into the cloth in the next step (0.64 mm at 1/120 s) and be thrown back out. Pairs nearest
    at a face's edge are left out (their normal leans off the face's: such elements held a cloth sliding down a cloth
    on a 30 deg incline), and edge-edge pairs (near an edge's end, a vertex's contact again: with them a layered
    outfit held still kept a hip particle swinging at up to 0.9 mm/s, 0.1 without). A vertex-face pair nearest at an
    edge or corner of its face whose contact another face there holds gets nothing (`keeps_nearest_feature`: each
    particle's faces in `ring_offsets`, `ring_faces`). With `friction_in_solve`,
    its Coulomb friction (coefficient `friction`) enters the system as well (see `self_contact_friction_terms`).
    Its stiffness is k times the element's `gain` (`element_gain`, kept by eval_self_contact_gain_targets).
    Batched worlds: `pairs`, `tri_indices` and `edge_indices` are one world's (its own model's), its particles from
    `particle_offset` on in the batch's arrays; the element is counted in its world's counters. Each
    element keeps its k and `coefficient` h^2 k (its world's: the worlds' stiffness may differ) for the product and
    the friction. A particle of a welded point the solve takes as one particle (`particle_point_root` >= 0) is its
    root in the element (they coincide: cloth_warp/sewing.py `welded_view`). A pair beyond r that the contact checks may
    admit within the step (`admissible`), or one leaving the contact, is kept in the admissible arrays instead, so that
    each check reads it there
    rather than weighing every candidate again."""
    tid = wp.tid()
    if tid >= count[0]:
        return
    idx = solved_pair(pairs[tid], kind, tri_indices, edge_indices, particle_point_root, particle_offset)
    if any_pinned(idx, particle_pinned):
        return
    alpha = start_weights(kind, x0, idx)
    if at_edge_end(kind, alpha):
        return
    gap = weighted_sum(alpha, x0[idx[0]], x0[idx[1]], x0[idx[2]], x0[idx[3]])
    d = wp.length(gap)
    if d <= NORMAL_EPS:
        return
    n = gap / d
    v_rel = weighted_sum(alpha, v0[idx[0]], v0[idx[1]], v0[idx[2]], v0[idx[3]])
    v_n = wp.dot(n, v_rel)
    leaving = leaves_contact(d, v_n, rest_distance, dt, gravity)
    resting_beyond = d < rest_distance + admit_depth(rest_distance) and nearest_inside(kind, alpha)  # force-free element
    keep_admissible = leaving or not (d < rest_distance or resting_beyond)  # (else an element)
    if keep_admissible and not (leaving or admissible(kind, x0, idx, gap, d, rest_distance)):
        return
    if kind == 0:  # (only for the pairs kept either way: it looks at up to two vertices' faces)
        if not keeps_nearest_feature(pairs[tid], idx, alpha, d, ring_offsets, ring_faces, tri_indices, edge_indices,
                                     particle_point_root, particle_offset, x0):
            return
    g = element_gain(idx, alpha, gain)  # (for the pairs kept either way)
    k = g * stiffness
    if keep_admissible:
        slot = wp.atomic_add(admissible_count_out, 0, 1)
        if slot < capacity:
            admissible_indices_out[slot] = idx
            admissible_weights_out[slot] = alpha
            admissible_gap_out[slot] = gap
            admissible_stiffness_out[slot] = k
            admissible_coefficient_out[slot] = g * coefficient
            admissible_admitted_out[slot] = 0
        return
    e = wp.atomic_add(element_count_out, 0, 1)
    if e >= capacity:
        return
    overlap = wp.max(rest_distance - d, 0.0)
    friction_mass = float(0.0)
    slide = wp.vec3(0.0)
    friction_overlap = overlap
    if friction_in_solve != 0:
        w = inverse_mass_weight(alpha, idx, inv_mass)
        v_t = v_rel - v_n * n
        friction_overlap = friction_load_overlap(overlap, v_n, wp.length(v_t), k, w, dt, gravity, stick_speed)
        terms = self_contact_friction_terms(v_t, dt * k * friction_overlap, w, friction, stick_speed)
        friction_mass = terms[0]
        slide = wp.vec3(terms[1], terms[2], terms[3])
    store_element(e, idx, alpha, n, friction_overlap, friction_mass, slide, k, g * coefficient, element_indices_out,
                  element_weights_out, element_normal_out, element_overlap_out, element_friction_mass_out,
                  element_friction_impulse_out, element_stiffness_out, element_coefficient_out)
    # the damper's b part, -d alpha_r v_T, and the slide's alpha_r J, as forces (b = h (f0 - h K v0))
    push = slide - friction_mass * (v_rel - v_n * n)
    block = (dt * dt * k) * wp.outer(n, n) + friction_mass * (wp.identity(n=3, dtype=float) - wp.outer(n, n))
    for r in range(4):
        a = alpha[r]
        wp.atomic_add(force_out, idx[r], (a * k * overlap) * n + (a / dt) * push)
        wp.atomic_add(kv_out, idx[r], (a * k * v_n) * n)
        wp.atomic_add(diag_out, idx[r], (a * a) * block)
    wp.atomic_add(counts_out, world_slot(particle_world_of(idx[0], particle_world, worlds), worlds, COUNT_SIZE) + COUNT_SELF_CONTACTS, 1)


@wp.func
def add_self_contact_product(e: int, element_indices: wp.array(dtype=wp.vec4i), element_weights: wp.array(dtype=wp.vec4),
                             element_normal: wp.array(dtype=wp.vec3), element_friction_mass: wp.array(dtype=float),
                             element_coefficient: wp.array(dtype=float), p: wp.array(dtype=wp.vec3), product_out: wp.array(dtype=wp.vec3)):
    """Self-contact element e's part of A p: h^2 k alpha_r n (n . q) + d alpha_r T q to each member r, q = sum alpha_s p_s
    (`element_coefficient` = h^2 k; d the element's friction damper, T = I - n n^T)."""
    idx = element_indices[e]
    alpha = element_weights[e]
    n = element_normal[e]
    q = weighted_sum(alpha, p[idx[0]], p[idx[1]], p[idx[2]], p[idx[3]])
    q_n = wp.dot(n, q)
    c = element_coefficient[e] * q_n * n + element_friction_mass[e] * (q - q_n * n)
    for r in range(4):
        wp.atomic_add(product_out, idx[r], alpha[r] * c)


@wp.kernel
def scatter_self_contact_product(
    element_count: wp.array(dtype=wp.int32),
    element_indices: wp.array(dtype=wp.vec4i),
    element_weights: wp.array(dtype=wp.vec4),
    element_normal: wp.array(dtype=wp.vec3),
    element_friction_mass: wp.array(dtype=float),
    element_coefficient: wp.array(dtype=float),
    p: wp.array(dtype=wp.vec3),
    walk: int,
    # outputs (accumulated)
    product_out: wp.array(dtype=wp.vec3),
):
    """The self-contact elements' part of A p (`add_self_contact_product`), the first element_count[0]: launched over the
    elements' capacity, a thread each; or with `walk`, by one thread element after element (the CPU's one-thread-per-world
    CG, every iteration: the same sums in the same order, without a thread for each element of the capacity, which is
    the candidates': 24576 for 18 elements on the 32^2 pile at rest)."""
    e = wp.tid()
    if walk != 0:
        for k in range(element_count[0]):
            add_self_contact_product(k, element_indices, element_weights, element_normal, element_friction_mass, element_coefficient,
                                     p, product_out)
        return
    if e >= element_count[0]:
        return
    add_self_contact_product(e, element_indices, element_weights, element_normal, element_friction_mass, element_coefficient, p,
                             product_out)


@wp.func
def element_kind(alpha: wp.vec4):
    """A self-contact element's pair kind from its weights: vertex-face (0: the vertex last, weight 1) or edge-edge (1:
    the second edge's weights negative)."""
    if alpha[3] > 0.0:
        return 0
    return 1


@wp.func
def element_geometry(element_weights: wp.vec4, idx: wp.vec4i, x0: wp.array(dtype=wp.vec3)):
    """A held self-contact element's weights alpha, gap sum_r alpha_r x0_r [m] and distance d [m] at x0, as
    eval_self_contacts evaluates them (the pair's closest points: differentiable in x0 through them)."""
    alpha = start_weights(element_kind(element_weights), x0, idx)
    gap = weighted_sum(alpha, x0[idx[0]], x0[idx[1]], x0[idx[2]], x0[idx[3]])
    return alpha, gap, wp.length(gap)


@wp.kernel(enable_backward=True)
def eval_residual_self_contacts(
    element_count: wp.array(dtype=wp.int32),
    element_indices: wp.array(dtype=wp.vec4i),
    element_weights: wp.array(dtype=wp.vec4),
    element_stiffness: wp.array(dtype=float),
    rest_distance: float,
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    dt: float,
    # output (accumulated)
    r_out: wp.array(dtype=wp.vec3),
):
    """A taped step's self-contact elements' part of r = b - A dv [kg m/s], the element set held fixed (frictionless in
    the solve): h k alpha_r ((r - d)+ n - h n (n . q)), q = sum alpha_s (v0_s + dv_s), with the weights alpha, the
    distance d and the normal n from x0 (`element_geometry`), k the element's stiffness, r the rest distance [m], h = `dt`
    [s]."""
    e = wp.tid()
    if e >= element_count[0]:
        return
    idx = element_indices[e]
    alpha, gap, d = element_geometry(element_weights[e], idx, x0)
    if d <= NORMAL_EPS:
        return
    n = gap / d
    q = weighted_sum(alpha, v0[idx[0]] + dv[idx[0]], v0[idx[1]] + dv[idx[1]], v0[idx[2]] + dv[idx[2]], v0[idx[3]] + dv[idx[3]])
    c = (dt * element_stiffness[e]) * (wp.max(rest_distance - d, 0.0) - dt * wp.dot(n, q)) * n
    for k in range(4):
        wp.atomic_add(r_out, idx[k], alpha[k] * c)


@wp.kernel(enable_backward=True)
def eval_self_contact_geometry(
    element_count: wp.array(dtype=wp.int32),
    element_indices: wp.array(dtype=wp.vec4i),
    element_weights: wp.array(dtype=wp.vec4),
    rest_distance: float,
    x0: wp.array(dtype=wp.vec3),
    # outputs
    weights_out: wp.array(dtype=wp.vec4),
    normal_out: wp.array(dtype=wp.vec3),
    overlap_out: wp.array(dtype=float),
):
    """A taped step's self-contact elements' weights, unit normals and overlaps (r - d)+ [m] at x0, as eval_self_contacts
    evaluates them (differentiable in x0; the element set held fixed): what their friction on the tape reads."""
    e = wp.tid()
    if e >= element_count[0]:
        return
    alpha, gap, d = element_geometry(element_weights[e], element_indices[e], x0)
    weights_out[e] = alpha
    if d > NORMAL_EPS:
        normal_out[e] = gap / d
        overlap_out[e] = wp.max(rest_distance - d, 0.0)


@wp.func
def pair_end_velocity(alpha: wp.vec4, idx: wp.vec4i, v0: wp.array(dtype=wp.vec3), dv: wp.array(dtype=wp.vec3)):
    """A self-contact pair's relative velocity [m/s] at the step's end, sum_r alpha_r (v0_r + dv_r)."""
    return weighted_sum(alpha, v0[idx[0]] + dv[idx[0]], v0[idx[1]] + dv[idx[1]], v0[idx[2]] + dv[idx[2]], v0[idx[3]] + dv[idx[3]])


@wp.kernel
def slide_self_contacts(
    element_count: wp.array(dtype=wp.int32),
    element_indices: wp.array(dtype=wp.vec4i),
    element_weights: wp.array(dtype=wp.vec4),
    element_normal: wp.array(dtype=wp.vec3),
    element_overlap: wp.array(dtype=float),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    element_stiffness: wp.array(dtype=float),
    friction: float,
    dt: float,
    stick_speed: float,
    max_rounds: int,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    element_friction_mass_out: wp.array(dtype=float),
    element_friction_impulse_out: wp.array(dtype=wp.vec3),
    rhs_out: wp.array(dtype=wp.vec3),
    release_out: wp.array(dtype=wp.int32),
):
    """A self-contact element whose friction damper (`self_contact_friction_terms`) the solve pushed past the static
    bound (solved relative slip s beyond the stick speed [m/s], d |s| > mu lambda) slides within the step, as a collider
    contact does (kernels/implicit.py eval_contact_release): its damper leaves the system (its b part, -d alpha_r v_T0,
    taken back) for the kinetic impulse J = -mu lambda s / |s| (alpha_r J to each member), and the step is solved again
    (release_out[RELEASE_FLAG]), while fewer than `max_rounds` re-solves ran. Without it a pair starting from rest
    under a load above the bound only sped up by the load's ratio to the bound per step (a cloth on a cloth on a 30 deg
    incline at 0.15 m/s after 10 frames, against 0.28 with the slide). The preconditioner keeps the damper's block
    (still SPD).

    A sliding element (its kinetic impulse J, from this step's slide or its start's speed) whose solved slip J reversed
    (s . J > 0: the elements around it changed in the re-solve, and friction now holds it) sticks again, with its damper
    d = mu lambda / max(eps, |v_T0|) in place of J, and the step is solved again, as a collider contact does. Left
    sliding, the cloth round it took an impulse it did not need (`eval_self_contact_friction` then stopped the pair
    alone): the layered outfit held still went through a stick-slip cycle between its garments, 20 Hz, 1.6-2.5 mm/s at
    its overskirt's hem (0.29 / 0.15 mm/s with this; docs/garments.md)."""
    e = wp.tid()
    if e >= element_count[0]:
        return
    idx = element_indices[e]
    rb = world_slot(particle_world_of(idx[0], particle_world, worlds), worlds, RELEASE_SIZE)  # (batched: its world's)
    if release_out[rb + RELEASE_ROUNDS] >= max_rounds:
        return
    d = element_friction_mass_out[e]
    j = element_friction_impulse_out[e]
    if d <= 0.0 and wp.dot(j, j) == 0.0:  # frictionless
        return
    alpha = element_weights[e]
    n = element_normal[e]
    v_end = pair_end_velocity(alpha, idx, v0, dv)
    slip = v_end - wp.dot(v_end, n) * n
    speed = wp.length(slip)
    bound = friction * dt * element_stiffness[e] * element_overlap[e]
    v_start = weighted_sum(alpha, v0[idx[0]], v0[idx[1]], v0[idx[2]], v0[idx[3]])
    v_t0 = v_start - wp.dot(v_start, n) * n
    if d <= 0.0:  # sliding
        if wp.dot(slip, j) > 0.0:  # reversed by its kinetic impulse: it sticks again
            d = stick_damper(bound, wp.length(v_t0), stick_speed)
            for r in range(4):
                wp.atomic_add(rhs_out, idx[r], -alpha[r] * (j + d * v_t0))
            element_friction_mass_out[e] = d
            element_friction_impulse_out[e] = wp.vec3(0.0)
            release_out[rb + RELEASE_FLAG] = 1
            release_out[RELEASE_FLAG] = 1
        return
    if speed <= SLIP_ALLOWANCE * stick_speed or d * speed <= SLIP_ALLOWANCE * bound:
        return
    j = (-bound / speed) * slip
    for r in range(4):
        wp.atomic_add(rhs_out, idx[r], alpha[r] * (j + d * v_t0))
    element_friction_mass_out[e] = 0.0
    element_friction_impulse_out[e] = j
    release_out[rb + RELEASE_FLAG] = 1
    release_out[RELEASE_FLAG] = 1


@wp.kernel
def eval_self_contact_gain_targets(
    element_count: wp.array(dtype=wp.int32),
    element_indices: wp.array(dtype=wp.vec4i),
    element_weights: wp.array(dtype=wp.vec4),
    element_normal: wp.array(dtype=wp.vec3),
    gain: wp.array(dtype=float),
    x0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    rest_distance: float,
    held_overlap: float,
    dt: float,
    # output: per particle the largest gain its elements ask (atomic max; zeroed by update_self_contact_gains)
    target_out: wp.array(dtype=float),
):
    """Each element's load, g k o at its solved end overlap o = r - n . (gap0 + h v_rel) [m] (`rest_distance` r, g its
    gain), asks for each of its weighted particles the gain that would hold it at `held_overlap` [m]: g o /
    held_overlap (update_self_contact_gains follows it). A loaded element gives way by load / stiffness; past the
    self-collision pass's reach the pass pushed it out every step and the next solve pulled it back (a T-shirt's fold
    at its armhole seam, held by the cloth's tension round it)."""
    e = wp.tid()
    if e >= element_count[0]:
        return
    idx = element_indices[e]
    alpha = element_weights[e]
    n = element_normal[e]
    gap = weighted_sum(alpha, x0[idx[0]], x0[idx[1]], x0[idx[2]], x0[idx[3]])
    overlap = rest_distance - wp.dot(n, gap + dt * pair_end_velocity(alpha, idx, v0, dv))
    if overlap <= 0.0:
        return
    target = element_gain(idx, alpha, gain) * overlap / held_overlap
    for r in range(4):
        if alpha[r] != 0.0:
            wp.atomic_max(target_out, idx[r], target)


@wp.kernel
def update_self_contact_gains(target_out: wp.array(dtype=float), gain_out: wp.array(dtype=float)):
    """Each particle's self-contact gain g (in place in `gain_out`) follows what its elements asked (`target_out`,
    eval_self_contact_gain_targets; none: 0; zeroed here for the next step) with hysteresis: up to the target when it is
    above g (by at most 2x a step: a pair the dressing hands over deep is not thrown apart in a step), halved while it
    is below g / 2, else kept, within [1, SELF_CONTACT_GAIN_MAX]. Followed both ways every step, the gains and the
    loads they shift fed each other: layers pressed into soft contacts swung at 2-33 mm/s, depending on the held
    overlap, where the hysteresis lets them rest."""
    i = wp.tid()
    g = gain_out[i]
    t = target_out[i]
    if t > g:
        g = wp.min(t, 2.0 * g)
    elif t < 0.5 * g:
        g = 0.5 * g
    gain_out[i] = wp.clamp(g, 1.0, SELF_CONTACT_GAIN_MAX)
    target_out[i] = 0.0  # (each thread reads and writes its own particle's)


@wp.kernel
def admit_self_contacts(
    # the step's admissible pairs (eval_self_contacts)
    admissible_count: wp.array(dtype=wp.int32),
    admissible_indices: wp.array(dtype=wp.vec4i),
    admissible_weights: wp.array(dtype=wp.vec4),
    admissible_gap: wp.array(dtype=wp.vec3),
    admissible_stiffness: wp.array(dtype=float),
    admissible_coefficient: wp.array(dtype=float),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    rest_distance: float,
    dt: float,
    capacity: int,
    max_rounds: int,
    particle_world: wp.array(dtype=wp.int32),
    worlds: int,
    # outputs
    admissible_admitted_out: wp.array(dtype=wp.int32),
    element_indices_out: wp.array(dtype=wp.vec4i),
    element_weights_out: wp.array(dtype=wp.vec4),
    element_normal_out: wp.array(dtype=wp.vec3),
    element_overlap_out: wp.array(dtype=float),
    element_friction_mass_out: wp.array(dtype=float),
    element_friction_impulse_out: wp.array(dtype=wp.vec3),
    element_count_out: wp.array(dtype=wp.int32),
    rhs_out: wp.array(dtype=wp.vec3),
    counts_out: wp.array(dtype=wp.int32),
    element_stiffness_out: wp.array(dtype=float),
    element_coefficient_out: wp.array(dtype=float),
    release_out: wp.array(dtype=wp.int32),
):
    """An admissible pair (eval_self_contacts `admissible`: it starts the step apart, beyond `rest_distance` r by more
    than SELF_ADMIT_DEPTH of the clearance) whose solved end points, at its start weights, are inside r by as much
    (d1 = |sum_r alpha_r (x0_r + h (v0_r + dv_r))|) becomes an element for the rest of the step, and the step is
    solved again (release_out[RELEASE_FLAG]) while fewer than `max_rounds` re-solves ran. Its linear force
    k (r - d0 - h n . v_rel1) is the penalty's at the end of the step, which the re-solve makes push: the admitting half
    of an active set on the piecewise-linear penalty, what backward Euler asks of it (an element that ends a step
    pulling is kept: README, Known limits). Without it a pair closing within a step met no force until the next step
    found it inside, by up to the whole approach, and was thrown out past r, to fall in again: a fold's edge in a 32^2
    pile (seed 12) swung by 0.3 mm every four steps at 24 mm/s; a cloth dropped onto another ended a step 1.8 mm inside.
    The admissible filters and the end measured at the start weights, not along the start normal n: a cloth sliding
    down a cloth on a 30 deg incline admitted pairs resting at r and pairs passing a face's corner, whose re-solves took
    the rounds its kinetic friction needed; it stuck (-0.91 m/s^2 against g (sin - mu cos) = 2.36). The element's b
    part, h alpha_i k (r - d0 - h v_n0) n, goes into rhs_out; its diagonal block stays out of the preconditioner (still
    SPD); it carries no friction this step (its overlap is kept as 0). `admissible_admitted_out` keeps a pair from being
    admitted twice."""
    a = wp.tid()
    if a >= admissible_count[0] or admissible_admitted_out[a] != 0:
        return
    idx = admissible_indices[a]
    rb = world_slot(particle_world_of(idx[0], particle_world, worlds), worlds, RELEASE_SIZE)
    if release_out[rb + RELEASE_ROUNDS] >= max_rounds:
        return
    alpha = admissible_weights[a]
    gap = admissible_gap[a]
    d = wp.length(gap)
    n = gap / d
    v_start = wp.dot(n, weighted_sum(alpha, v0[idx[0]], v0[idx[1]], v0[idx[2]], v0[idx[3]]))
    d_end = wp.length(gap + dt * pair_end_velocity(alpha, idx, v0, dv))  # (passing by, its distance along n would fall)
    if d_end > rest_distance - admit_depth(rest_distance):
        return
    e = wp.atomic_add(element_count_out, 0, 1)
    if e >= capacity:
        return
    admissible_admitted_out[a] = 1
    stiffness = admissible_stiffness[a]
    store_element(e, idx, alpha, n, 0.0, 0.0, wp.vec3(0.0), stiffness, admissible_coefficient[a], element_indices_out,
                  element_weights_out, element_normal_out, element_overlap_out, element_friction_mass_out,
                  element_friction_impulse_out, element_stiffness_out, element_coefficient_out)
    push = (dt * stiffness * (rest_distance - d - dt * v_start)) * n
    for r in range(4):
        wp.atomic_add(rhs_out, idx[r], alpha[r] * push)
    wp.atomic_add(counts_out, world_slot(particle_world_of(idx[0], particle_world, worlds), worlds, COUNT_SIZE) + COUNT_SELF_CONTACTS, 1)
    release_out[rb + RELEASE_FLAG] = 1
    release_out[RELEASE_FLAG] = 1


@wp.kernel(enable_backward=True)  # (a taped step's, on the tape: SolverImplicitEuler._taped_self_contact_friction)
def eval_self_contact_friction(
    element_count: wp.array(dtype=wp.int32),
    element_indices: wp.array(dtype=wp.vec4i),
    element_weights: wp.array(dtype=wp.vec4),
    element_normal: wp.array(dtype=wp.vec3),
    element_overlap: wp.array(dtype=float),
    element_friction_mass: wp.array(dtype=float),
    element_friction_impulse: wp.array(dtype=wp.vec3),
    element_stiffness: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    friction: float,
    dt: float,
    stick_speed: float,
    # outputs (accumulated; averaged per particle by kernels/selfcollide.py apply_velocity_changes)
    dv_sum_out: wp.array(dtype=wp.vec3),
    weight_out: wp.array(dtype=float),
):
    """Coulomb friction between the layers of each self-contact element (velocity level, as the self-collision pass's
    proximity impulses): the element's normal impulse over the step, lambda = h k ((r - d0) - h v_n) with v_n
    the pair's relative normal end velocity (the force linearised at the step's end, as the solve has it), slows the
    pair's relative tangential end velocity by mu lambda sum_r alpha_r^2 / m_r, at most to a stop. An element whose
    friction was in the solve (`self_contact_friction_terms`) only has its slip taken out where its damper held it
    within `stick_speed` [m/s] (no creep), or where the kinetic impulse reversed it (stopped)."""
    e = wp.tid()
    if e >= element_count[0]:
        return
    idx = element_indices[e]
    alpha = element_weights[e]
    n = element_normal[e]
    v_rel = pair_end_velocity(alpha, idx, v0, dv)
    mass_weight = inverse_mass_weight(alpha, idx, inv_mass)
    v_t = v_rel - wp.dot(v_rel, n) * n
    speed = wp.length(v_t)
    if mass_weight <= 0.0 or speed <= 0.0:
        return
    slide = element_friction_impulse[e]
    if element_friction_mass[e] > 0.0 or wp.dot(slide, slide) > 0.0:  # friction in the solve
        if (element_friction_mass[e] > 0.0 and speed <= SLIP_ALLOWANCE * stick_speed) or wp.dot(slide, v_t) > 0.0:
            add_impulse(idx, alpha, inv_mass, (-1.0 / mass_weight) * v_t, dv_sum_out, weight_out)
        return
    impulse = dt * element_stiffness[e] * (element_overlap[e] - dt * wp.dot(v_rel, n))
    if impulse <= 0.0:
        return
    keep = wp.max(1.0 - friction * impulse * mass_weight / speed, 0.0)
    add_impulse(idx, alpha, inv_mass, ((keep - 1.0) / mass_weight) * v_t, dv_sum_out, weight_out)
