"""Shared solver machinery: the step interface and scratch buffers (Provot strain limiting: :mod:`.strain_limit`)."""

from __future__ import annotations

import warp as wp

from ..kernels import forces as kf
from ..model import Control, Model, State
from .strain_limit import DEFAULT_SWEEPS, StrainLimiter


class SolverBase:
    """Common interface: ``step(state_in, state_out, control, dt)``.

    A solver never writes `state_in` or the model. Forward runs may swap two states; taped rollouts keep
    one State per step. Scratch arrays are reused only when nothing is taped (``state_in.requires_grad``
    is False); otherwise every intermediate gets a fresh array so no taped kernel's input is overwritten.

    A step runs three stages: the integrator proper (:meth:`integrate`), Provot strain limiting, then
    collision handling (:class:`~cloth_warp.collision.CollisionHandler`, when the model has colliders or
    self-collision), so the state a step returns is always the collision-resolved one.

    Args:
        model: the model to simulate.
        strain_limit: Provot's maximum strain of structural/shear springs (0.1 = 10 %), None to disable.
        strain_limit_iterations: the most Gauss-Seidel sweeps over all colours per step (default 128).
        strain_limit_tolerance: sweep until no structural/shear spring exceeds the limit by more than this
            strain (checked on the device: eager, captured and taped steps alike); None for exactly
            `strain_limit_iterations` sweeps. Steps left above it are counted in
            ``strain_limiter.read_report()`` (per frame in the Simulator).
        collisions: handle the model's colliders and self-collision (default True).
        collision_rounds: strain-limit / collision passes per step when both are on (default 2).
    """

    name = "base"
    stability: float | None = None  # explicit integrators: the largest stable h omega_max

    def __init__(self, model: Model, *, strain_limit: float | None = 0.1, strain_limit_iterations: int = DEFAULT_SWEEPS,
                 strain_limit_tolerance: float | None = 1.0e-3, collisions: bool = True, collision_rounds: int = 2):
        from ..collision import CollisionHandler

        self.model = model
        self.strain_limiter = (
            StrainLimiter(model, strain_limit, strain_limit_iterations, tolerance=strain_limit_tolerance) if strain_limit else None
        )
        handler = CollisionHandler(model) if collisions else None
        self.collisions = handler if handler is not None and handler.active else None
        if int(collision_rounds) < 1:
            raise ValueError(f"collision_rounds must be >= 1, got {collision_rounds!r}")
        self.collision_rounds = int(collision_rounds)
        self._scratch: dict = {}
        # Per-step solver report (iterative solvers fill these). last_failure names a failure that makes the
        # step's result meaningless ("non-finite residual"), None otherwise.
        self.last_iterations = 0
        self.last_residual = 0.0
        self.converged = True
        self.last_failure: str | None = None

    def notify_model_changed(self, flags: int) -> None:
        """Model fields changed (:class:`~cloth_warp.model.ModelFlags`): refresh what this solver and its passes
        derived from the model when they were built. Everything else is read from the model at every step."""
        if self.strain_limiter is not None:
            self.strain_limiter.notify_model_changed(flags)
        if self.collisions is not None:
            self.collisions.notify_model_changed(flags)

    # -- checkpoints ------------------------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        """What this solver carries from one step to the next, as numpy arrays and scalars ({} when nothing).

        The strain limiter carries nothing (each step sweeps from the integrator's output; its report is
        per step); the collision handler's state is :meth:`CollisionHandler.checkpoint_state
        <cloth_warp.collision.CollisionHandler.checkpoint_state>`. Scratch buffers are written before they are
        read in every step."""
        out = {"name": self.name}
        if self.collisions is not None:
            out.update({f"collisions.{k}": v for k, v in self.collisions.checkpoint_state().items()})
        return out

    def restore_state(self, state: dict) -> None:
        """Inverse of :meth:`checkpoint_state` (on a solver of the same kind built for the same model)."""
        if str(state.get("name", self.name)) != self.name:
            raise ValueError(f"checkpoint of a {state.get('name')} solver, this one is {self.name}")
        if self.collisions is not None:
            self.collisions.restore_state({k[len("collisions."):]: v for k, v in state.items() if k.startswith("collisions.")})

    def scratch(self, key: str, dtype, requires_grad: bool, shape=None) -> wp.array:
        """A work array: reused across steps when not taped, fresh (and differentiable) when taped."""
        shape = self.model.particle_count if shape is None else shape
        if requires_grad:
            return wp.zeros(shape, dtype=dtype, device=self.model.device, requires_grad=True)
        buf = self._scratch.get(key)
        if buf is None:
            buf = wp.zeros(shape, dtype=dtype, device=self.model.device)
            self._scratch[key] = buf
        return buf

    def element_forces(self, x: wp.array, v: wp.array, control: Control, key: str = "") -> wp.array:
        """Scatter every spring's, bend triple's, membrane element's, plate stencil's and triangle's (drag) force into a per-particle
        array [N]. Every integrator reads its forces here."""
        m = self.model
        force = self.scratch("element_force" + key, wp.vec3, x.requires_grad)
        force.zero_()
        dev = m.device
        if m.linear_spring_count:
            wp.launch(kf.eval_spring_forces, dim=m.linear_spring_count,
                      inputs=[m.spring_ends, m.spring_rest_length, m.spring_stiffness, m.spring_damping, x, v],
                      outputs=[force], device=dev)
        if m.spring_count > m.linear_spring_count:
            wp.launch(kf.eval_bending_forces, dim=m.spring_count - m.linear_spring_count,
                      inputs=[m.bend_triples, m.spring_stiffness, m.linear_spring_count, x],
                      outputs=[force], device=dev)
        if m.membrane_count:
            wp.launch(kf.eval_membrane_forces, dim=m.membrane_count,
                      inputs=[m.membrane_vertices, m.membrane_rest_inverse, m.membrane_rest_area, m.membrane_stiffness,
                              m.membrane_damping, x, v], outputs=[force], device=dev)
        if m.plate_count:
            wp.launch(kf.scatter_plate_product, dim=m.plate_count,
                      inputs=[m.plate_offsets, m.plate_points, m.plate_weights, m.plate_stiffness, x, -1.0], outputs=[force], device=dev)
        if m.tri_count:
            wp.launch(kf.eval_drag_forces, dim=m.tri_count,
                      inputs=[m.tri_vertices, m.tri_drag, m.tri_corner_weights, x, v, control.wind], outputs=[force], device=dev)
        return force

    def step(self, state_in: State, state_out: State, control: Control, dt: float):
        """Advance state_in by dt [s] into state_out under control (pins' targets at the step's end)."""
        if not (dt > 0.0):
            raise ValueError(f"time step must be positive, got {dt!r}")
        limiter = self.strain_limiter if self.strain_limiter is not None and self.strain_limiter.active else None
        collide = self.collisions
        if limiter is None and collide is None:
            self.integrate(state_in, state_out.particle_q, state_out.particle_qd, control, dt)
            return
        rg = state_in.requires_grad
        x = self.scratch("x_unlimited", wp.vec3, rg)
        v = self.scratch("v_unlimited", wp.vec3, rg)
        self.integrate(state_in, x, v, control, dt)
        # With both, limiter and collisions alternate: the limiter pulls over-stretched cloth back (possibly
        # into a collider), the collision pass puts it back out; the last word is the collisions'.
        rounds = self.collision_rounds if limiter is not None and collide is not None else 1
        if collide is not None:
            collide.begin_step()
        for r in range(rounds):
            last = r == rounds - 1
            if limiter is not None:
                limited = state_out if collide is None else State(self.scratch(f"x_limited{r}", wp.vec3, rg),
                                                                  self.scratch(f"v_limited{r}", wp.vec3, rg))
                limiter.apply(self, x, v, limited, dt)
                x, v = limited.particle_q, limited.particle_qd
            if collide is not None:
                out = state_out if last else State(self.scratch(f"x_collided{r}", wp.vec3, rg), self.scratch(f"v_collided{r}", wp.vec3, rg))
                collide.apply(state_in.particle_q, x, v, control, dt, out.particle_q, out.particle_qd)
                x, v = out.particle_q, out.particle_qd
        if limiter is not None:
            limiter.record_step()  # what the last round left

    def integrate(self, state_in: State, x_out: wp.array, v_out: wp.array, control: Control, dt: float):
        """The integrator proper (no strain limiting)."""
        raise NotImplementedError
