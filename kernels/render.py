"""Preview ray caster: one ray per pixel against the BVH of cloth and colliders, Lambert shading with
shadows, a ground plane.

Forward-only (previews are never differentiated).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def sky_color(direction: wp.vec3, up: wp.vec3):
    s = wp.clamp(wp.dot(direction, up), -1.0, 1.0)
    return wp.lerp(wp.vec3(0.80, 0.83, 0.86), wp.vec3(0.46, 0.62, 0.82), wp.max(s, 0.0))


@wp.func
def in_shadow(mesh: wp.uint64, origin: wp.vec3, light_dir: wp.vec3):
    hit = wp.mesh_query_ray(mesh, origin, light_dir, 1.0e6)
    return hit.result


@wp.kernel
def render_cloth(
    mesh: wp.uint64,
    tri_indices: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=wp.vec3),
    eye: wp.vec3,
    forward: wp.vec3,
    right: wp.vec3,
    cam_up: wp.vec3,
    tan_half_fov: float,
    width: int,
    height: int,
    up: wp.vec3,
    light_dir: wp.vec3,
    ground_height: float,
    checker_size: float,
    front_colors: wp.array(dtype=wp.vec3),
    back_color: wp.vec3,
    tri_material: wp.array(dtype=wp.int32),
    collider_color: wp.vec3,
    pixels_out: wp.array(dtype=wp.vec3),
):
    """Shade pixel (tid % width, tid // width) (row 0 at the top), linear RGB in [0, 1]."""
    tid = wp.tid()
    px = tid % width
    py = tid // width
    aspect = float(width) / float(height)
    sx = (2.0 * (float(px) + 0.5) / float(width) - 1.0) * tan_half_fov * aspect
    sy = (1.0 - 2.0 * (float(py) + 0.5) / float(height)) * tan_half_fov
    d = wp.normalize(forward + sx * right + sy * cam_up)
    color = sky_color(d, up)
    ambient = 0.28
    eps = 1.0e-4

    t_ground = float(1.0e30)
    denom = wp.dot(d, up)
    if denom < -1.0e-6:
        t_ground = (ground_height - wp.dot(eye, up)) / denom

    hit = wp.mesh_query_ray(mesh, eye, d, 1.0e6)
    if hit.result and hit.t < t_ground:
        f = hit.face
        n0 = vertex_normals[tri_indices[3 * f + 0]]
        n1 = vertex_normals[tri_indices[3 * f + 1]]
        n2 = vertex_normals[tri_indices[3 * f + 2]]
        n = n0 * hit.u + n1 * hit.v + n2 * (1.0 - hit.u - hit.v)
        if wp.length(n) < 1.0e-8:
            n = hit.normal
        n = wp.normalize(n)
        albedo = front_colors[f]
        if wp.dot(n, d) > 0.0:  # two-sided: shade the side facing the camera
            n = -n
            albedo = back_color
        if tri_material[f] != 0:
            albedo = collider_color
        p = eye + hit.t * d
        diffuse = wp.max(wp.dot(n, light_dir), 0.0)
        if diffuse > 0.0:
            if in_shadow(mesh, p + n * eps, light_dir):
                diffuse = 0.0
        # A little rim light keeps silhouettes readable in shadow.
        rim = 0.12 * wp.pow(1.0 - wp.abs(wp.dot(n, d)), 2.0)
        color = albedo * (ambient + (1.0 - ambient) * diffuse) + wp.vec3(rim, rim, rim)
    elif t_ground < 1.0e29:
        p = eye + t_ground * d
        # Checker in the ground plane: coordinates along two axes orthogonal to up.
        a = wp.normalize(wp.cross(up, right))
        b = wp.cross(a, up)
        i = int(wp.floor(wp.dot(p, a) / checker_size))
        j = int(wp.floor(wp.dot(p, b) / checker_size))
        shade = 0.78
        if (i + j) % 2 == 0:
            shade = 0.70
        light = 1.0
        if in_shadow(mesh, p + up * eps, light_dir):
            light = 0.55
        fade = wp.exp(-0.02 * t_ground)
        ground = wp.vec3(shade, shade, shade) * light
        color = wp.lerp(sky_color(d, up), ground, fade)
    pixels_out[tid] = color
