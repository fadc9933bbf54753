"""Differentiable rollouts: losses over a run, taped steps and checkpointed backward passes.

A :class:`Rollout` advances a model T steps with any solver and returns a loss and its gradient. Gradients
land in the ``.grad`` of what the loss depends on: the model's differentiable arrays (``particle_mass``,
``spring_stiffness``, ``spring_damping``, ``spring_rest_length``, ``tri_drag``, ``membrane_stiffness``,
``membrane_damping``, ``plate_stiffness``, collider friction), the
initial state's ``particle_q`` / ``particle_qd``, the control's ``wind`` and, for animated handles, each
step's pin targets (folded into per-keyframe translation gradients, :attr:`Rollout.handle_gradients`)::

    model = builder.finalize("cpu", requires_grad=True)
    rollout = cw.Rollout(model, cw.SolverImplicitEuler(model), dt=1 / 60, steps=120, checkpoint_every="auto")
    loss = cw.PositionLoss({120: target_positions})
    value = rollout.gradient(loss)                  # forward + backward
    d_stiffness = model.spring_stiffness.grad.numpy()

Checkpointing (``checkpoint_every=S``): the forward pass keeps only every S-th state; the backward pass
re-runs each segment under its own tape, from the last segment to the first, seeding it with the
gradient of the segment's end state. Peak memory then grows like T/S + S states (about 2 sqrt(T) at
S = sqrt(T), "auto") instead of T, for one extra forward pass. Forward passes take the same code path as
the taped ones (fixed strain-limit sweeps, no warm start), so re-runs reproduce them exactly.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .kernels import losses as kl
from .model import Control, Model, ModelFlags, State
from .solvers.base import SolverBase


class Loss:
    """A loss over a rollout: a sum of terms evaluated at some steps (taped when the rollout is)."""

    steps: frozenset = frozenset()

    def evaluate(self, step: int, state: State, out: wp.array):
        """Add the terms of `step` to `out` (one float) with kernel launches."""
        raise NotImplementedError

    def notify_model_changed(self, flags: int) -> None:
        """Refresh what the loss derived from the model when it was built (:class:`~cloth_warp.model.ModelFlags`)."""

    def end_segment(self) -> None:
        """A rollout evaluated the loss over one segment (:meth:`Rollout.gradient` after each taped segment,
        :meth:`Rollout.forward` after the whole run)."""


class PositionLoss(Loss):
    """Mean squared distance [m^2] between the particles and target positions.

    L = 1 / (K n) sum_k sum_i |x_i(t_k) - y_i^k|^2 over the K target steps (n particles, or the selected
    `particles`). With one target step it is a final-shape loss.
    """

    def __init__(self, targets: dict[int, np.ndarray], device=None, particles=None):
        if not targets:
            raise ValueError("PositionLoss needs at least one target step")
        self.steps = frozenset(int(k) for k in targets)
        self.particles = None if particles is None else wp.array(np.asarray(particles, np.int32), dtype=wp.int32, device=device)
        self.targets = {int(k): wp.array(np.asarray(v, np.float32).reshape(-1, 3), dtype=wp.vec3, device=device) for k, v in targets.items()}
        count = next(iter(self.targets.values())).shape[0]
        self.weight = 1.0 / (len(self.targets) * count)

    def evaluate(self, step, state, out):
        target = self.targets[step]
        x = state.particle_q
        if self.particles is not None:
            x = _gather(x, self.particles)
        if x.shape[0] != target.shape[0]:
            raise ValueError(f"target of step {step} has {target.shape[0]} points, the cloth {x.shape[0]}")
        wp.launch(kl.eval_position_loss, dim=target.shape[0], inputs=[x, target, self.weight], outputs=[out], device=x.device)


class LossSum(Loss):
    """The sum of losses, each evaluated at its own steps. With batched worlds (:mod:`cloth_warp.worlds`) one loss
    per world over that world's particles (:func:`cloth_warp.worlds.world_losses`) fits every world at once: a world's
    parameters reach only its own term, so each gets the gradient of its own run (tests/test_worlds.py)."""

    def __init__(self, losses, record_terms: bool = False, device=None):
        self.losses = list(losses)
        if not self.losses:
            raise ValueError("LossSum needs at least one loss")
        self.steps = frozenset().union(*(loss.steps for loss in self.losses))
        self.terms = None
        """With `record_terms`: each loss's value as well, one float per loss on `device` (:meth:`term_values`)."""
        self._term_totals = np.zeros(len(self.losses))
        if record_terms:
            self.terms = wp.zeros(len(self.losses), dtype=float, device=device, requires_grad=True)

    def evaluate(self, step, state, out):
        for k, loss in enumerate(self.losses):
            if step in loss.steps:
                loss.evaluate(step, state, out)
                if self.terms is not None:  # (taped too: its adjoint is zero, the gradients unchanged)
                    loss.evaluate(step, state, self.terms[k:k + 1])

    def end_segment(self) -> None:
        if self.terms is not None:  # each segment's terms (float32) summed in float64, as the rollout sums its loss
            self._term_totals += self.terms.numpy().astype(np.float64)
            self.terms.zero_()

    def term_values(self, reset: bool = True) -> np.ndarray:
        """Each loss's value over the rollout segments since the last reset (each segment's float32 value summed in
        float64, as :meth:`Rollout.gradient` sums the loss: a world's loss in a batch is its single run's bit for bit);
        then reset."""
        values = self._term_totals.copy()
        if reset:
            self._term_totals[:] = 0.0
        return values

    def notify_model_changed(self, flags: int) -> None:
        for loss in self.losses:
            loss.notify_model_changed(flags)


