"""Animated control on the device: handle pin targets, collider poses, point-cache colliders and gusty wind
evaluated from a device clock, so a frame's control updates can be captured into a graph.

Each function repeats, operation for operation, the host formula it replaces (``cloth_warp.model``:
``interpolate_keyframes``, ``_slerp``, ``quat_to_matrix``, ``quat_multiply``, ``Handle.targets``;
``Collider.pose_at`` / ``vertices_at``; ``GustyWind.at``): times, weights and transforms in float64, one
rounding to float32 where the result is stored. The module is compiled without floating-point contraction
(``fuse_fp`` off: no FMA on the CPU or CUDA) so each product and sum is rounded as numpy rounds it.

The clock is ``wp.array(dtype=wp.float64)`` of shape (2,): [time at the end of the step [s], dt [s]].
Keyframe tables are concatenated per animated object, object j's keyframes being
``first[j] .. first[j + 1] - 1``; quaternions are vec4d (x, y, z, w) as given (not normalised).
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})


@wp.func
def keyframe_segment(times: wp.array(dtype=wp.float64), first: int, last: int, time: wp.float64):
    """The largest k in [first, last) with times[k] <= time, for times[first] < time < times[last]
    (numpy's ``searchsorted(times, time, side="right") - 1``)."""
    lo = first
    hi = last
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if times[mid] <= time:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def dot4(a: wp.vec4d, b: wp.vec4d):
    """a . b, summed in index order."""
    return ((a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]) + a[3] * b[3]


@wp.func
def slerp(q0: wp.vec4d, q1: wp.vec4d, s: wp.float64):
    """Spherical interpolation of quaternions (x, y, z, w) at fraction s, along the shorter arc (normalised
    first; linear and renormalised where they are within acos(0.9995))."""
    a = q0 / wp.sqrt(dot4(q0, q0))
    b = q1 / wp.sqrt(dot4(q1, q1))
    d = dot4(a, b)
    if d < wp.float64(0.0):
        b = -b
        d = -d
    one = wp.float64(1.0)
    if d > wp.float64(0.9995):
        q = a + s * (b - a)
        return q / wp.sqrt(dot4(q, q))
    theta = wp.acos(d)
    return (wp.sin((one - s) * theta) * a + wp.sin(s * theta) * b) / wp.sin(theta)


@wp.func
def interpolate_keyframes(
    key_times: wp.array(dtype=wp.float64),
    key_translations: wp.array(dtype=wp.vec3d),
    key_rotations: wp.array(dtype=wp.vec4d),
    first: int,
    last: int,
    time: wp.float64,
):
    """(translation [m], quaternion (x, y, z, w)) of keyframes first..last at `time` [s]: linear / slerp
    between keyframes, held (as given) before the first and after the last."""
    if time <= key_times[first]:
        return key_translations[first], key_rotations[first]
    if time >= key_times[last]:
        return key_translations[last], key_rotations[last]
    k = keyframe_segment(key_times, first, last, time)
    s = (time - key_times[k]) / (key_times[k + 1] - key_times[k])
    t = (wp.float64(1.0) - s) * key_translations[k] + s * key_translations[k + 1]
    return t, slerp(key_rotations[k], key_rotations[k + 1], s)


@wp.func
def quat_multiply(a: wp.vec4d, b: wp.vec4d):
    """Hamilton product a * b of quaternions (x, y, z, w): rotate by b, then by a."""
    return wp.vec4d(
        a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
        a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
        a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
        a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2],
    )


@wp.func
def rotate(q: wp.vec4d, r: wp.vec3d):
    """R(q) r for a quaternion (x, y, z, w) (normalised first), through the rotation matrix's rows."""
    u = q / wp.sqrt(dot4(q, q))
    x = u[0]
    y = u[1]
    z = u[2]
    w = u[3]
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    row0 = wp.vec3d(one - two * (y * y + z * z), two * (x * y - z * w), two * (x * z + y * w))
    row1 = wp.vec3d(two * (x * y + z * w), one - two * (x * x + z * z), two * (y * z - x * w))
    row2 = wp.vec3d(two * (x * z - y * w), two * (y * z + x * w), one - two * (x * x + y * y))
    return wp.vec3d(
        (r[0] * row0[0] + r[1] * row0[1]) + r[2] * row0[2],
        (r[0] * row1[0] + r[1] * row1[1]) + r[2] * row1[2],
        (r[0] * row2[0] + r[1] * row2[1]) + r[2] * row2[2],
    )


