"""Batched worlds: several independent cloths stepped together, one launch per stage for all of them.

A batch is one :class:`~cloth_warp.Model` whose particles belong to W worlds (``Model.particle_world``; each world's
particles contiguous, ``Model.world_particle_start``). Elements never join two worlds, so every per-element and
per-particle kernel is already per world; what couples cloths in one model is what reduces over it, and those
reductions are kept per world:

- the implicit solver's CG (kernels/implicit.py): r.s, c.Ac and r.r, alpha and beta, the stop test and the warm start
  per world; the loop runs while any world iterates and a world that stopped takes steps of zero, so each world
  gets exactly its own solve (on the CPU, where a kernel's threads run in order, bit for bit its single-world
  result).

The worlds of a batch share the colliders (each scene's must be the same) and the global settings (gravity, damping,
up axis): they are variants of one scene in their cloths (material, size, mesh, pins, handles, initial state).
Not batched yet: the strain limiter's and self-collision's loops, contacts in the solve, block Jacobi, per-world
diagnostics and divergence, attachments.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .model import Model


def build_worlds(scenes: Sequence, device=None, requires_grad: bool = False) -> Model:
    """One :class:`~cloth_warp.Model` holding each scene (:class:`~cloth_warp.scene.Scene`) as an independent world,
    in order. The scenes may differ in their cloths; see the module for what they must share."""
    from .builder import ModelBuilder
    from .scene import scene_builder

    if not scenes:
        raise ValueError("build_worlds: no scenes")
    batch = ModelBuilder()
    for k, scene in enumerate(scenes):
        b = scene_builder(scene, device)
        if b.self_collision:
            raise ValueError(f"world {k}: self-collision is not batched yet (collision.self_collision = false)")
        batch.add_world(b)
    return batch.finalize(device, requires_grad=requires_grad)


def world_slices(model: Model) -> list[slice]:
    """Each world's particles in the model's flat arrays."""
    s = model.world_particle_start
    return [slice(int(s[k]), int(s[k + 1])) for k in range(model.world_count)]


def split_worlds(model: Model, values: np.ndarray) -> list[np.ndarray]:
    """Per-particle values (positions, velocities) cut into one array per world."""
    return [values[sl] for sl in world_slices(model)]
