"""Batched worlds: several independent cloths stepped together, one launch per stage for all of them.

A batch is one :class:`~cloth_warp.Model` whose particles belong to W worlds (``Model.particle_world``; each world's
particles contiguous, ``Model.world_particle_start``). Elements never join two worlds, so every per-element and
per-particle kernel is already per world; what couples cloths in one model is what reduces over it, and those
reductions are kept per world:

- the implicit solver's CG (kernels/implicit.py): r.s, c.Ac and r.r, alpha and beta, the stop test, the warm start and
  the record per world; the loop runs while any world iterates, and a world that stopped keeps its dv, residual and
  direction (the per-particle kernels skip it), so each world gets exactly its own solve;
- the strain limiter (kernels/constraints.py): the excess, the stop test and the record per world, the sweeps
  only in the worlds still above the tolerance.

On the CPU, where a kernel's threads run in order and each world's atomics add in its own order, every world equals
its single-world run bit for bit (tests/test_worlds.py). A world that stopped still pays the element products
(springs, bends, membranes, drag) until the last world stops: gating them per element cost more than it saved
(benchmarks/bench_worlds.py).

The worlds of a batch share the colliders (each scene's must be the same) and the global settings (gravity, damping,
up axis, the [solver] table): they are variants of one scene in their cloths (material, size, mesh, pins, handles,
initial state). Not batched yet: self-collision, contacts in the solve, block Jacobi, taped strain limiting, per-world
diagnostics, divergence and caches, attachments.
"""

from __future__ import annotations

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

    if not scenes:
        raise ValueError("build_worlds: no scenes")
    for k, scene in enumerate(scenes[1:], 1):
        for key in SHARED_TABLES:
            if _resolved(scenes[0], key) != _resolved(scene, key):
                raise ValueError(f"world {k}: {key} differs from world 0's; batched worlds share {', '.join(SHARED_TABLES)}")
    batch = ModelBuilder()
    for k, scene in enumerate(scenes):
        b = scene_builder(scene, device)
        if b.self_collision:
            raise ValueError(f"world {k}: self-collision is not batched yet (collision.self_collision = false)")
        batch.add_world(b)
    return batch.finalize(device, requires_grad=requires_grad)


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


def split_worlds(model: Model, values: np.ndarray) -> list[np.ndarray]:
    """Per-particle values (positions, velocities) cut into one array per world."""
    return [values[sl] for sl in world_slices(model)]