@wp.func
def to_vec3(v: wp.vec3d):
    """Round a float64 vector to float32 (nearest)."""
    return wp.vec3(wp.float32(v[0]), wp.float32(v[1]), wp.float32(v[2]))


@wp.func
def to_transform(p: wp.vec3d, q: wp.vec4d):
    """A float32 wp.transform from a float64 position [m] and quaternion (x, y, z, w), each entry rounded."""
    return wp.transform(to_vec3(p), wp.quat(wp.float32(q[0]), wp.float32(q[1]), wp.float32(q[2]), wp.float32(q[3])))


@wp.kernel
def advance_clock(dt: wp.float64, clock_out: wp.array(dtype=wp.float64)):
    """Start the next step: one more step since the clock's origin, time = origin + steps x dt [s] (from the count,
    not summed step by step: a run restored at any step has the same clock as one that went through), length dt."""
    steps = clock_out[3] + wp.float64(1.0)
    clock_out[3] = steps
    clock_out[0] = clock_out[2] + steps * dt
    clock_out[1] = dt


@wp.kernel
def handle_pin_targets(
    clock: wp.array(dtype=wp.float64),
    # handles
    key_first: wp.array(dtype=wp.int32),
    key_times: wp.array(dtype=wp.float64),
    key_translations: wp.array(dtype=wp.vec3d),
    key_rotations: wp.array(dtype=wp.vec4d),
    handle_pivot: wp.array(dtype=wp.vec3d),
    # handle particles
    member_particle: wp.array(dtype=wp.int32),
    member_handle: wp.array(dtype=wp.int32),
    member_rest: wp.array(dtype=wp.vec3d),
    # outputs
    pin_target_out: wp.array(dtype=wp.vec3),
):
    """Pin target [m] of one handle particle at the clock's time: its rest position turned by the handle's
    interpolated rotation R about the pivot c and moved by its translation t, x = R (x_rest - c) + c + t."""
    i = wp.tid()
    h = member_handle[i]
    t, q = interpolate_keyframes(key_times, key_translations, key_rotations, key_first[h], key_first[h + 1] - 1,
                                 clock[0])
    c = handle_pivot[h]
    x = rotate(q, member_rest[i] - c) + c + t
    pin_target_out[member_particle[i]] = to_vec3(x)


@wp.kernel
def collider_poses(
    clock: wp.array(dtype=wp.float64),
    key_first: wp.array(dtype=wp.int32),
    key_times: wp.array(dtype=wp.float64),
    key_translations: wp.array(dtype=wp.vec3d),
    key_rotations: wp.array(dtype=wp.vec4d),
    initial_position: wp.array(dtype=wp.vec3d),
    initial_rotation: wp.array(dtype=wp.vec4d),
    # outputs
    pose_start_out: wp.array(dtype=wp.transform),
    pose_end_out: wp.array(dtype=wp.transform),
):
    """One collider's pose (world <- local) at the start (time - dt) and end (time) of the step: the
    keyframe transform applied after the initial pose, p = p0 + t, q = q_key q0 (p0, q0 without keyframes)."""
    j = wp.tid()
    p0 = initial_position[j]
    q0 = initial_rotation[j]
    first = key_first[j]
    last = key_first[j + 1] - 1
    time = clock[0]
    if last < first:
        pose_start_out[j] = to_transform(p0, q0)
        pose_end_out[j] = to_transform(p0, q0)
        return
    t0, r0 = interpolate_keyframes(key_times, key_translations, key_rotations, first, last, time - clock[1])
    t1, r1 = interpolate_keyframes(key_times, key_translations, key_rotations, first, last, time)
    pose_start_out[j] = to_transform(p0 + t0, quat_multiply(r0, q0))
    pose_end_out[j] = to_transform(p0 + t1, quat_multiply(r1, q0))