class ChamferLoss(Loss):
    """Symmetric Chamfer distance [m^2] to target point sets (targets on a different mesh).

    L = 1/K sum_k [mean_i min_j |x_i - y_j|^2 + mean_j min_i |y_j - x_i|^2]; nearest points by brute force
    (O(n m) per target step), the gradient flows through the matched pairs.
    """

    def __init__(self, targets: dict[int, np.ndarray], device=None):
        if not targets:
            raise ValueError("ChamferLoss needs at least one target step")
        self.steps = frozenset(int(k) for k in targets)
        self.targets = {int(k): wp.array(np.asarray(v, np.float32).reshape(-1, 3), dtype=wp.vec3, device=device) for k, v in targets.items()}

    def evaluate(self, step, state, out):
        y = self.targets[step]
        x = state.particle_q
        k = len(self.targets)
        wp.launch(kl.eval_nearest_loss, dim=x.shape[0], inputs=[x, y, 1.0 / (k * x.shape[0])], outputs=[out], device=x.device)
        wp.launch(kl.eval_nearest_loss_reverse, dim=y.shape[0], inputs=[x, y, 1.0 / (k * y.shape[0])], outputs=[out], device=x.device)


class CentroidLoss(Loss):
    """Squared distance [m^2] of the (mass-weighted) centroid of the particles to a target point at one step."""

    def __init__(self, target, step: int, model: Model):
        self.steps = frozenset([int(step)])
        self.target = wp.vec3(*np.asarray(target, float))
        self.model = model
        self.weights = wp.zeros(model.particle_count, dtype=float, device=model.device)
        """m_i / sum_j m_j, shape (n,): held fixed under the tape (no gradient to the masses through them)."""
        self._read_weights()

    def _read_weights(self):
        m = self.model.particle_mass.numpy().astype(np.float64)
        self.weights.assign((m / m.sum()).astype(np.float32))

    def notify_model_changed(self, flags: int) -> None:
        """New masses (PARTICLE_PROPERTIES): new centroid weights."""
        if flags & ModelFlags.PARTICLE_PROPERTIES:
            self._read_weights()

    def centroid(self, x: wp.array) -> wp.array:
        return _weighted_sum(x, self.weights)

    def evaluate(self, step, state, out):
        x = state.particle_q
        wp.launch(kl.eval_point_loss, dim=1, inputs=[self.centroid(x), self.target, 1.0], outputs=[out], device=x.device)

    def measure(self, state: State) -> dict:
        """The centroid [m] of `state` and its distance [m] to the target (for reports)."""
        c = self.centroid(state.particle_q).numpy()[0].astype(float)
        return {"centroid": [float(v) for v in c], "distance_m": float(np.linalg.norm(c - np.asarray(self.target, float)))}


