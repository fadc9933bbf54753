"""Fitting one scene to many targets at once (``cloth-warp fit SCENE --target A --target B ...``).

A :class:`BatchFit` fits the same scene keys to each of N target caches, as N :class:`~cloth_warp.fitting.SceneFit`
runs would, but simulates them as one batch (:mod:`cloth_warp.worlds`): world k is the scene with target k's
current values, one taped :class:`~cloth_warp.gradients.Rollout` steps and differentiates all of them, and one loss
per world (:func:`~cloth_warp.worlds.world_losses`) gives each world the gradient of its own run and its own loss.
Each world then takes its own Adam steps (:class:`~cloth_warp.fitting.FitRun`) from its own gradient, carried to its
scene keys by its own :meth:`SceneFit.chain_rule <cloth_warp.fitting.SceneFit.chain_rule>` on its slice of the
batch's arrays (:func:`~cloth_warp.worlds.element_worlds`). On the CPU every world's fit equals its single fit bit for
bit (tests/test_batch_fit.py); on a GPU the batch fills the device where one small cloth cannot.

What a batch shares, a batched fit cannot fit per target: the wind and the colliders' friction
(:data:`~cloth_warp.worlds.SHARED_TABLES`). Losses: ``positions`` and ``final`` (the Chamfer loss, the scene's
centroid and chord-angle targets: one target at a time, with ``SceneFit``). A world whose loss or gradient is not
finite stops fitting (its result ``failed``, with the message) while the others go on.
"""

from __future__ import annotations

import re
import time
from collections.abc import Sequence

import numpy as np
import warp as wp

from .fitting import FitResult, FitRun, SceneFit, load_build
from .gradients import Rollout, model_grad_arrays
from .scene import Scene, SceneError, build_solver, with_values
from .worlds import SHARED_TABLES, build_worlds, element_worlds, world_losses

BATCHED_LOSSES = ("positions", "final")
"""The losses a batched fit takes (a position loss per world over that world's particles)."""
_SHARED_KEYS = re.compile(r"^(forces\.|colliders\[)")


