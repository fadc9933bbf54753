"""Batched worlds (cloth_warp.worlds): each world of a batch steps exactly as it does alone."""

import numpy as np
import pytest
import warp as wp

from cloth_warp.runner import find_scene, load_kernels
from cloth_warp.scene import build_model, build_solver, build_wind, load_scene
from cloth_warp.simulator import Simulator
from cloth_warp.worlds import build_worlds, split_worlds

FRAMES = 12


def _run(model, scene, frames=FRAMES):
    solver = build_solver(scene, model)
    load_kernels(solver, model.device)
    sim = Simulator(model, solver, fps=float(scene.get("output.fps")), substeps=int(scene.get("solver.substeps")), wind=build_wind(scene))
    sweeps = []
    for _ in range(frames):
        sim.step_frame()
        sweeps.append(sim.frame_report.passes["strain_limit"].sweeps if "strain_limit" in sim.frame_report.passes else 0)
    return sim, sum(sweeps)


def _check_batch(name, variants):
    scenes = [load_scene(find_scene(name), v) for v in variants]
    singles = [_run(build_model(s, "cpu"), s) for s in scenes]
    batch, _ = _run(build_worlds(scenes, "cpu"), scenes[0])
    assert batch.model.world_count == len(scenes)
    for k, (x, (single, _)) in enumerate(zip(split_worlds(batch.model, batch.positions()), singles)):
        assert np.array_equal(x, single.positions()), f"world {k} differs from its single run by {np.abs(x - single.positions()).max():.3g} m"
    return singles


@pytest.mark.parametrize("seed", [0, 1])
def test_batched_worlds_equal_their_single_runs_bit_for_bit(seed):
    """Worlds of different sizes and materials (so their CG iteration counts and strain-limit sweeps differ per step),
    batched in one model, each equal to its own run on the CPU bit for bit."""
    rng = np.random.default_rng(seed)
    presets = ["cotton", "silk", "denim", "wool"]
    variants = [{"material.preset": presets[int(rng.integers(len(presets)))], "cloth.grid.resolution": [int(rng.integers(6, 14)), int(rng.integers(6, 14))],
                 "solver.strain_limit": 0.03, "scene.seed": int(rng.integers(100)), "cloth.jitter": 0.002} for _ in range(3)]
    singles = _check_batch("hanging_cloth", variants)
    sweeps = [s for _, s in singles]
    its = [single.frame_report.iterations for single, _ in singles]
    # the test's point: worlds that differ in their work per step (limiter sweeps and CG iterations)
    assert max(sweeps) > 0 and len(set(sweeps)) > 1 and len(set(its)) > 1, (sweeps, its)


def test_batched_worlds_share_colliders():
    """Drapes over the same ball (a collider shared by the worlds) in three materials."""
    _check_batch("drape_sphere", [{"cloth.grid.resolution": [8, 8], "collision.self_collision": False, "material.preset": p}
                                  for p in ("cotton", "silk", "denim")])


def test_batched_worlds_refuse_what_they_do_not_share():
    base = load_scene(find_scene("hanging_cloth"), {"cloth.grid.resolution": [4, 4]})
    with pytest.raises(ValueError, match="solver"):
        build_worlds([base, load_scene(find_scene("hanging_cloth"), {"cloth.grid.resolution": [4, 4], "solver.tolerance": 1e-5})], "cpu")
    drape = {"cloth.grid.resolution": [4, 4]}
    with pytest.raises(ValueError, match="self-collision"):
        build_worlds([load_scene(find_scene("drape_sphere"), drape)] * 2, "cpu")
    model = build_worlds([base, base], "cpu")
    with pytest.raises(ValueError, match="batched worlds"):
        build_solver(load_scene(find_scene("hanging_cloth"), {"solver.collider_contacts": "solve"}), model)
    with pytest.raises(ValueError, match="batched worlds"):
        Simulator(model, build_solver(base, model), adaptive=True)


def test_one_world_model_is_unbatched():
    scene = load_scene(find_scene("hanging_cloth"), {"cloth.grid.resolution": [4, 4]})
    m = build_model(scene, "cpu")
    assert m.world_count == 1 and not m.particle_world.numpy().any()
    assert list(m.world_particle_start) == [0, m.particle_count]