class ChordAngleLoss(Loss):
    """Squared difference [rad^2] between a chord's angle below horizontal and a target angle at one step.

    The chord runs from a fixed `origin` [m] (a cantilever's clamp edge) to the centroid of the `tip`
    particles; "horizontal" is the plane normal to the model's up axis. For the ASTM D1388 cantilever
    test the target is 41.5 deg at overhang 2c (c the bending length).
    """

    def __init__(self, angle_deg: float, tip, step: int, model: Model, origin=(0.0, 0.0, 0.0)):
        self.steps = frozenset([int(step)])
        self.angle = math.radians(float(angle_deg))
        self.origin = wp.vec3(*np.asarray(origin, float))
        self.up = wp.vec3(0.0, 0.0, 1.0) if model.up_axis == "Z" else wp.vec3(0.0, 1.0, 0.0)
        tip = np.asarray(tip, np.int64)
        if tip.size == 0:
            raise ValueError("ChordAngleLoss: no tip particles")
        w = np.zeros(model.particle_count, np.float32)
        w[tip] = 1.0 / tip.size
        self.weights = wp.array(w, dtype=float, device=model.device)

    def tip(self, x: wp.array) -> wp.array:
        return _weighted_sum(x, self.weights)

    def evaluate(self, step, state, out):
        x = state.particle_q
        wp.launch(kl.eval_chord_angle_loss, dim=1, inputs=[self.tip(x), self.origin, self.up, self.angle, 1.0], outputs=[out],
                  device=x.device)

    def measure(self, state: State) -> dict:
        """The chord angle [deg] of `state` (for reports)."""
        d = self.tip(state.particle_q).numpy()[0].astype(float) - np.asarray(self.origin, float)
        up = np.asarray(self.up, float)
        rise = float(d @ up)
        return {"chord_angle_deg": math.degrees(math.atan2(-rise, float(np.linalg.norm(d - rise * up))))}


_NO_LOSS = Loss()


def _weighted_sum(x: wp.array, weights: wp.array) -> wp.array:
    """sum_i weights_i x_i as a one-element (taped) array."""
    c = wp.zeros(1, dtype=wp.vec3, device=x.device, requires_grad=x.requires_grad)
    wp.launch(kl.eval_weighted_sum, dim=x.shape[0], inputs=[x, weights], outputs=[c], device=x.device)
    return c


def _gather(x: wp.array, ids: wp.array) -> wp.array:
    out = wp.zeros(ids.shape[0], dtype=wp.vec3, device=x.device, requires_grad=x.requires_grad)
    wp.launch(kl.gather_points, dim=ids.shape[0], inputs=[x, ids], outputs=[out], device=x.device)
    return out


def model_grad_arrays(model: Model) -> dict[str, wp.array]:
    """The model's differentiable arrays by name (those with a .grad)."""
    names = ("particle_q", "particle_qd", "particle_mass", "spring_rest_length", "spring_stiffness", "spring_damping", "tri_drag",
             "membrane_stiffness", "membrane_damping", "plate_stiffness", "collider_static_friction", "collider_kinetic_friction")
    return {n: getattr(model, n) for n in names if getattr(model, n, None) is not None and getattr(model, n).requires_grad}


