"""Batched worlds: several independent cloths stepped together, one launch per stage for all of them.

A batch is one :class:`~cloth_warp.Model` whose particles belong to W worlds (``Model.particle_world``; each world's
particles contiguous, ``Model.world_particle_start``). Elements never join two worlds, so every per-element and
per-particle kernel is already per world; what couples cloths in one model is what reduces over it, and those
reductions are kept per world:

- the implicit solver's CG (kernels/implicit.py): r.s, c.Ac and r.r, alpha and beta, the stop test, the warm start and
  the record per world; the loop runs while any world iterates, and a world that stopped keeps its dv, residual and
  direction (the per-particle kernels skip it), so each world gets exactly its own solve;
- block Jacobi (the same kernels): each world's residual check, stop and iteration count;
- collider contacts in the solve: each world's release flag, re-solve rounds and contact counts; a re-solve takes
  only the worlds that released a contact, the others keep their solve as it was;
- the strain limiter (kernels/constraints.py): the excess, the stop test and the record per world, the sweeps
  only in the worlds still above the tolerance.

On the CPU, where a kernel's threads run in order and each world's atomics add in its own order, every world equals
its single-world run bit for bit (tests/test_worlds.py). The CG's iteration there runs one thread per world
(kernels/implicit.py cg_*_worlds, over :func:`world_ranges`): each walks its world's elements and particles in the
order the one-item kernels take them, and a world that stopped costs one test while the batch's slowest iterates.
With one thread per item (CUDA's form; ``SolverImplicitEuler.world_threads = False``) a stopped world's items
still cost 2-8 ns each every iteration (gating them per element cost more than it saved): a batch of 64 worlds of
four materials ran at 0.86x their one-by-one runs that way, 1.07x with a thread per world, in one run
(benchmarks/bench_worlds.py; a single cloth's CG takes the one-thread kernels as well).

The worlds of a batch share the colliders (each scene's must be the same) and the global settings (gravity, damping,
up axis, the [solver] table): they are variants of one scene in their cloths (material, size, mesh, pins, handles,
initial state).

Each world is checked on its own (:class:`~cloth_warp.simulator.Simulator` with a batch: ``world_stats``, ``world_solves``,
``world_failures``): a world that diverges gets its diagnosis and is held at its last good state while the others
go on. :func:`run_worlds` steps a batch and writes one cache per world (a diverged world's closed as ``diverged``
with the frames before it). Gradients: a taped rollout of a batch (:class:`~cloth_warp.gradients.Rollout`) with one
loss per world (:func:`world_losses`) gives every world its own run's gradient; taped strain limiting sweeps each world
only while it is above the limit, as the forward path does, and its adjoint replays the same worlds per sweep.
Attachments bind each world's particles to the shared colliders. A batch's checkpoint keeps its diverged worlds and
each world's warm start. Self-collision runs one pass per world on the world's own model (``Model.world_models``,
:class:`~cloth_warp.collision.WorldSelfCollisionPass`), the self-contacts in the solve from each world's pass. Not batched
yet: taped steps with self-collision; :func:`run_worlds`
does not resume its caches.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Sequence

import numpy as np

from .model import Model


SHARED_TABLES = ("forces", "colliders", "collision", "solver", "output.fps")
"""The scene tables (and keys) every world of a batch shares: one solver steps them all, against the same colliders."""


def build_worlds(scenes: Sequence, device=None, requires_grad: bool = False) -> Model:
    """One :class:`~cloth_warp.Model` holding each scene (:class:`~cloth_warp.scene.Scene`) as an independent world,
    in order. The scenes may differ in their cloths (the [scene], [cloth], [material], [pins], [handles] tables);
    :data:`SHARED_TABLES` they must share (a clear error names the first that differs)."""
    from .builder import ModelBuilder
    from .scene import scene_builder

    check_batchable(scenes)
    batch = ModelBuilder()
    builders = [scene_builder(scene, device) for scene in scenes]
    for b in builders:
        batch.add_world(b)
    model = batch.finalize(device, requires_grad=requires_grad)
    if model.self_collision:  # each world's self-collision runs on its own model (WorldSelfCollisionPass)
        model.world_models = [b.finalize(device) for b in builders]
    return model


def check_batchable(scenes: Sequence) -> None:
    """Refuse (ValueError naming the first key) scenes that cannot be worlds of one batch: none, a table of
    :data:`SHARED_TABLES` that differs from the first scene's. Reads the scenes only (no model is built): the gate
    :func:`build_worlds` and a batched sweep check before anything runs."""
    if not scenes:
        raise ValueError("build_worlds: no scenes")
    for k, scene in enumerate(scenes[1:], 1):
        for key in SHARED_TABLES:
            if _resolved(scenes[0], key) != _resolved(scene, key):
                raise ValueError(f"world {k}: {key} differs from world 0's; batched worlds share {', '.join(SHARED_TABLES)}")


def _resolved(scene, key: str):
    """A scene key's value, or a table's values with the schema's defaults filled in (arrays of tables as written)."""
    from .scene import SCHEMA, Key

    node = SCHEMA
    for part in key.split("."):
        node = node[part]
    if isinstance(node, Key):
        return scene.get(key)
    if type(node) is dict:
        return {name: _resolved(scene, f"{key}.{name}") for name in node}
    return scene.data.get(key)  # an array of tables ([[colliders]])


