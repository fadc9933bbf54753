"""Collider contacts found for the implicit solve (kernels/contact.py): which particles touch, the normal, the
surface velocity and the prescribed normal speed that ends the step at the thickness."""

import numpy as np
import pytest
import trimesh
import warp as wp

import cloth_warp as cw
from cloth_warp.collision import collider_distance
from cloth_warp.kernels import contact as kct

DT = 1.0 / 120.0
THICKNESS = 0.01
MARGIN = 0.5


def find_contacts(model, x, v, time=0.0, dt=DT):
    control = model.control()
    model.update_control(control, time + dt, dt, force=True)
    n = len(x)
    out = [wp.zeros(n, dtype=wp.int32), wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=float),
           wp.zeros(1, dtype=wp.int32)]
    wp.launch(kct.eval_collider_contacts, dim=n,
              inputs=[model.particle_pinned, model.collider_count, model.collider_shape, model.collider_size, model.collider_mesh,
                      model.collider_deforming, model.collider_thickness, model.collider_static_friction,
                      model.collider_kinetic_friction, model.collider_mesh_max_distance, control.collider_transform_start,
                      control.collider_transform_end, wp.array(x, dtype=wp.vec3), wp.array(v, dtype=wp.vec3), dt, MARGIN],
              outputs=out)
    return [a.numpy() for a in out]


def particles(builder, points):
    for p in points:
        builder.add_particle(p)


def test_contacts_on_a_ground_plane():
    """Check who touches the ground (y = 0): resting within the margin, inside (pushed out), approaching fast
    enough to arrive this step; not: above the margin and slow, pinned; the push lands the step at the thickness."""
    b = cw.ModelBuilder()
    heights = [0.01, 0.012, 0.004, 0.1, 0.02, 0.01]
    speeds = [0.0, 0.0, 0.0, -12.0, 0.0, 0.0]  # the 4th covers 10 cm in one 1/120 s step
    particles(b, [(0.1 * k, y, 0.0) for k, y in enumerate(heights)])
    b.pin([5])
    b.add_ground(thickness=THICKNESS)
    m = b.finalize("cpu")
    x = np.array([(0.1 * k, y, 0.0) for k, y in enumerate(heights)], np.float32)
    v = np.array([(0.0, s, 0.0) for s in speeds], np.float32)
    col, normal, vel, push, count = find_contacts(m, x, v)
    np.testing.assert_array_equal(col, [0, 0, 0, 0, -1, -1])
    assert count[0] == 4
    np.testing.assert_allclose(normal[:4], [[0, 1, 0]] * 4, atol=1e-6)
    np.testing.assert_allclose(vel[:4], 0.0, atol=1e-6)
    np.testing.assert_allclose(push[:4], (THICKNESS - np.array(heights[:4])) / DT, rtol=1e-5, atol=1e-4)
    assert push[2] > 0.0 and push[3] < 0.0  # out from inside, down onto the surface from above


@pytest.mark.parametrize("shape", ["sphere", "box", "capsule", "cylinder", "mesh"])
def test_contact_normals_match_the_collider_distance(shape, rng):
    """Check, on every shape, that a particle near the surface gets the collider's outward normal and the push
    computed from its signed distance (`collision.collider_distance`, the post-solve pass's function)."""
    centre = (0.0, 0.5, 0.0)

    def with_collider(points):
        b = cw.ModelBuilder()
        particles(b, points)
        if shape == "sphere":
            b.add_sphere(centre, 0.2, thickness=THICKNESS)
        elif shape == "box":
            b.add_box(centre, (0.3, 0.2, 0.25), rotation=cw.quat_from_axis_angle((1, 1, 0), 30.0), thickness=THICKNESS)
        elif shape == "capsule":
            b.add_capsule(centre, 0.1, 0.3, axis=(1.0, 0.5, 0.0), thickness=THICKNESS)
        elif shape == "cylinder":
            b.add_cylinder(centre, 0.15, 0.3, thickness=THICKNESS)
        else:
            ico = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
            b.add_collider_mesh(ico.vertices, ico.faces, position=centre, thickness=THICKNESS)
        return b.finalize("cpu")

    model0 = with_collider([(0.0, 0.0, 0.0)])
    directions = rng.normal(size=(200, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    pts = np.array(centre) + 0.4 * directions
    # pull each point onto the surface along the distance function, then offset it to a random height
    for _ in range(4):
        d, n = collider_distance(model0, 0, pts)
        pts = pts - d[:, None] * n
    heights = rng.uniform(-0.5 * THICKNESS, 1.6 * THICKNESS, size=len(pts))
    _, n = collider_distance(model0, 0, pts)
    pts = (pts + heights[:, None] * n).astype(np.float32)
    d, n = collider_distance(model0, 0, pts)
    m = with_collider(pts)
    col, normal, vel, push, _ = find_contacts(m, pts, np.zeros_like(pts))
    touching = d < THICKNESS * (1.0 + MARGIN)
    clear = np.abs(d - THICKNESS * (1.0 + MARGIN)) > 1e-5  # away from the threshold's float32 rounding
    np.testing.assert_array_equal((col == 0)[clear], touching[clear])
    np.testing.assert_allclose(normal[touching], n[touching], atol=2e-5)
    np.testing.assert_allclose(push[touching], (THICKNESS - d[touching]) / DT, rtol=1e-4, atol=2e-3)


def test_contact_takes_a_moving_collider_surface_velocity():
    """Check a particle resting on a rising box lid gets the lid's velocity as the surface velocity."""
    b = cw.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_particle((0.0, 0.11, 0.0))
    b.add_box((0.0, 0.0, 0.0), (1.0, 0.2, 1.0), thickness=THICKNESS, keyframes=[(0.0, (0, 0, 0)), (2.0, (0, 2.0, 0))])
    m = b.finalize("cpu")
    col, normal, vel, push, _ = find_contacts(m, np.array([[0.0, 0.11, 0.0]], np.float32), np.zeros((1, 3), np.float32))
    assert col[0] == 0
    np.testing.assert_allclose(normal[0], [0, 1, 0], atol=1e-6)
    np.testing.assert_allclose(vel[0], [0.0, 1.0, 0.0], atol=1e-4)