class Rollout:
    """T steps of `solver` at `dt` [s] from an initial state, differentiable with respect to everything it reads.

    Args:
        model: built with ``requires_grad=True``.
        solver: any solver (explicit, symplectic, midpoint, RK4, implicit with CG or Jacobi).
        dt: step [s]; steps: T.
        checkpoint_every: None keeps every state on one tape (memory ~T); an int S keeps every S-th state
            and re-runs segments in the backward pass; ``"auto"`` uses S = ceil(sqrt(T)).
        control: the control of static scenes (default ``model.control(requires_grad=True)``); its
            ``wind`` is the wind parameter. Animated scenes (handles, moving colliders) get a fresh control
            per step that shares this wind.
    """

    def __init__(self, model: Model, solver: SolverBase, *, dt: float, steps: int, checkpoint_every=None, control: Control | None = None):
        if not model.requires_grad:
            raise ValueError("a differentiable rollout needs a model built with requires_grad=True")
        if int(steps) < 1:
            raise ValueError(f"steps must be >= 1, got {steps!r}")
        self.model = model
        self.solver = solver
        self.dt = float(dt)
        self.steps = int(steps)
        if checkpoint_every == "auto":
            checkpoint_every = math.ceil(math.sqrt(self.steps))
        self.segment = self.steps if checkpoint_every is None else max(1, min(int(checkpoint_every), self.steps))
        self.control = control if control is not None else model.control(requires_grad=True)
        self.handle_gradients: dict[str, np.ndarray] = {}
        """Per handle name, d loss / d keyframe translation [per m], shape (keyframes, 3) (after gradient())."""
        self.final_state: State | None = None
        self.peak_states = 0

    def notify_model_changed(self, flags: int) -> None:
        """Model fields changed (:class:`~cloth_warp.model.ModelFlags`): tell the solver (and the passes it
        built), and re-derive the static control's pin targets from new initial positions."""
        self.solver.notify_model_changed(flags)
        if flags & ModelFlags.PARTICLE_INITIAL_STATE:
            wp.copy(self.control.pin_target, self.model.particle_q)
            self.model.update_control(self.control, 0.0, force=True)

    # -- pieces ---------------------------------------------------------------------------------
    def control_at(self, step: int) -> Control:
        """The control of step `step` (which ends at (step + 1) dt)."""
        m = self.model
        if not m.animated:
            return self.control
        c = m.control(requires_grad=False)
        c.wind = self.control.wind
        m.update_control(c, (step + 1) * self.dt, self.dt, force=True)
        if m.handles:
            c.pin_target = wp.clone(c.pin_target, requires_grad=True)
        return c

    def _advance(self, start: int, stop: int, state: State, loss: Loss, out: wp.array, keep: bool):
        """Steps start..stop-1 from `state` (the state at `start`); evaluates the loss at steps in (start, stop]
        (and at 0 when start == 0). Returns the states (all of them when `keep`, else the last) and controls."""
        states, controls = [state], []
        if start == 0 and 0 in loss.steps:
            loss.evaluate(0, state, out)
        for k in range(start, stop):
            nxt = self.model.state(requires_grad=True)
            ctl = self.control_at(k)
            self.solver.step(state, nxt, ctl, self.dt)
            if k + 1 in loss.steps:
                loss.evaluate(k + 1, nxt, out)
            state = nxt
            if keep:
                states.append(nxt)
                controls.append(ctl)
        if not keep:
            states = [state]
        return states, controls

    def zero_grad(self, state0: State | None = None):
        """Zero the gradients a :meth:`gradient` call accumulates into."""
        for a in model_grad_arrays(self.model).values():
            a.grad.zero_()
        if self.control.wind.requires_grad:
            self.control.wind.grad.zero_()
        if state0 is not None:
            state0.particle_q.grad.zero_()
            state0.particle_qd.grad.zero_()

    def forward(self, loss: Loss, state0: State | None = None) -> float:
        """The loss of a rollout, without a tape."""
        state0 = state0 if state0 is not None else self.model.state(requires_grad=True)
        out = wp.zeros(1, dtype=float, device=self.model.device, requires_grad=True)
        states, _ = self._advance(0, self.steps, state0, loss, out, keep=False)
        self.final_state = states[-1]
        loss.end_segment()  # (one segment: the whole rollout)
        return float(out.numpy()[0])

    def gradient(self, loss: Loss, state0: State | None = None, zero: bool = True) -> float:
        """Run forward and backward; returns the loss. Gradients accumulate in the arrays' ``.grad``
        (zeroed first unless `zero` is False)."""
        m = self.model
        state0 = state0 if state0 is not None else m.state(requires_grad=True)
        if zero:
            self.zero_grad(state0)
        self.handle_gradients = {h.name: np.zeros((len(h.keyframes), 3)) for h in m.handles}
        bounds = list(range(0, self.steps, self.segment)) + [self.steps]
        # Forward: keep the state at every segment start (only needed with more than one segment).
        checkpoints = [state0]
        state = state0
        for a, b in zip(bounds[:-2], bounds[1:-1]):
            state = self._advance(a, b, state, _NO_LOSS, None, keep=False)[0][-1]
            checkpoints.append(State(wp.clone(state.particle_q, requires_grad=True), wp.clone(state.particle_qd, requires_grad=True)))
        # Backward: segments in reverse, each under its own tape.
        seed = None
        total = 0.0
        self.peak_states = len(checkpoints) + self.segment
        for s in range(len(bounds) - 2, -1, -1):
            a, b = bounds[s], bounds[s + 1]
            out = wp.zeros(1, dtype=float, device=m.device, requires_grad=True)
            tape = wp.Tape()
            with tape:
                states, controls = self._advance(a, b, checkpoints[s], loss, out, keep=True)
            if s == len(bounds) - 2:
                self.final_state = states[-1]
            total += float(out.numpy()[0])
            loss.end_segment()
            grads = {} if seed is None else {states[-1].particle_q: seed[0], states[-1].particle_qd: seed[1]}
            tape.backward(loss=out, grads=grads)
            self._collect_handle_gradients(a, controls)
            start = states[0]
            if s > 0:
                seed = (wp.clone(start.particle_q.grad), wp.clone(start.particle_qd.grad))
            del tape, states, controls
        return total

    def _collect_handle_gradients(self, start: int, controls: list[Control]):
        m = self.model
        if not m.handles or not controls:
            return
        from .model import keyframe_weights

        for k, ctl in enumerate(controls):
            g = ctl.pin_target.grad.numpy()
            time = (start + k + 1) * self.dt
            for h in m.handles:
                self.handle_gradients[h.name] += np.outer(keyframe_weights(h.keyframes, time), g[h.particles].sum(0))