def world_slices(model: Model) -> list[slice]:
    """Each world's particles in the model's flat arrays."""
    s = model.world_particle_start
    return [slice(int(s[k]), int(s[k + 1])) for k in range(model.world_count)]


def world_ranges(model: Model) -> np.ndarray:
    """Where each world's items start in each kind of the model's arrays, int32 (RANGE_KINDS, W + 1) in the rows of
    kernels/worlds.py RANGE_* (particles, linear springs, bend triples, membranes, triangles, plate stencils), each row
    ending with the kind's count: the ranges the one-thread-per-world kernels walk. An element's world is its first
    particle's, and each kind's elements are ordered by world (the builder concatenates the worlds)."""
    from .kernels.worlds import RANGE_KINDS

    world = model.particle_world.numpy() if model.world_count > 1 else np.zeros(model.particle_count, np.int32)
    springs = model.spring_ends.numpy()[:, 0] if model.spring_count else np.zeros(0, int)
    bends = model.bend_triples.numpy()[:, 0] if model.spring_count > model.linear_spring_count else np.zeros(0, int)
    first = [np.arange(model.particle_count), springs[:model.linear_spring_count], bends,
             model.membrane_vertices.numpy()[:, 0] if model.membrane_count else np.zeros(0, int),
             model.tri_vertices.numpy()[:, 0] if model.tri_count else np.zeros(0, int),
             model.plate_points.numpy()[model.plate_offsets.numpy()[:-1]] if model.plate_count else np.zeros(0, int)]
    assert len(first) == RANGE_KINDS
    ranges = np.zeros((RANGE_KINDS, model.world_count + 1), np.int32)
    for k, items in enumerate(first):
        owners = world[items]
        if np.any(np.diff(owners) < 0):
            raise ValueError(f"world_ranges: kind {k}'s items are not ordered by world")
        ranges[k] = np.searchsorted(owners, np.arange(model.world_count + 1))
    return ranges


def split_worlds(model: Model, values: np.ndarray) -> list[np.ndarray]:
    """Per-particle values (positions, velocities) cut into one array per world."""
    return [values[sl] for sl in world_slices(model)]


def element_worlds(model: Model) -> dict[str, np.ndarray]:
    """For each differentiable model array (:func:`~cloth_warp.gradients.model_grad_arrays`, but the colliders'
    friction, which the worlds share), the world of each of its elements: the particle arrays by ``particle_world``,
    the springs, triangles, membranes and plate stencils by their first particle. Taken in order, a world's elements
    are its own model's, in its own model's order (the builder concatenates worlds, and sorts springs stably by
    their first particle, which the world offsets keep in order): ``array[owners == k]`` is world k's array."""
    world = model.particle_world.numpy()
    first = {"spring": model.spring_indices.numpy().reshape(-1, 2)[:, 0], "tri": model.tri_indices.numpy().reshape(-1, 3)[:, 0],
             "membrane": model.membrane_vertices.numpy().reshape(-1, 3)[:, 0]}
    first["plate"] = model.plate_points.numpy()[model.plate_offsets.numpy()[:-1]] if model.plate_count else np.zeros(0, int)
    from .gradients import model_grad_arrays

    out = {}
    for name in model_grad_arrays(model):
        family = name.split("_")[0]
        if family == "particle":
            out[name] = world
        elif family in first:
            out[name] = world[first[family]]
    return out


def world_losses(model: Model, targets: Sequence[dict]):
    """One :class:`~cloth_warp.gradients.PositionLoss` per world (`targets[k]`: {step: that world's target
    positions}) over that world's particles, summed (:class:`~cloth_warp.gradients.LossSum`): a rollout of the batch
    then gives each world the gradient of its own run with its own loss (bit for bit on the CPU), and each world's
    loss (``LossSum.term_values()``)."""
    from .gradients import LossSum, PositionLoss

    slices = world_slices(model)
    if len(targets) != len(slices):
        raise ValueError(f"world_losses: {len(targets)} targets for {len(slices)} worlds")
    return LossSum((PositionLoss(t, device=model.device, particles=np.arange(sl.start, sl.stop)) for t, sl in zip(targets, slices)),
                   record_terms=True, device=model.device)


