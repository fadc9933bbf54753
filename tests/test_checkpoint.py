"""Checkpoints: a fresh Simulator restored from a checkpoint continues bit for bit (CPU); two runs repeating bit for bit
is tests/test_faults.py::test_two_runs_give_bit_identical_caches."""

import io
import pathlib

import numpy as np
import pytest

import cloth_warp as cw
from cloth_warp.scene import PASSES_ONLY, build_model, build_solver, build_wind, load_scene

SCENES = pathlib.Path(__file__).resolve().parents[1] / "scenes"


def make_sim(name: str, overrides: dict) -> cw.Simulator:
    """A Simulator built from scratch from a shipped scene with overrides, as cloth_warp.runner builds it."""
    scene = load_scene(SCENES / f"{name}.toml", overrides)
    model = build_model(scene, "cpu")
    solver = build_solver(scene, model)
    return cw.Simulator(model, solver, fps=float(scene.get("output.fps")), substeps=int(scene.get("solver.substeps")),
                        adaptive=bool(scene.get("solver.adaptive")), dt_min=float(scene.get("solver.dt_min")), wind=build_wind(scene))


def through_npz(checkpoint: dict) -> dict:
    """The checkpoint as the runner stores it: an .npz without pickling, 0-d arrays back as scalars."""
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in checkpoint.items()})
    buf.seek(0)
    with np.load(buf, allow_pickle=False) as z:
        return {k: (z[k].item() if z[k].ndim == 0 else z[k]) for k in z.files}


def state(sim):
    return sim.state.particle_q.numpy().copy(), sim.state.particle_qd.numpy().copy()


# scenes ask for up to 128 strain-limit sweeps per step; explicit integrators at many substeps need far fewer
FEW_SWEEPS = {"solver.strain_limit_iterations": 4}

CONFIGS = {
    # name: (scene, overrides, frames N, checkpoint after K, what must hold at the checkpoint)
    "symplectic_captured": ("hanging_cloth", {"cloth.grid.resolution": [12, 12], "solver.integrator": "symplectic_euler",
                                              "solver.substeps": 32, **FEW_SWEEPS}, 12, 5, lambda sim: sim.capture and sim._graph is not None),
    "implicit_cg_warm": ("hanging_cloth", {"cloth.grid.resolution": [12, 12]}, 12, 5, lambda sim: sim.solver.has_previous),
    "implicit_jacobi_warm": ("hanging_cloth", {"cloth.grid.resolution": [8, 8], "solver.linear_solver": "jacobi", "solver.substeps": 4},
                             8, 3, lambda sim: sim.solver.has_previous),
    "adaptive": ("hanging_cloth", {"cloth.grid.resolution": [12, 12], "solver.integrator": "symplectic_euler", "solver.substeps": 2,
                                   "solver.adaptive": True, **FEW_SWEEPS}, 6, 2, lambda sim: sim.stepper.report.rejected > 0 and sim.stepper.dt < sim.dt),
    "collider_moving": ("sphere_shot", {"cloth.grid.resolution": [12, 12]}, 8, 2, lambda sim: sim.model.animated),
    "gusty_wind": ("flag", {"cloth.grid.resolution": [12, 8]}, 12, 5, lambda sim: not sim.wind.steady),
    "handles": ("curtain", {"cloth.grid.resolution": [8, 10]}, 24, 20, lambda sim: bool(sim.model.handles)),
    # the self-contacts' candidates in the solve are the last step's close pairs: without them in the checkpoint the
    # resumed pile's first step had no repulsion between its layers (velocities 0.25 m/s off)
    "contacts_in_solve": ("pile", {"cloth.grid.resolution": [16, 16], "solver.collider_contacts": "solve", "solver.self_contacts": "solve",
                                   "solver.contact_friction": "solve", "solver.tolerance": 1e-4}, 40, 36,
                          lambda sim: sim.frame_info["solve_self_contacts"] > 100),
}


def straight_and_resumed(name, overrides, n, k):
    """Simulators of a scene: one run N frames straight, one run K frames (checkpointed there), and a new one
    restored from that checkpoint through .npz and run the N - K frames left."""
    straight = make_sim(name, overrides)
    for _ in range(n):
        straight.step_frame()
    first = make_sim(name, overrides)
    for _ in range(k):
        first.step_frame()
    resumed = make_sim(name, overrides)
    resumed.restore(through_npz(first.checkpoint()))
    assert resumed.frame == k
    for _ in range(n - k):
        resumed.step_frame()
    return straight, first, resumed


