"""Loss terms of differentiable rollouts; each accumulates into a one-element loss array."""

import warp as wp


@wp.kernel
def eval_position_loss(
    x: wp.array(dtype=wp.vec3),
    target: wp.array(dtype=wp.vec3),
    weight: float,
    # outputs (accumulated)
    loss_out: wp.array(dtype=float),
):
    """loss += weight |x_i - target_i|^2 [m^2]."""
    i = wp.tid()
    d = x[i] - target[i]
    wp.atomic_add(loss_out, 0, weight * wp.dot(d, d))


@wp.func
def nearest_point(p: wp.vec3, points: wp.array(dtype=wp.vec3)):
    """Index of the point of `points` nearest to p (brute force; the search itself is not differentiated)."""
    best = int(0)
    best_d = float(1.0e30)
    for k in range(points.shape[0]):
        d = wp.length_sq(p - points[k])
        if d < best_d:
            best_d = d
            best = k
    return best


@wp.kernel
def eval_nearest_loss(
    query: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    weight: float,
    # outputs (accumulated)
    loss_out: wp.array(dtype=float),
):
    """loss += weight min_k |query_i - points_k|^2 (one direction of the Chamfer distance)."""
    i = wp.tid()
    d = query[i] - points[nearest_point(query[i], points)]
    wp.atomic_add(loss_out, 0, weight * wp.dot(d, d))


@wp.kernel
def eval_nearest_loss_reverse(
    x: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    weight: float,
    # outputs (accumulated)
    loss_out: wp.array(dtype=float),
):
    """loss += weight min_i |points_k - x_i|^2 (the Chamfer direction from fixed points to the cloth)."""
    k = wp.tid()
    d = x[nearest_point(points[k], x)] - points[k]
    wp.atomic_add(loss_out, 0, weight * wp.dot(d, d))


@wp.kernel
def eval_weighted_sum(
    x: wp.array(dtype=wp.vec3),
    weight: wp.array(dtype=float),
    # outputs (accumulated)
    sum_out: wp.array(dtype=wp.vec3),
):
    """sum += weight_i x_i (a centroid when the weights are 1/n)."""
    i = wp.tid()
    wp.atomic_add(sum_out, 0, weight[i] * x[i])


@wp.kernel
def eval_point_loss(
    point: wp.array(dtype=wp.vec3),
    target: wp.vec3,
    weight: float,
    # outputs (accumulated)
    loss_out: wp.array(dtype=float),
):
    """loss += weight |point - target|^2."""
    d = point[0] - target
    wp.atomic_add(loss_out, 0, weight * wp.dot(d, d))


@wp.kernel
def gather_points(
    x: wp.array(dtype=wp.vec3),
    ids: wp.array(dtype=wp.int32),
    # outputs
    points_out: wp.array(dtype=wp.vec3),
):
    """points_out = x[ids] (a loss over selected particles)."""
    i = wp.tid()
    points_out[i] = x[ids[i]]


@wp.kernel
def eval_chord_angle_loss(
    tip: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    up: wp.vec3,
    angle: float,
    weight: float,
    # outputs (accumulated)
    loss_out: wp.array(dtype=float),
):
    """loss += weight (a - angle)^2 [rad^2], a = the chord origin -> tip's angle below horizontal."""
    d = tip[0] - origin
    rise = wp.dot(d, up)
    run = wp.length(d - rise * up)
    a = wp.atan2(-rise, run)
    wp.atomic_add(loss_out, 0, weight * (a - angle) * (a - angle))