@dataclasses.dataclass(frozen=True)
class WorldResult:
    """One world of a :func:`run_worlds` batch: its cache, ``complete`` or ``diverged``, the frames written
    (the initial state included), for a diverged world the diagnosis, the largest strain at a frame's end, and the
    world's particle count."""

    world: int
    output: pathlib.Path
    status: str
    frames_written: int
    message: str = ""
    max_strain: float = 0.0
    particles: int = 0


def run_worlds(scenes: Sequence, outputs: Sequence, frames: int | None = None, device=None) -> list[WorldResult]:
    """Simulate the scenes as one batch (:func:`build_worlds`) for `frames` frames (default: the first scene's
    ``output.frames``) and write world k's frames to ``outputs[k]`` (a cache :func:`~cloth_warp.cache.open_cache`
    writes, as ``cloth-warp run`` would for that scene alone: frame 0 is the initial state). A world that diverges
    does not stop the others: its cache is closed at once with status ``diverged`` and the diagnosis; the batch
    stops only when every world has."""
    import json

    from .cache import open_cache
    from .scene import build_model, build_solver, build_wind
    from .simulator import Simulator

    if len(outputs) != len(scenes):
        raise ValueError(f"run_worlds: {len(scenes)} scenes but {len(outputs)} outputs")
    if len({pathlib.Path(o).resolve() for o in outputs}) != len(outputs):
        raise ValueError("run_worlds: two worlds write the same output")
    first = scenes[0]
    model = build_worlds(scenes, device)
    solver = build_solver(first, model)
    fps = float(first.get("output.fps"))
    n_frames = int(frames if frames is not None else first.get("output.frames"))
    sim = Simulator(model, solver, fps=fps, substeps=int(first.get("solver.substeps")), wind=build_wind(first))
    slices = world_slices(model)
    writers = []
    try:
        for k, (scene, out) in enumerate(zip(scenes, outputs)):
            # the world's own model: its cache's meshes, UVs and colliders (built with the batch when it has self-collision)
            alone = model.world_models[k] if model.world_models else build_model(scene, device)
            meta = {"scene_path": str(scene.path) if scene.path else None,
                    "resolved_scene": json.dumps(scene.resolved(), sort_keys=True),
                    "batch": json.dumps({"world": k, "worlds": len(scenes)}), "integrator": solver.name,
                    "frames_requested": n_frames}
            writers.append(open_cache(out, alone, fps=fps, save_every=int(scene.get("output.save_every")),
                                      normals=bool(scene.get("output.normals")), velocities=bool(scene.get("output.velocities")),
                                      metadata=meta))
        q, qd = sim.state.particle_q.numpy(), sim.state.particle_qd.numpy()
        for w, sl in zip(writers, slices):
            w.write(q[sl], qd[sl])
        results: dict[int, WorldResult] = {}
        strain = [0.0] * len(scenes)
        for _ in range(n_frames):
            try:
                sim.step_frame()
            except Exception:
                if len(sim.world_failures) != len(scenes):
                    raise
            q, qd = sim.state.particle_q.numpy(), sim.state.particle_qd.numpy()
            for k, (w, sl) in enumerate(zip(writers, slices)):
                if k in results:
                    continue
                failure = sim.world_failures.get(k)
                if failure is not None:
                    w.close("diverged", {"message": str(failure)})
                    results[k] = WorldResult(k, w.path, "diverged", w.saved_frames, str(failure), strain[k], sl.stop - sl.start)
                    continue
                stats = sim.world_stats[k]
                strain[k] = max(strain[k], float(stats.max_strain))
                solves = sim.world_solves[k] if sim.world_solves is not None else None
                w.write(q[sl], qd[sl], {"maxStrain": stats.max_strain, "dt": sim.dt,
                                        "solverIterations": solves.iterations if solves else 0,
                                        "solverResidual": solves.last_residual if solves else 0.0})
            if len(results) == len(scenes):
                break
        for k, w in enumerate(writers):
            if k not in results:
                w.close("complete")
                results[k] = WorldResult(k, w.path, "complete", w.saved_frames, max_strain=strain[k],
                                         particles=slices[k].stop - slices[k].start)
        return [results[k] for k in range(len(scenes))]
    except BaseException as exc:
        for w in writers:
            if not w.closed:
                w.close("interrupted" if isinstance(exc, KeyboardInterrupt) else "failed")
        raise
