"""Recorded frames: every fixed-step frame of a shipped scene is recorded once as a graph and replayed; replays give
the frames an uncaptured run gives, bit for bit on the CPU (the same kernels in the same order: the linear solve,
the strain limiter and the self-collision sweeps loop on the device in both), with the same per-frame counters,
and a replayed frame issues no eager work."""

import numpy as np
import pytest

from cloth_warp import reductions
from cloth_warp.collision import SelfCollisionPass
from cloth_warp.profiling import LaunchCounter
from cloth_warp.scene import PASSES_ONLY
from intersections import intersecting_pairs
from test_checkpoint import make_sim

# name: (shipped scene, overrides, frames) -- each covers a pass kind or an animated input
CONFIGS = {
    "implicit_cg": ("hanging_cloth", {"cloth.grid.resolution": [10, 10]}, 6),
    "implicit_jacobi": ("hanging_cloth", {"cloth.grid.resolution": [6, 6], "solver.linear_solver": "jacobi", "solver.substeps": 8}, 4),
    "no_strain_limit": ("hanging_cloth", {"cloth.grid.resolution": [8, 8], "solver.strain_limit": 0.0}, 5),
    "handles": ("curtain", {"cloth.grid.resolution": [8, 10]}, 30),
    "moving_collider": ("sphere_shot", {"cloth.grid.resolution": [10, 10]}, 8),
    "gusty_wind": ("flag", {"cloth.grid.resolution": [9, 6]}, 8),
    "static_colliders": ("tablecloth", {**PASSES_ONLY, "cloth.grid.resolution": [12, 9]}, 20),
    "explicit_colliders": ("incline", {"cloth.grid.resolution": [8, 8], "solver.integrator": "symplectic_euler", "solver.substeps": 96,
                                       "solver.strain_limit_iterations": 8}, 6),
    "self_collision": ("pile", {**PASSES_ONLY, "cloth.grid.resolution": [10, 10]}, 30),
    "twist": ("twist", {"cloth.grid.resolution": [6, 16]}, 12),
    "contacts_in_solve": ("pile", {"cloth.grid.resolution": [12, 12], "solver.collider_contacts": "solve", "solver.self_contacts": "solve",
                                   "solver.contact_friction": "after"}, 40),
}


def run(name, overrides, frames, capture, setup=None, replay_loops=False):
    """The frames of a shipped scene, recorded and replayed (`capture`) or uncaptured: then every kernel launched one by
    one, or with `replay_loops` the implicit solver's linear-solve loops replayed as graphs (its default)."""
    sim = make_sim(name, overrides)
    if setup is not None:
        setup(sim)
    if not capture:
        sim.capture = False
        if sim.stepper is not None:
            sim.stepper.capture = False
        if hasattr(sim.solver, "replay_loops"):
            sim.solver.replay_loops = replay_loops
    out = []
    for _ in range(frames):
        sim.step_frame()
        out.append((sim.state.particle_q.numpy().copy(), sim.state.particle_qd.numpy().copy(), dict(sim.frame_info)))
    return sim, out


def assert_same_frames(a, b):
    for f, ((qa, va, ia), (qb, vb, ib)) in enumerate(zip(a, b)):
        assert np.array_equal(qa, qb) and np.array_equal(va, vb), f"frame {f + 1}: positions differ by {np.abs(qa - qb).max():.3g}"
        assert ia == ib, (f + 1, ia, ib)


@pytest.mark.parametrize("config", list(CONFIGS))
def test_replayed_frames_equal_uncaptured_frames(config):
    """Check each pass kind (strain limiter, colliders static and keyframed, self-collision), the implicit solver's
    CG and Jacobi loops, handles and the gusty wind run captured, and give the uncaptured run's frames and counters
    bit for bit (every kernel launched one by one, and with the linear solves' loops replayed as graphs, as an
    uncaptured run has them); once recorded, a frame is one replay with no eager launch, copy or fill."""
    name, overrides, frames = CONFIGS[config]
    sim, captured = run(name, overrides, frames, True)
    assert sim.capture and sim._graph is not None
    plain, uncaptured = run(name, overrides, frames, False)
    assert not plain.capture
    assert_same_frames(captured, uncaptured)
    if hasattr(plain.solver, "replay_loops"):
        assert_same_frames(uncaptured, run(name, overrides, frames, False, replay_loops=True)[1])
    with LaunchCounter() as counts:
        sim.step_frame()
    assert counts.replays == 1 and counts.eager == 0, counts.to_dict()
    assert counts.reads == 1, counts.to_dict()  # the frame's record block: statistics, solve record, every pass's counters


@pytest.mark.parametrize("config", ["implicit_cg", "contacts_in_solve"])
def test_block_reductions_give_the_per_thread_frames(config, monkeypatch):
    """Check the CUDA form of the reducing kernels (CG dot products and the strain limiter's excess summed or
    maximised per block, then one atomic per block: cloth_warp.reductions), forced on the CPU, where a block is
    one thread, gives the per-thread form's frames bit for bit: the same values combined in the same order."""
    name, overrides, frames = CONFIGS[config]
    _, plain = run(name, overrides, frames, True)
    monkeypatch.setattr(reductions, "USE_BLOCKS", True)
    _, blocks = run(name, overrides, frames, True)
    assert_same_frames(plain, blocks)