@wp.func
def point_cache_vertex(times: wp.array(dtype=wp.float64), cache: wp.array2d(dtype=wp.vec3), i: int, time: wp.float64):
    """Vertex i [m] of a point cache (samples, vertices) at `time` [s]: linear between samples, held outside."""
    last = times.shape[0] - 1
    if time <= times[0]:
        return wp.vec3d(cache[0, i])
    if time >= times[last]:
        return wp.vec3d(cache[last, i])
    k = keyframe_segment(times, 0, last, time)
    w = (time - times[k]) / (times[k + 1] - times[k])
    return (wp.float64(1.0) - w) * wp.vec3d(cache[k, i]) + w * wp.vec3d(cache[k + 1, i])


@wp.kernel
def point_cache_vertices(
    clock: wp.array(dtype=wp.float64),
    times: wp.array(dtype=wp.float64),
    cache: wp.array2d(dtype=wp.vec3),
    # outputs
    points_out: wp.array(dtype=wp.vec3),
    velocities_out: wp.array(dtype=wp.vec3),
):
    """A deforming collider's vertex at the end of the step [m] and its velocity over the step,
    (x(time) - x(time - dt)) / dt [m/s] (0 when dt = 0)."""
    i = wp.tid()
    time = clock[0]
    dt = clock[1]
    end = point_cache_vertex(times, cache, i, time)
    v = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    if dt > wp.float64(0.0):
        v = (end - point_cache_vertex(times, cache, i, time - dt)) / dt
    points_out[i] = to_vec3(end)
    velocities_out[i] = to_vec3(v)


@wp.kernel
def attachment_pin_targets(
    particles: wp.array(dtype=wp.int32),
    triangles: wp.array(dtype=wp.vec3i),
    weights: wp.array(dtype=wp.vec3),
    offset: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    collider: int,
    collider_transform_end: wp.array(dtype=wp.transform),
    # outputs
    pin_target_out: wp.array(dtype=wp.vec3),
):
    """An attached particle's target [m]: its triangle's point at fixed barycentric weights plus its `offset` in the
    triangle's frame (first edge, across it, unit normal; cloth_warp.model.triangle_frames), on the collider's current
    local vertices (`points`), placed by its end-of-step pose."""
    k = wp.tid()
    t = triangles[k]
    w = weights[k]
    a = points[t[0]]
    b = points[t[1]]
    c = points[t[2]]
    e1 = wp.normalize(b - a)
    n = wp.normalize(wp.cross(b - a, c - a))
    o = offset[k]
    local = w[0] * a + w[1] * b + w[2] * c + o[0] * e1 + o[1] * wp.cross(n, e1) + o[2] * n
    pin_target_out[particles[k]] = wp.transform_point(collider_transform_end[collider], local)


@wp.func
def gust_signal(omega: wp.vec4d, phase: wp.vec4d, time: wp.float64):
    """sqrt(1/2) sum_j sin(omega_j time + phase_j): unit RMS (omega [rad/s], phase [rad]), summed in index order
    as numpy sums four terms."""
    a0 = wp.sin(omega[0] * time + phase[0])
    a1 = wp.sin(omega[1] * time + phase[1])
    a2 = wp.sin(omega[2] * time + phase[2])
    a3 = wp.sin(omega[3] * time + phase[3])
    return wp.sqrt(wp.float64(0.5)) * (((a0 + a1) + a2) + a3)


@wp.kernel
def gusty_wind(
    clock: wp.array(dtype=wp.float64),
    time_offset: wp.float64,
    mean: wp.vec3d,
    strength: wp.float64,
    turn: wp.float64,
    up: wp.vec3d,
    speed_omega: wp.vec4d,
    speed_phase: wp.vec4d,
    turn_omega: wp.vec4d,
    turn_phase: wp.vec4d,
    deg_to_rad: wp.float64,
    # outputs
    wind_out: wp.array(dtype=wp.vec3),
):
    """Wind velocity [m/s] at clock time + time_offset [s]: the mean scaled by 1 + strength g(t) and turned
    about `up` by turn h(t) degrees (Rodrigues), g and h the unit-RMS gust signals."""
    time = clock[0] + time_offset
    one = wp.float64(1.0)
    w = mean * (one + strength * gust_signal(speed_omega, speed_phase, time))
    angle = turn * gust_signal(turn_omega, turn_phase, time) * deg_to_rad
    c = wp.cos(angle)
    s = wp.sin(angle)
    k_dot_w = (up[0] * w[0] + up[1] * w[1]) + up[2] * w[2]
    wind_out[0] = to_vec3(w * c + wp.cross(up, w) * s + up * k_dot_w * (one - c))
