"""Attachments (ModelBuilder.attach): cloth particles bound to a mesh collider's surface follow it as it moves and
deforms, on the host path and in recorded frames."""

import numpy as np
import pytest
import trimesh

import cloth_warp as cw

FPS = 60


def breathing_ball():
    """An icosphere whose point cache breathes (radius x 1 .. 1.25) and sways 15 cm sideways over 2 s."""
    ico = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    times = np.linspace(0.0, 2.0, 21)
    cache = np.stack([ico.vertices * (1.0 + 0.25 * np.sin(np.pi * t)) + np.array([0.15 * np.sin(2 * np.pi * t), 0.0, 0.0]) for t in times])
    return ico, times, cache


def strip_on(b, height):
    """A 12 x 30 cm cotton strip hanging in the xy-plane, its top row at `height`, 2 mm in front of a 20 cm ball."""
    return b.add_cloth_grid(resolution=(6, 10), size=(0.12, 0.3), position=(-0.06, height - 0.3, 0.202), name="strip")


def follow_errors(sim, model, particles, frames):
    """Per frame, the largest distance [m] between the attached particles and their targets on the collider."""
    errors = []
    for f in range(1, frames + 1):
        sim.step_frame()
        target = model.attachments[0].targets(model.colliders[model.attachments[0].collider], f / FPS)
        errors.append(np.abs(sim.positions()[particles] - target).max())
    return np.array(errors)


def test_attached_particles_follow_a_deforming_body_every_frame():
    """Check a strip's top row bound to a breathing, swaying point-cache ball stays on its surface points (the offset
    it was bound with along the normal) to 1e-4 m in every frame of 1 s (measured 1.3e-7 m), moving with the surface:
    the attached particles' velocity is the surface point's over the step."""
    ico, times, cache = breathing_ball()
    b = cw.ModelBuilder()
    body = b.add_collider_mesh(ico.vertices, ico.faces, position=(0.0, 1.0, 0.0), point_cache=cache, point_cache_times=times, name="body")
    strip = strip_on(b, 1.0)
    top = strip.select("edge:top")
    start = b.particle_positions[top].copy()
    attachment = b.attach(top, body)
    # bound where they are (2-11 mm off the faceted surface): the target at time 0 is the particle itself
    np.testing.assert_allclose(attachment.targets(body, 0.0), start, atol=1e-12)
    from cloth_warp.colliders import mesh_signed_distance

    np.testing.assert_allclose(np.linalg.norm(attachment.offset, axis=1),
                               mesh_signed_distance(ico.vertices, ico.faces, start - [0.0, 1.0, 0.0]), atol=1e-12)
    model = b.finalize("cpu")
    sim = cw.Simulator(model, cw.SolverImplicitEuler(model), fps=FPS, substeps=2)
    errors = follow_errors(sim, model, top, 60)
    assert errors.max() < 1e-4, errors.max()
    h = 1.0 / (2 * FPS)
    t = 1.0
    moving = (attachment.targets(model.colliders[0], t) - attachment.targets(model.colliders[0], t - h)) / h
    np.testing.assert_allclose(sim.state.particle_qd.numpy()[top], moving, atol=1e-3)
    assert np.abs(moving).max() > 0.1  # the surface does move


def test_attachments_on_a_keyframed_body_replay_captured():
    """Check particles bound (offset 0: put onto the surface) to a rigid mesh collider that turns and travels by keyframes
    follow it to 1e-4 m in every frame, and that a recorded run (the targets written on the device) gives the
    uncaptured run's frames bit for bit."""
    ico = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    keys = [(0.0, (0.0, 0.0, 0.0)), (1.0, (0.3, 0.1, 0.0), cw.quat_from_axis_angle((0, 1, 0), 60.0))]

    def build():
        b = cw.ModelBuilder()
        body = b.add_collider_mesh(ico.vertices, ico.faces, position=(0.0, 1.0, 0.0), keyframes=keys, name="body")
        strip = strip_on(b, 1.0)
        top = strip.select("edge:top")
        a = b.attach(top, body, offset=0.0)
        np.testing.assert_allclose(body.distance(b.particle_positions[top]), 0.0, atol=1e-9)  # moved onto the surface
        np.testing.assert_allclose(a.targets(body, 0.0), b.particle_positions[top], atol=1e-12)
        return b.finalize("cpu"), top

    runs = []
    for capture in (True, False):
        model, top = build()
        sim = cw.Simulator(model, cw.SolverImplicitEuler(model), fps=FPS, substeps=2, capture=capture)
        assert sim.capture == capture
        errors = follow_errors(sim, model, top, 45)
        assert errors.max() < 1e-4, errors.max()
        # and independently of the targets' formula: on the surface of the body as posed at the end
        from cloth_warp.colliders import mesh_signed_distance
        from cloth_warp.model import quat_to_matrix

        p, q = model.colliders[0].pose_at(45 / FPS)
        local = (sim.positions()[top] - p) @ quat_to_matrix(q)
        np.testing.assert_allclose(mesh_signed_distance(ico.vertices, ico.faces, local), 0.0, atol=1e-5)
        runs.append(sim.positions())
    np.testing.assert_array_equal(runs[0], runs[1])