def test_overflowing_buffers_grow_and_the_frame_equals_an_uncaptured_run():
    """Check a self-collision pass whose pair buffers start far too small: the frame that overflowed is run again
    (its buffers grown), captured and uncaptured runs agree bit for bit, and no frame leaves intersecting triangles."""
    def small(sim):
        p = SelfCollisionPass(sim.model, pair_capacity=16)
        p.set_recordable(True)
        sim.solver.passes = tuple(p if q.name == p.name else q for q in sim.solver.passes)

    overrides = {**PASSES_ONLY, "cloth.grid.resolution": [12, 12]}
    sim, captured = run("pile", overrides, 30, True, small)
    plain, uncaptured = run("pile", overrides, 30, False, small)
    assert sim.capture and sim.reruns >= 1 and plain.reruns == sim.reruns
    caps = sim.solver.pass_named("self_collision").self_collision.capacities()
    assert min(caps["vertex_face"], caps["edge_edge"]) > 16, caps
    assert_same_frames(captured, uncaptured)
    tris = sim.model.tri_indices.numpy().reshape(-1, 3)
    assert sum(len(intersecting_pairs(q, tris)) for q, _, _ in captured) == 0


def test_adaptive_steps_replay_a_graph_per_step_size():
    """Check adaptive stepping records a trial step once per step size and replays it: with steps rejected and
    retried at half the size, the frames and counters equal an uncaptured adaptive run bit for bit, and a frame
    issues replays instead of its steps' launches."""
    overrides = {"cloth.grid.resolution": [8, 8], "solver.integrator": "symplectic_euler", "solver.substeps": 12,
                 "solver.adaptive": True}
    sim, captured = run("hanging_cloth", overrides, 6, True)
    plain, uncaptured = run("hanging_cloth", overrides, 6, False)
    assert sim.stepper.capture and not plain.stepper.capture
    assert len(sim.stepper._graphs) >= 2  # the nominal step and at least one smaller one
    assert sum(info["rejected"] for _, _, info in captured) >= 1
    assert_same_frames(captured, uncaptured)
    with LaunchCounter() as counts:
        sim.step_frame()
    assert counts.replays >= 1 and counts.launches == 0, counts.to_dict()


def test_a_deforming_collider_records_its_frames_with_host_refits_between_graphs(tmp_path):
    """Check a cloth lying on a deforming ball read from a USD point cache (growing from 15 to 30 cm radius in 1 s:
    the walking body's kind of collider) is recorded on the CPU: its frames are graphs with the ball's BVH refit as
    a host call between them, one per step (Warp 1.19 does not record wp.Mesh.refit into a CPU graph), and give
    the uncaptured run's frames and counters bit for bit while the ball lifts the cloth (a graph querying the
    tree of its recording would leave the cloth inside the grown ball). Once recorded, a frame is steps + 1
    replays, the refits and nothing else eager."""
    import cloth_warp as cw
    from cloth_warp.scene import build_model, build_solver, load_scene
    from test_colliders import _growing_ball_cache, growing_ball_scene

    r0, _ = _growing_ball_cache(tmp_path / "body.usda")
    scene = growing_ball_scene(tmp_path, r0, substeps=3)
    frames = []
    for capture in (True, False):
        sc = load_scene(scene)
        m = build_model(sc, "cpu")
        s = cw.Simulator(m, build_solver(sc, m), fps=float(sc.get("output.fps")), substeps=3, capture=capture)
        assert s.capture == capture and s.animator.host_calls
        out = []
        for _ in range(24):
            s.step_frame()
            out.append((s.state.particle_q.numpy().copy(), s.state.particle_qd.numpy().copy(), dict(s.frame_info)))
        frames.append(out)
        if capture:
            with LaunchCounter() as counts:
                s.step_frame()
            assert s._graph.host_calls == 3
            assert counts.replays == 4 and counts.eager == 3 and counts.launches == 3, counts.to_dict()
            assert counts.reads == 1, counts.to_dict()
    assert all(info["collider_contacts"] > 0 for _, _, info in frames[0][5:])
    assert frames[0][-1][0][:, 1].max() > r0 + 0.1  # lifted by the growing ball (r = 0.27 m at 0.8 s)
    assert_same_frames(*frames)


def test_a_frame_recorded_late_equals_the_first_recording_and_eager_frames():
    """Check a run whose frame graph is recorded again midway (as after a re-run) gives the frames of the graph recorded
    at its start and of an uncaptured run, with every contact in the solve: a 9² pile folding onto itself, recorded
    again at frame 26. (The self-collision pass allocated its capturable buffers inside the first recording, whose
    graph then cleared the close pairs the next step's self-contacts start from in every frame: 3-5 mm off an
    uncaptured run from frame 27.)"""
    overrides = {"cloth.grid.resolution": [9, 9], "scene.seed": 2, "material.preset": "cotton", "solver.collider_contacts": "solve",
                 "solver.self_contacts": "solve", "solver.contact_friction": "solve", "solver.tolerance": 1e-4}

    def again_at_26(sim):
        step = sim.step_frame

        def stepped():
            stats = step()
            if sim.frame == 26:
                sim._graph = None  # the next frame is recorded again
            return stats

        sim.step_frame = stepped

    _, first = run("pile", overrides, 40, True)
    _, late = run("pile", overrides, 40, True, again_at_26)
    _, eager = run("pile", overrides, 40, False)
    assert_same_frames(first, late)
    assert_same_frames(first, eager)