class BatchFit:
    """Fit `parameters` of `scene` to each of `targets` at once, one world per target.

    Args:
        scene: the scene; its values are every world's start.
        targets: target caches (paths or :class:`~cloth_warp.cache.CacheReader`) or {frame: points} dicts, one per
            world; each must have at least `frames` frames.
        parameters, loss, frames, checkpoint_every, solver_tolerance: as :class:`~cloth_warp.fitting.SceneFit`
            (``loss``: one of :data:`BATCHED_LOSSES`).
        device: the batch's Warp device (the per-world bookkeeping stays on the CPU).
    """

    def __init__(self, scene: Scene, targets: Sequence, parameters: list[str] | None = None, *, loss: str | None = None,
                 frames: int | None = None, checkpoint_every=None, device=None, solver_tolerance: float | None = None):
        if len(targets) < 1:
            raise SceneError("fit: no targets")
        loss = scene.get("fit.loss") if loss is None else loss
        if loss not in BATCHED_LOSSES:
            raise SceneError(f"loss: {loss!r} is not batched; with several targets use {' or '.join(BATCHED_LOSSES)} "
                             "(or fit one target at a time)")
        parameters = scene.get("fit.params") if parameters is None else parameters
        for spec in parameters or []:
            if _SHARED_KEYS.match(spec):
                raise SceneError(f"--param {spec}: the worlds of a batch share it ({', '.join(SHARED_TABLES)}); fit it with one "
                                 "target at a time")
        # one single-world fit per target: its parameters, target, chain rule and optimizer (its own model and
        # solver are only built, on the CPU: the batch simulates)
        self.fits = [SceneFit(scene, t, parameters, loss=loss, frames=frames, checkpoint_every=checkpoint_every, device="cpu",
                              solver_tolerance=solver_tolerance) for t in targets]
        lengths = sorted({f.frames for f in self.fits})
        if len(lengths) > 1:
            raise SceneError(f"fit: the targets have {lengths[0]} to {lengths[-1]} frames; give --frames N (at most "
                             f"{lengths[0]}) to fit the same frames of each")
        first = self.fits[0]
        self.scene, self.frames, self.loss_kind, self.tolerance = scene, first.frames, first.loss_kind, first.tolerance
        self.device = wp.get_device(device)
        self.model = build_worlds(self._scenes(), self.device, requires_grad=True)
        self.owners = element_worlds(self.model)
        for k, fit in enumerate(self.fits):
            for name, array in model_grad_arrays(fit.model).items():
                if name in self.owners and int(np.sum(self.owners[name] == k)) != array.shape[0]:
                    raise AssertionError(f"world {k}: {name} has {array.shape[0]} elements alone, "
                                         f"{int(np.sum(self.owners[name] == k))} in the batch")
        self.loss = world_losses(self.model, [{s: t.numpy() for s, t in f.loss.targets.items()} for f in self.fits])
        tight = self.tolerance.tolerance
        self.solver = build_solver(scene if tight is None else with_values(scene, {"solver.tolerance": tight}), self.model)
        self.rollout = Rollout(self.model, self.solver, dt=first.dt, steps=first.rollout.steps, checkpoint_every=first.rollout.segment)
        self.evaluations = 0

    def _scenes(self, values: Sequence[list[np.ndarray]] | None = None) -> list[Scene]:
        if values is None:
            values = [None] * len(self.fits)
        return [fit._scene_with(fit._values(v)) for fit, v in zip(self.fits, values)]

    def loss_and_gradient(self, values: Sequence[list[np.ndarray]]) -> tuple[np.ndarray, list[list[np.ndarray]]]:
        """Each world's loss at its parameter values (`values[k]`: one array per parameter, as
        :attr:`SceneFit.parameters` orders them) and its gradient with respect to each of them, from one taped
        rollout of the batch."""
        load_build(build_worlds(self._scenes(values), "cpu", requires_grad=True), self.model, (self.rollout, self.loss))
        state0 = self.model.state(requires_grad=True)
        self.loss.term_values()  # (reset)
        self.rollout.gradient(self.loss, state0)
        losses = self.loss.term_values()
        self.evaluations += 1
        grads = {name: a.grad.numpy().astype(np.float64) for name, a in model_grad_arrays(self.model).items() if name in self.owners}
        grads["particle_qd"] = state0.particle_qd.grad.numpy().astype(np.float64)
        shared = {name: np.zeros(a.shape) for name, a in model_grad_arrays(self.model).items() if name not in self.owners}
        out = []
        for k, (fit, v) in enumerate(zip(self.fits, values)):
            # (no fitted key reaches an array the worlds share, the colliders' friction: refused above)
            own = {name: g[self.owners[name] == k] for name, g in grads.items()}
            out.append(fit.chain_rule(v, {**shared, **own}))
        return losses, out

    def run(self, iterations: int = 50, learning_rate: float = 0.05, decay: float = 0.1, progress=None,
            betas: tuple[float, float] | None = None) -> list[FitResult]:
        """Adam per world, as :meth:`SceneFit.run` per target (the same schedule and bounds); returns one
        :class:`~cloth_warp.fitting.FitResult` per target, and leaves each world's best values in the batch's model and
        solver and in that world's fit (:attr:`fits`, for :func:`~cloth_warp.fitting.write_fit_outputs`).
        `progress(iteration, iterations, losses)` is called after every evaluation of the batch. Ctrl-C ends every
        world's fit with its best values so far (status ``interrupted``)."""
        t0 = time.perf_counter()
        runs = [FitRun(f, iterations, learning_rate, decay, betas) for f in self.fits]
        failed: dict[int, str] = {}
        status = "complete"
        try:
            for it in range(iterations):
                values = [r.values() if k not in failed else r.best[1] for k, r in enumerate(runs)]
                losses, grads = self.loss_and_gradient(values)
                for k, (r, v, loss, g) in enumerate(zip(runs, values, losses, grads)):
                    if k in failed:
                        continue
                    try:
                        r.step(it, v, float(loss), g, {})
                    except FloatingPointError as exc:
                        failed[k] = str(exc)
                if progress is not None:
                    progress(it + 1, iterations, [float(x) for x in losses])
                if len(failed) == len(runs):
                    break
        except KeyboardInterrupt:
            status = "interrupted"
        results = []
        for k, r in enumerate(runs):
            result = r.result("failed" if k in failed else status)
            if k in failed:
                result.measured = {"failure": failed[k]}
            result.wall_s = time.perf_counter() - t0  # (the batch's: the worlds ran together)
            results.append(result)
        load_build(build_worlds(self._scenes(), "cpu", requires_grad=True), self.model, (self.rollout, self.loss))
        return results