def test_attach_needs_a_mesh_collider_of_the_builder():
    b = cw.ModelBuilder()
    ball = b.add_sphere((0, 0, 0), 0.2)
    strip = strip_on(b, 0.2)
    with pytest.raises(ValueError, match="mesh collider"):
        b.attach(strip.select("edge:top"), ball)


SCARF = ('[cloth]\ngrid = { resolution = [4, 10], size = [0.1, 0.4] }\nposition = [-0.05, 0.95, 0.16]\nname = "scarf"\n'
         '[[colliders]]\ntype = "mannequin"\nmotion = "walk"\nname = "body"\n'
         '[[attachments]]\nselect = "edge:top"\ncollider = "body"\noffset = 0.005\n'
         '[solver]\nintegrator = "implicit_euler"\nsubsteps = 2\n[output]\nframes = 15\nfps = 60\n')


def test_a_scene_attaches_a_cloth_to_a_walking_mannequin(tmp_path):
    """Check [[attachments]] in a scene: a scarf's top edge bound to a walking mannequin's chest (put onto its surface,
    offset 0.005 m) follows it to 1e-4 m in every frame of 0.25 s."""
    from cloth_warp.scene import build_model, build_solver, load_scene

    path = tmp_path / "scarf.toml"
    path.write_text(SCARF)
    scene = load_scene(path)
    model = build_model(scene, "cpu")
    assert len(model.attachments) == 1 and len(model.attachments[0].particles) == 5
    sim = cw.Simulator(model, build_solver(scene, model), fps=FPS, substeps=2)
    errors = follow_errors(sim, model, model.attachments[0].particles, 15)
    assert errors.max() < 1e-4, errors.max()


def test_a_run_records_how_far_attachments_drift_in_every_frame(tmp_path):
    """Check a run's cache holds, per frame, the largest distance of an attached particle from its point on the body
    (`attachmentGap`, recomputed here from the cache's positions and the model's bindings), its summary the largest,
    and that the measure sees a particle moved off its point."""
    from cloth_warp.cache import CacheReader
    from cloth_warp.model import attachment_gap
    from cloth_warp.runner import run_scene
    from cloth_warp.scene import build_model, load_scene

    path = tmp_path / "scarf.toml"
    path.write_text(SCARF)
    out = tmp_path / "scarf.usdc"
    summary = run_scene(path, output=out, frames=8)
    assert summary["status"] == "complete" and 0.0 < summary["attachment_gap"] < 1e-4
    model = build_model(load_scene(path), "cpu")
    r = CacheReader(out)
    times, gaps = r.diagnostics()["attachmentGap"]
    assert len(gaps) == 8 and summary["attachment_gap"] == pytest.approx(max(gaps), rel=1e-6)
    for tc, gap in zip(times, gaps):
        assert gap == pytest.approx(attachment_gap(model, r.points(int(tc)), (tc - r.start_frame) / FPS), rel=1e-4, abs=1e-9)
    x = r.points(r.end_frame).astype(np.float64)
    attached = model.attachments[0].particles
    x[attached[2]] += [0.0, 0.003, 0.004]  # 5 mm off
    assert attachment_gap(model, x, 8 / FPS) == pytest.approx(0.005, abs=1e-4)
    assert attachment_gap(model, r.points(r.start_frame), 0.0) < 1e-6