@pytest.mark.parametrize("config", list(CONFIGS))
def test_restored_run_is_bit_identical(config):
    """Check N frames uninterrupted equal K frames, a checkpoint through .npz, a new model and Simulator restored
    from it, and N - K more frames: positions and velocities bit for bit, frame counter and time too."""
    name, overrides, n, k, holds = CONFIGS[config]
    straight, first, resumed = straight_and_resumed(name, overrides, n, k)
    assert holds(first), "the checkpoint is not taken where the state it must carry exists"
    for key, value in first.checkpoint().items():  # plain numpy arrays and Python scalars only
        assert isinstance(value, np.ndarray | bool | int | float | str), (key, type(value))
    q0, v0 = state(straight)
    q1, v1 = state(resumed)
    assert np.array_equal(q0, q1) and np.array_equal(v0, v1)
    assert resumed.frame == straight.frame and resumed.time == straight.time
    if straight.stepper is not None:
        assert resumed.stepper.dt == straight.stepper.dt and resumed.stepper.report.steps == straight.stepper.report.steps


def test_self_collision_restore_is_bit_identical():
    """Check the pile (self-collision, ground) resumes bit for bit after layers have met, broad-phase capacities and
    per-frame counters included."""
    overrides = {**PASSES_ONLY, "cloth.grid.resolution": [10, 10]}
    n, k = 30, 22
    straight = make_sim("pile", overrides)
    infos = []
    for _ in range(n):
        straight.step_frame()
        infos.append(dict(straight.frame_info))
    first = make_sim("pile", overrides)
    for _ in range(k):
        first.step_frame()
    assert sum(info["broad_phase_builds"] for info in infos[:k]) > 0
    resumed = make_sim("pile", overrides)
    resumed.restore(through_npz(first.checkpoint()))
    grids = [s.solver.pass_named("self_collision").self_collision.grid.checkpoint_state() for s in (first, resumed)]
    assert grids[0] == grids[1]  # buffers sized as the run it continues: same growth counters from here on
    for f in range(k, n):
        resumed.step_frame()
        assert resumed.frame_info == infos[f]
    q0, v0 = state(straight)
    q1, v1 = state(resumed)
    assert np.array_equal(q0, q1) and np.array_equal(v0, v1)
    assert sum(info["self_proximity"] + info["self_ccd"] for info in infos) > 0  # the layers did meet


def test_checkpoint_at_frame_zero_and_twice():
    """Check a checkpoint before any frame restores to the initial run, and restoring into a used Simulator (its
    captured graph kept) rewinds it."""
    overrides = {"cloth.grid.resolution": [8, 8], "solver.integrator": "symplectic_euler", "solver.substeps": 32, **FEW_SWEEPS}
    sim = make_sim("hanging_cloth", overrides)
    start = sim.checkpoint()
    for _ in range(4):
        sim.step_frame()
    q4, v4 = state(sim)
    after4 = sim.checkpoint()
    for _ in range(3):
        sim.step_frame()
    sim.restore(start)  # rewind the same simulator: its graph writes the same arrays
    for _ in range(4):
        sim.step_frame()
    assert np.array_equal(state(sim)[0], q4) and np.array_equal(state(sim)[1], v4)
    assert sim.frame == 4 and after4["frame"] == 4


def test_restore_refuses_another_scene():
    """Check restoring a checkpoint into a Simulator of another size, rate or solver raises ValueError naming it."""
    sim = make_sim("hanging_cloth", {"cloth.grid.resolution": [8, 8]})
    checkpoint = sim.checkpoint()
    with pytest.raises(ValueError, match="particles"):
        make_sim("hanging_cloth", {"cloth.grid.resolution": [6, 6]}).restore(checkpoint)
    with pytest.raises(ValueError, match="substeps"):
        make_sim("hanging_cloth", {"cloth.grid.resolution": [8, 8], "solver.substeps": 2}).restore(checkpoint)
    with pytest.raises(ValueError, match="solver"):
        make_sim("hanging_cloth", {"cloth.grid.resolution": [8, 8], "solver.integrator": "symplectic_euler"}).restore(checkpoint)
    with pytest.raises(ValueError, match="missing"):
        sim.restore({"particle_q": checkpoint["particle_q"]})


@pytest.mark.slow
@pytest.mark.parametrize("name, overrides, n, k", [
    ("twist", {"cloth.grid.resolution": [6, 20]}, 45, 35),
    ("drape_sphere", {**PASSES_ONLY, "cloth.grid.resolution": [16, 16]}, 40, 30),
])
def test_restored_run_is_bit_identical_slow(name, overrides, n, k):
    """As test_restored_run_is_bit_identical on handles turning a strip into self-contact, and on a drape over a ball."""
    straight, _, resumed = straight_and_resumed(name, overrides, n, k)
    assert all(np.array_equal(a, b) for a, b in zip(state(straight), state(resumed)))
